"""Side-by-side comparison of a simulated sequence and garment predictions, as USD tracks.

Copies of the posed body are placed along +X (``spacing`` apart, wide enough that they never
overlap): the ground-truth simulation first, then one per prediction. Predicted garments are
coloured by their per-vertex distance to the simulation (light grey at 0 through orange to red at
``error_scale`` and beyond); the simulation keeps the garment colour.

:func:`side_by_side_tracks` places any number of predictions; :func:`compare_tracks` is the
three-copy comparison of ``simgen export usd --compare`` (simulation, the model post-processed,
LBS); ``simgen eval compare`` places every compared model and LBS.
"""

from __future__ import annotations

import numpy as np
import torch

from simgen.errors import InputError

__all__ = ["ERROR_SCALE", "error_colors", "side_by_side_tracks", "compare_tracks"]

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
    :class:`~simgen.learn.data.GarmentData` holding ``sequence_id``; frames: only the first N. The
    tracks come from :func:`side_by_side_tracks` with the predictions "ours" and "lbs".
    """
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
    tracks, meta = side_by_side_tracks(body_v, model.body.faces.cpu().numpy(), model.template.faces.cpu().numpy(),
                                       s.vertices[:n], {"ours": pred.vertices.cpu().numpy(), "lbs": lbs.cpu().numpy()},
                                       error_scale=error_scale)
    meta = {"sequence": sequence_id, "motion": s.motion, "shape_id": str(s.shape_id),
            "betas": [float(x) for x in s.betas[0]], **meta}
    return tracks, meta, s.fps


def side_by_side_tracks(body_vertices, body_faces, garment_faces, ground_truth, predictions: dict, *,
                        error_scale: float = ERROR_SCALE, spacing: float | None = None):
    """MeshTracks of the simulation and N predictions side by side, and a metadata dict.

    body_vertices [m] (T, Vb, 3); body_faces (Fb, 3); garment_faces (F, 3); ground_truth [m]
    (T, V, 3); predictions: {name: garment [m] (T, V, 3)} in display order (names are USD prim
    name parts: letters, digits, '_'); spacing [m] between copies along +X (default: 1.15 x the
    scene's width, at least 1 m). Tracks: body_<name> and garment_<name> for "ground_truth" and
    each prediction, the predictions coloured by their per-vertex error (clipped at error_scale [m]).
    Metadata: compare_order, spacing_m, error_scale_m, mean_error_cm {name: [cm]}.
    """
    from simgen.io.usd import MeshTrack

    gt = np.asarray(ground_truth)
    body_v = np.asarray(body_vertices)
    errors = {name: np.linalg.norm(np.asarray(x) - gt, axis=-1) for name, x in predictions.items()}
    if spacing is None:
        width = float(np.ptp(np.concatenate([body_v.reshape(-1, 3), gt.reshape(-1, 3)])[:, 0]))
        spacing = max(1.0, 1.15 * width)
    tracks = []
    order = [("ground_truth", gt, None)] + [(name, np.asarray(x), error_colors(errors[name], error_scale))
                                            for name, x in predictions.items()]
    for k, (label, garment, colors) in enumerate(order):
        offset = np.array([k * spacing, 0.0, 0.0], dtype=np.float32)
        tracks.append(MeshTrack(name=f"body_{label}", points=body_v + offset, faces=body_faces, role="body"))
        tracks.append(MeshTrack(name=f"garment_{label}", points=garment + offset, faces=garment_faces, colors=colors,
                                role="garment"))
    meta = {"compare_order": [label for label, _, _ in order], "spacing_m": float(spacing),
            "error_scale_m": float(error_scale),
            "mean_error_cm": {name: float(e.mean() * 100) for name, e in errors.items()}}
    return tracks, meta
