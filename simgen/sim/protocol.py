"""The start protocol's schedule: which frames a batched simulation steps and where the body is at
each substep of each (Santesteban's thesis, section 4.3.1; :mod:`simgen.sim.driver` tells the
phases).

Host work only (numpy): :class:`JobSchedule` turns a job's clip and shape into the body targets that
:class:`simgen.sim.frame_runner.FrameRunner` uploads for each frame (each slot of a
:class:`simgen.sim.pool.SimulationPool` follows its own); :class:`ProtocolSchedule` stacks those of
jobs that run in lockstep.
"""

from __future__ import annotations

import numpy as np

from simgen.rotations import quat_slerp

__all__ = ["PHASES", "JobSchedule", "ProtocolSchedule"]

PHASES = ("relax", "ramp", "rest", "animate")


def _identity_quats(k: int) -> np.ndarray:
    """k identity rotations for the 24 joints, wxyz, (k, 24, 4)."""
    q = np.zeros((k, 24, 4))
    q[..., 0] = 1.0
    return q


def _trans_at(clip, times: np.ndarray) -> np.ndarray:
    """Root translation [m] (K, 3) at times [s] (K,), linear between frames, clamped to the clip."""
    t = clip.times
    return np.stack([np.interp(times, t, clip.trans[:, c]) for c in range(3)], axis=1)


class JobSchedule:
    """The frames of one job in order, and the body's joint rotations, root translation and shape at
    the end of every substep of each.

    clip: the job's MotionClip; betas (nb,): its target shape; fps [1/s]: output frame rate;
    substeps S: solver steps per frame; relax/ramp/rest_frames: the protocol's frame counts;
    animate_frames: output frames (more than the clip holds repeat its last pose).

    ``frames`` is the list of (phase, k) in the order they run; output frame 0 of the animation is
    the rest phase's end state and takes no step (:meth:`steps`).
    """

    def __init__(self, clip, betas: np.ndarray, fps: float, substeps: int, *, relax_frames: int,
                 ramp_frames: int, rest_frames: int, animate_frames: int) -> None:
        from simgen.body.warp_lbs import quats_from_simgen
        from simgen.motion.ops import quats_at

        self._xyzw = quats_from_simgen
        S = int(substeps)
        self.substeps = S
        self.ramp_frames = int(ramp_frames)
        self.betas = np.asarray(betas, dtype=np.float64).reshape(-1)                      # (nb,)
        self.frames = ([("relax", k) for k in range(relax_frames)] + [("ramp", k) for k in range(ramp_frames)]
                       + [("rest", k) for k in range(rest_frames)]
                       + [("animate", k) for k in range(animate_frames)])
        self.protocol_frames = int(relax_frames) + int(ramp_frames) + int(rest_frames)
        self.trans0 = clip.trans[0].astype(np.float64)                                     # (3,)
        self.q_first = quats_at(clip, np.array([0.0]))[0]                                  # (24, 4) wxyz
        self.identity = quats_from_simgen(_identity_quats(1))[0].astype(np.float32)       # (24, 4) xyzw
        self.fractions = np.arange(1, S + 1) / S                                           # substep ends
        # Animation targets over the whole clip (one slerp call): (T-1, S, ...).
        frame_dt = 1.0 / float(fps)
        times = ((np.arange(max(animate_frames - 1, 0))[:, None] + self.fractions[None]) * frame_dt).reshape(-1)
        self.anim_quats = (quats_from_simgen(quats_at(clip, np.minimum(times, clip.duration))).astype(np.float32)
                           .reshape(-1, S, 24, 4))
        self.anim_trans = _trans_at(clip, times).astype(np.float32).reshape(-1, S, 3)

    @staticmethod
    def steps(phase: str, k: int) -> bool:
        """Whether frame (phase, k) takes solver steps (animation frame 0 only records the rest state)."""
        return not (phase == "animate" and k == 0)

    def start_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Joint rotations xyzw (24, 4) and root translation [m] (3,) before the first frame: the
        template body at rest, at the clip's first-frame translation."""
        return self.identity, self.trans0

    def targets(self, phase: str, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint rotations xyzw (S, 24, 4), root translation [m] (S, 3) and betas (S, nb) at the ends
        of frame (phase, k)'s substeps."""
        S = self.substeps
        tr = np.broadcast_to(self.trans0[None], (S, 3))
        if phase == "relax":
            return np.broadcast_to(self.identity, (S, 24, 4)), tr, np.zeros((S, len(self.betas)))
        if phase == "ramp":
            u = (k + self.fractions) / self.ramp_frames                                   # 0 -> 1, linear
            q = quat_slerp(_identity_quats(1), self.q_first[None], u[:, None] * np.ones((S, 24)))
            return self._xyzw(q), tr, u[:, None] * self.betas[None]
        full = np.broadcast_to(self.betas[None], (S, len(self.betas)))
        if phase == "rest":
            return np.broadcast_to(self._xyzw(self.q_first)[None], (S, 24, 4)), tr, full
        # animate: output frame k is clip time k / fps; frame 0 is the rest phase's last state.
        return self.anim_quats[k - 1], self.anim_trans[k - 1], full


class ProtocolSchedule:
    """Several jobs in lockstep, all with ``animate_frames`` output frames: their
    :class:`JobSchedule` targets stacked over the instances.

    clips: one MotionClip per instance (N); betas (N, nb): each instance's target shape; the other
    arguments as :class:`JobSchedule`.
    """

    def __init__(self, clips, betas: np.ndarray, fps: float, substeps: int, *, relax_frames: int,
                 ramp_frames: int, rest_frames: int, animate_frames: int) -> None:
        self.betas = np.asarray(betas, dtype=np.float64)                                   # (N, nb)
        self.jobs = [JobSchedule(c, b, fps, substeps, relax_frames=relax_frames, ramp_frames=ramp_frames,
                                 rest_frames=rest_frames, animate_frames=animate_frames)
                     for c, b in zip(clips, self.betas)]
        self.substeps, self.num_instances = int(substeps), len(clips)
        self.frames = self.jobs[0].frames
        self.trans0 = np.stack([j.trans0 for j in self.jobs])                              # (N, 3)

    steps = staticmethod(JobSchedule.steps)

    def start_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Joint rotations xyzw (N, 24, 4) and root translation [m] (N, 3) before the first frame."""
        return np.stack([j.start_pose()[0] for j in self.jobs]), self.trans0

    def body_targets(self, phase: str, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint rotations xyzw (S, N, 24, 4), root translation [m] (S, N, 3) and betas (S, N, nb) at
        the ends of frame (phase, k)'s substeps."""
        q, tr, bt = zip(*(j.targets(phase, k) for j in self.jobs))
        return np.stack(q, axis=1), np.stack(tr, axis=1), np.stack(bt, axis=1)
