"""The start protocol's schedule: which frames a batched simulation steps and where the body is at
each substep of each (Santesteban's thesis, section 4.3.1; :mod:`simgen.sim.driver` tells the
phases).

Host work only (numpy): :class:`ProtocolSchedule` turns the jobs' clips and shapes into the body
targets that :class:`simgen.sim.frame_runner.FrameRunner` uploads for each frame.
"""

from __future__ import annotations

import numpy as np

from simgen.rotations import quat_slerp

__all__ = ["PHASES", "ProtocolSchedule"]

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


class ProtocolSchedule:
    """The frames of a batch in order, and the body's joint rotations, root translation and shape at
    the end of every substep of each.

    clips: one MotionClip per instance (N); betas (N, nb): each instance's target shape; fps [1/s]:
    output frame rate; substeps S: solver steps per frame; relax/ramp/rest_frames: the protocol's
    frame counts; animate_frames: output frames of the longest job (shorter clips hold their last
    pose).

    ``frames`` is the list of (phase, k) in the order they run; output frame 0 of the animation is
    the rest phase's end state and takes no step (:meth:`steps`).
    """

    def __init__(self, clips, betas: np.ndarray, fps: float, substeps: int, *, relax_frames: int,
                 ramp_frames: int, rest_frames: int, animate_frames: int) -> None:
        from simgen.body.warp_lbs import quats_from_simgen
        from simgen.motion.ops import quats_at

        self._xyzw = quats_from_simgen
        S, N = int(substeps), len(clips)
        self.substeps, self.num_instances = S, N
        self.ramp_frames = int(ramp_frames)
        self.betas = np.asarray(betas, dtype=np.float64)                                   # (N, nb)
        self.frames = ([("relax", k) for k in range(relax_frames)] + [("ramp", k) for k in range(ramp_frames)]
                       + [("rest", k) for k in range(rest_frames)]
                       + [("animate", k) for k in range(animate_frames)])
        self.trans0 = np.stack([c.trans[0].astype(np.float64) for c in clips])              # (N, 3)
        self.q_first = np.stack([quats_at(c, np.array([0.0]))[0] for c in clips])          # (N, 24, 4) wxyz
        self.identity = quats_from_simgen(_identity_quats(1))[0].astype(np.float32)        # (24, 4) xyzw
        self.fractions = np.arange(1, S + 1) / S                                           # substep ends
        # Animation targets of every job over its whole clip (one slerp call each): (T-1, S, ...).
        frame_dt = 1.0 / float(fps)
        times = ((np.arange(max(animate_frames - 1, 0))[:, None] + self.fractions[None]) * frame_dt).reshape(-1)
        self.anim_quats = [quats_from_simgen(quats_at(c, np.minimum(times, c.duration))).astype(np.float32)
                           .reshape(-1, S, 24, 4) for c in clips]
        self.anim_trans = [_trans_at(c, times).astype(np.float32).reshape(-1, S, 3) for c in clips]

    @staticmethod
    def steps(phase: str, k: int) -> bool:
        """Whether frame (phase, k) takes solver steps (animation frame 0 only records the rest state)."""
        return not (phase == "animate" and k == 0)

    def start_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Joint rotations xyzw (N, 24, 4) and root translation [m] (N, 3) before the first frame:
        the template body at rest, at each clip's first-frame translation."""
        N = self.num_instances
        return np.broadcast_to(self.identity, (N, 24, 4)), self.trans0

    def body_targets(self, phase: str, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint rotations xyzw (S, N, 24, 4), root translation [m] (S, N, 3) and betas (S, N, nb) at
        the ends of frame (phase, k)'s substeps."""
        S, N = self.substeps, self.num_instances
        nb = self.betas.shape[1]
        tr = np.broadcast_to(self.trans0[None], (S, N, 3))
        if phase == "relax":
            return np.broadcast_to(self.identity, (S, N, 24, 4)), tr, np.zeros((S, N, nb))
        if phase == "ramp":
            u = (k + self.fractions) / self.ramp_frames                                   # 0 -> 1, linear
            q = quat_slerp(_identity_quats(1)[None], self.q_first[None], u[:, None, None] * np.ones((S, N, 24)))
            return self._xyzw(q), tr, u[:, None, None] * self.betas[None]
        full = np.broadcast_to(self.betas[None], (S, N, nb))
        if phase == "rest":
            q = self._xyzw(self.q_first)
            return np.broadcast_to(q[None], (S, N, 24, 4)), tr, full
        # animate: output frame k is clip time k / fps; frame 0 is the rest phase's last state.
        return (np.stack([a[k - 1] for a in self.anim_quats], axis=1),
                np.stack([a[k - 1] for a in self.anim_trans], axis=1), full)
