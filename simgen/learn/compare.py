"""Side-by-side comparison of a simulated sequence, the model's prediction and LBS, as USD tracks.

Three copies of the posed body are placed along +X (``spacing`` apart, wide enough that they never
overlap): the ground-truth simulation, the model (post-processed) and the LBS baseline. The
prediction and LBS garments are coloured by their per-vertex distance to the simulation (light grey
at 0 through orange to red at ``error_scale`` and beyond); the simulation keeps the garment colour.
"""

from __future__ import annotations

import numpy as np
import torch

from simgen.errors import InputError

__all__ = ["ERROR_SCALE", "error_colors", "compare_tracks"]

#: Error [m] shown in full red.
ERROR_SCALE = 0.04

_STOPS = np.array([[0.0, 0.85, 0.85, 0.85], [0.5, 1.0, 0.62, 0.15], [1.0, 0.80, 0.02, 0.02]])


def error_colors(error, scale: float = ERROR_SCALE) -> np.ndarray:
    """Per-vertex RGB in [0, 1] for errors [m] (any shape) -> shape (..., 3), clipped at ``scale``."""
    t = np.clip(np.asarray(error, dtype=np.float64) / scale, 0.0, 1.0)
    return np.stack([np.interp(t, _STOPS[:, 0], _STOPS[:, k]) for k in (1, 2, 3)], axis=-1).astype(np.float32)


@torch.no_grad()
def compare_tracks(model, data, sequence_id: str, *, frames: int | None = None, error_scale: float = ERROR_SCALE):
    """MeshTracks (body and garment for ground truth, ours, LBS) and a metadata dict for one sequence.

    model: a :class:`~simgen.learn.garment_model.GarmentModel`; data: the
    :class:`~simgen.learn.data.GarmentData` holding ``sequence_id``; frames: only the first N.
    """
    from simgen.io.usd import MeshTrack
    from simgen.learn.garment_model import lbs_baseline

    if sequence_id not in data.sequences:
        close = ", ".join(sorted(data.sequences)[:5])
        raise InputError(f"dataset has no sequence {sequence_id!r} (e.g. {close})")
    s = data.sequences[sequence_id]
    n = s.num_frames if frames is None else min(int(frames), s.num_frames)
    if n < 1:
        raise InputError(f"--frames must be at least 1, got {frames}")
    dev = model.device
    b = torch.as_tensor(s.betas[:n], device=dev)
    p = torch.as_tensor(s.poses[:n], device=dev)
    t = torch.as_tensor(s.trans[:n], device=dev)
    pred = model.predict(b, p, t, s.fps, postprocess=True)
    lbs = lbs_baseline(model.template, b, pred.transforms)
    body_v = model.body(b, p, t)[0].cpu().numpy()
    gt = s.vertices[:n]
    ours, base = pred.vertices.cpu().numpy(), lbs.cpu().numpy()
    err_ours = np.linalg.norm(ours - gt, axis=-1)
    err_lbs = np.linalg.norm(base - gt, axis=-1)
    width = float(np.ptp(np.concatenate([body_v.reshape(-1, 3), gt.reshape(-1, 3)])[:, 0]))
    spacing = max(1.0, 1.15 * width)
    faces_b = model.body.faces.cpu().numpy()
    faces_g = model.template.faces.cpu().numpy()
    tracks = []
    for k, (label, garment, colors) in enumerate((("ground_truth", gt, None),
                                                  ("ours", ours, error_colors(err_ours, error_scale)),
                                                  ("lbs", base, error_colors(err_lbs, error_scale)))):
        offset = np.array([k * spacing, 0.0, 0.0], dtype=np.float32)
        tracks.append(MeshTrack(name=f"body_{label}", points=body_v + offset, faces=faces_b, role="body"))
        tracks.append(MeshTrack(name=f"garment_{label}", points=garment + offset, faces=faces_g, colors=colors,
                                role="garment"))
    meta = {"sequence": sequence_id, "motion": s.motion, "shape_id": str(s.shape_id),
            "betas": [float(x) for x in s.betas[0]], "compare_order": ["ground_truth", "ours", "lbs"],
            "spacing_m": spacing, "error_scale_m": float(error_scale),
            "mean_error_cm": {"ours": float(err_ours.mean() * 100), "lbs": float(err_lbs.mean() * 100)}}
    return tracks, meta, s.fps
