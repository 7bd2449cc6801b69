"""Soft-tissue sequences as USD and MP4: the posed body with Delta, coloured by |Delta| (thesis Figs.
3.1, 3.6 and 3.8 colour the displacement's magnitude the same way).

``simgen export softtissue --data STORE --sequence ID --out DIR [--model DIR]``: the ground truth
and, with a trained SoftSMPL, its prediction beside it (+X), each vertex coloured from grey (0)
through orange to red (``scale``, 2 cm by default).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from simgen.errors import InputError

__all__ = ["softtissue_tracks", "export_softtissue", "MAGNITUDE_SCALE"]

MAGNITUDE_SCALE = 0.02   # [m] |Delta| drawn in the colour map's top colour


def _posed(body, seq, delta) -> np.ndarray:
    import torch

    from simgen.body.torch_lbs import TorchBody
    from simgen.learn.softtissue.dyna import posed_vertices

    tb = TorchBody(body, dtype=torch.float64)
    b = torch.as_tensor(body.check_betas(np.asarray(seq.betas).reshape(-1)[:body.num_betas])[0])
    with torch.no_grad():
        x = posed_vertices(tb, torch.as_tensor(np.asarray(delta, dtype=np.float64)), b,
                           torch.as_tensor(seq.poses, dtype=torch.float64).reshape(-1, 72),
                           torch.as_tensor(seq.trans, dtype=torch.float64).reshape(-1, 3))
    return x.numpy().astype(np.float32)


def softtissue_tracks(body, seq, predicted: np.ndarray | None = None, *, scale: float = MAGNITUDE_SCALE):
    """MeshTracks of one :class:`SoftTissueSequence`: ``body_ground_truth`` (posed with its Delta) and,
    given ``predicted`` Delta (T, V, 3) [m], ``body_predicted`` beside it along +X; each coloured by
    |Delta| clipped at ``scale`` [m]. Returns (tracks, metadata)."""
    from simgen.io.usd import MeshTrack
    from simgen.learn.compare import error_colors

    shown = [("ground_truth", np.asarray(seq.displacements))]
    if predicted is not None:
        shown.append(("predicted", np.asarray(predicted)))
    tracks, spacing = [], None
    for k, (label, delta) in enumerate(shown):
        points = _posed(body, seq, delta)
        if spacing is None:
            spacing = max(1.0, 1.15 * float(np.ptp(points[..., 0])))
        points = points + np.array([k * spacing, 0.0, 0.0], dtype=np.float32)
        colors = error_colors(np.linalg.norm(delta, axis=-1), scale)
        tracks.append(MeshTrack(name=f"body_{label}", points=points, faces=body.faces, colors=colors, role="body"))
    meta = {"sequence": seq.name, "motion": seq.motion, "subject": seq.subject,
            "betas": [float(b) for b in seq.betas], "colour_scale_m": float(scale), "spacing_m": float(spacing),
            "shown": [label for label, _ in shown],
            "peak_cm": {label: float(100 * np.linalg.norm(d, axis=-1).max()) for label, d in shown}}
    return tracks, meta


def export_softtissue(data, sequence: str, out_dir, *, body, model=None, usd: bool = True, mp4: bool = True,
                      frames: int | None = None, scale: float = MAGNITUDE_SCALE, size=(1280, 720),
                      progress=None) -> dict:
    """Write OUT_DIR/<sequence>.usdc and/or .mp4 of one sequence of ``data`` (:class:`SoftTissueData`)
    posed on ``body``; with ``model`` (a loaded SoftSMPL) its prediction beside the ground truth.
    frames: only the first N. Returns {"usd": path|None, "mp4": path|None, "meta": {...}}."""
    from dataclasses import replace

    seq = next((s for s in data.sequences if s.name == sequence), None)
    if seq is None:
        names = [s.name for s in data.sequences]
        raise InputError(f"no sequence {sequence!r} in {data.source} (it has {', '.join(names[:8])}"
                         f"{', ...' if len(names) > 8 else ''})")
    if frames is not None:
        seq = replace(seq, poses=seq.poses[:frames], trans=seq.trans[:frames],
                      displacements=seq.displacements[:frames])
    predicted = None
    if model is not None:
        predicted = model.predict(seq.betas, seq.poses, seq.trans, seq.fps).cpu().numpy()
    tracks, meta = softtissue_tracks(body, seq, predicted, scale=scale)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"usd": None, "mp4": None, "meta": meta}
    if usd:
        from simgen.io.usd import write_usd

        paths["usd"] = write_usd(out / f"{sequence}.usdc", tracks, fps=seq.fps,
                                 metadata={"source": str(data.source), **meta})
    if mp4:
        from simgen.io.render import render_sequence, scene_legend

        legend = {"sequence": sequence, **scene_legend(betas=seq.betas, motion=seq.motion),
                  "colour": f"displacement, grey 0 to red {100 * scale:g} cm",
                  "shown": " and ".join(meta["shown"])}
        paths["mp4"] = render_sequence(out / f"{sequence}.mp4", tracks, fps=seq.fps, size=size, legend=legend,
                                       progress=progress)
    return paths
