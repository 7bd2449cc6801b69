"""The pictures of one simulation for `simgen simulate` and `simgen demo`: a PNG still and an MP4 of
a :class:`simgen.sim.SimulationResult`, framed and labelled by :mod:`simgen.io.render` (its
:func:`~simgen.io.render.follow_cameras`, 1280x720, a legend of garment, shape, motion and frame).

What the video shows: the body in motion from its first frame. Two kinds of frames come before that
and are left out unless ``with_start``:

- the thesis's start protocol (relax, ramp, rest; :mod:`simgen.sim.driver`). The result keeps its
  frames apart from the clip's (``protocol_positions``, ``protocol_phases``, saved as such in the
  .npz) and records the body only for the clip; with ``with_start`` the body is re-posed on the host
  from the same schedule the solver followed (:class:`simgen.sim.protocol.ProtocolSchedule`).
- the clip's lead-in: a clip that starts at the exact rest pose (every procedural clip of the
  library, :mod:`simgen.motion.procedural`) spends its first :data:`LEAD_IN_S` seconds leaving the
  T-pose, arms coming down, so that the protocol's ramp is empty and the cloth sees the arms come
  down as part of the motion. Those output frames are simulated and stay in the .npz and the USD;
  the video starts after them when at least :data:`MIN_SHOWN_S` of the clip remains (else it shows
  every frame). Clips that start in motion (motion capture) have no lead-in.

The legend's frame line counts output frames of the .npz (frame k at clip time k / fps), so a video
frame is found in the data by its number.

The still is the middle frame of the part the video shows of the clip (output frame L + (T - L) // 2,
L the lead-in): in motion, never a start frame, and the same picture as that frame of the video.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["LEAD_IN_S", "MIN_SHOWN_S", "SimulationPictures", "lead_in_frames", "simulation_pictures",
           "protocol_body_vertices"]

#: [s] How long a clip that starts at the exact rest pose takes to leave it: the procedural clips'
#: arms come down from the T-pose over their first 0.9 s (simgen.motion.procedural; a test holds the
#: two equal).
LEAD_IN_S = 0.9
#: [s] The least of the clip the video must keep for the lead-in to be left out.
MIN_SHOWN_S = 0.5


def lead_in_frames(clip, num_frames: int, fps: float) -> int:
    """How many output frames (of ``num_frames`` at ``fps``) the video leaves out at the clip's
    start: round(LEAD_IN_S * fps) when the clip's first pose is the rest pose (every joint rotation
    below 1e-6 rad) and at least MIN_SHOWN_S of output remains after them, else 0."""
    if np.max(np.abs(np.asarray(clip.poses[0], dtype=np.float64))) > 1e-6:
        return 0
    n = int(round(LEAD_IN_S * fps))
    return n if num_frames - n >= MIN_SHOWN_S * fps else 0


def protocol_body_vertices(result, body, clip) -> np.ndarray:
    """The body [m] at the end of each start-protocol frame of ``result``, shape (P, Vb, 3) float32.

    result: a :class:`~simgen.sim.SimulationResult` of ``body`` doing ``clip``; its metadata gives
    the protocol's frame counts and the target betas. The joint rotations, root translation and
    shape are the solver's own targets (:meth:`ProtocolSchedule.body_targets` at the last substep).
    """
    from simgen.rotations import quat_to_axis_angle
    from simgen.sim.protocol import ProtocolSchedule

    meta = result.metadata
    counts = {k: int(meta["config"][f"{k}_frames"]) for k in ("relax", "ramp", "rest")}
    betas = body.check_betas(np.asarray(meta["betas"], dtype=np.float64))
    schedule = ProtocolSchedule([clip], betas, float(result.fps), 1, relax_frames=counts["relax"],
                                ramp_frames=counts["ramp"], rest_frames=counts["rest"], animate_frames=1)
    poses, trans, shapes = [], [], []
    for phase, k in schedule.frames:
        if phase == "animate":
            continue
        quats, tr, b = schedule.body_targets(phase, k)        # (S=1, N=1, ...), quaternions xyzw
        q = np.asarray(quats[-1, 0], dtype=np.float64)
        poses.append(quat_to_axis_angle(np.concatenate([q[:, 3:], q[:, :3]], axis=1)))
        trans.append(tr[-1, 0])
        shapes.append(b[-1, 0])
    if len(poses) != len(result.protocol_positions):
        raise ValueError(f"the schedule has {len(poses)} protocol frames, the result "
                         f"{len(result.protocol_positions)}")
    out = [body.forward(np.asarray(shapes[i:i + 16]), np.asarray(poses[i:i + 16]), np.asarray(trans[i:i + 16]))
           .vertices.astype(np.float32) for i in range(0, len(poses), 16)]
    return np.concatenate(out) if out else np.zeros((0, body.num_vertices, 3), np.float32)


@dataclass
class SimulationPictures:
    """The tracks, legend and frame labels of a simulation's renders (:func:`simulation_pictures`).

    tracks: body and garment, (T', V, 3) each; fps [1/s]; legend: garment, shape, motion;
    labels: T' frame lines of the legend; still: the frame index of the PNG in ``tracks``.
    """

    tracks: list
    fps: float
    legend: dict
    labels: list
    still: int

    def png(self, path) -> Path:
        """Render the still (the same picture as that frame of :meth:`mp4`)."""
        from simgen.io.render import render_frame

        return render_frame(path, self.tracks, frame=self.still, legend=self.legend,
                            frame_label=self.labels[self.still], fps=self.fps)

    def mp4(self, path, progress=None) -> Path:
        """Render every frame; progress(done, total) after each."""
        from simgen.io.render import render_sequence

        return render_sequence(path, self.tracks, fps=self.fps, legend=self.legend, frame_labels=self.labels,
                               progress=progress)


def simulation_pictures(result, body, clip, *, garment: str, with_start: bool = False) -> SimulationPictures:
    """What to render of ``result`` (``body`` doing ``clip``, garment named ``garment``).

    Without ``with_start``: the output frames from the end of the clip's lead-in
    (:func:`lead_in_frames`) on. With it: the start protocol's P frames (labelled "start: PHASE
    k/n"), then every output frame. The still is the middle of the output frames after the lead-in
    either way. Needs ``result.body_vertices`` (``SimulationConfig.record_body``).
    """
    from simgen.io.render import frame_text, scene_legend
    from simgen.io.usd import MeshTrack

    if result.body_vertices is None:
        raise ValueError("the simulation did not record the body (SimulationConfig.record_body)")
    n = result.num_frames
    lead = lead_in_frames(clip, n, result.fps)
    first = 0 if with_start else lead
    body_points, cloth_points = result.body_vertices[first:], result.positions[first:]
    labels = [frame_text(k, n, result.fps) for k in range(first, n)]
    start: list[str] = []
    if with_start and len(result.protocol_positions):
        phases = [str(p) for p in result.protocol_phases]
        body_points = np.concatenate([protocol_body_vertices(result, body, clip), body_points])
        cloth_points = np.concatenate([result.protocol_positions, cloth_points])
        start = [f"start: {p} {phases[:i + 1].count(p)}/{phases.count(p)}" for i, p in enumerate(phases)]
    tracks = [MeshTrack(name="body", points=body_points, faces=result.body_faces, role="body"),
              MeshTrack(name=garment, points=cloth_points, faces=result.faces, role="garment")]
    legend = scene_legend(garment=garment, betas=result.metadata.get("betas"), motion=clip.name)
    still = len(start) + (lead - first) + (n - lead) // 2
    return SimulationPictures(tracks, float(result.fps), legend, start + labels, still)
