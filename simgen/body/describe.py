"""A summary of a body model for people: counts, height, joint positions, identity and provenance.

``describe_body`` returns plain Python data (JSON-serialisable) and ``format_body_description``
turns it into the text block that ``simgen body info`` prints.
"""

from __future__ import annotations

import numpy as np

from simgen.body.model import SMPL_JOINT_NAMES, BodyModel
from simgen.errors import InputError

__all__ = ["describe_body", "format_body_description"]

# Meta keys shown as provenance, in this order, when a model has them (the open body's bake and
# the SMPL file loader write different subsets).
_PROVENANCE_KEYS = ("source", "path", "file", "format", "gender", "licence", "license", "anny_version", "seed",
                    "num_samples", "rest_pose", "frame")


def describe_body(model: BodyModel, betas=None) -> dict:
    """Describe ``model`` shaped by ``betas``.

    betas: shape (B',) with B' <= model.num_betas (zero-padded), or None for the mean shape.
    Returns a dict with: name, model_id, hash (SHA-256 hex of the arrays), num_vertices,
    num_faces, num_betas (slots), live_components (indices of non-zero shape components),
    has_pose_correctives, betas (the B values used), height_m (max y - min y of the shaped rest
    body [m]), joints (list of {"name", "parent", "position" [m] (x, y, z)} in SMPL order, rest
    pose) and provenance (selected meta entries).
    """
    b = model.check_betas(np.zeros(model.num_betas) if betas is None else betas)
    if b.shape[0] != 1:
        raise InputError(f"betas must describe one body, shape (B,), got shape {b.shape}")
    verts = model.shaped_vertices(b)[0]
    joints = model.rest_joints(b)[0]
    live = [int(k) for k in range(model.num_betas) if np.any(model.shapedirs[:, :, k] != 0.0)]
    names = SMPL_JOINT_NAMES if len(SMPL_JOINT_NAMES) == joints.shape[0] else [f"joint{j}" for j in range(len(joints))]
    return {
        "name": model.name,
        "model_id": model.model_id,
        "hash": model.hash,
        "num_vertices": model.num_vertices,
        "num_faces": int(model.faces.shape[0]),
        "num_betas": model.num_betas,
        "live_components": live,
        "has_pose_correctives": model.has_pose_correctives,
        "betas": [float(x) for x in b[0]],
        "height_m": float(verts[:, 1].max() - verts[:, 1].min()),
        "joints": [
            {"name": names[j], "parent": (names[int(p)] if p >= 0 else None),
             "position": [float(x) for x in joints[j]]}
            for j, p in enumerate(model.parents)
        ],
        "provenance": {k: model.meta[k] for k in _PROVENANCE_KEYS if k in model.meta},
    }


def format_body_description(desc: dict) -> str:
    """The text block of ``simgen body info`` for a dict from :func:`describe_body`."""
    betas = desc["betas"]
    shape = "mean shape" if not any(betas) else "betas " + ", ".join(
        f"{x:+.2f}" for x in betas[: max(i + 1 for i, x in enumerate(betas) if x)])
    live = desc["live_components"]
    lines = [
        f"Body model {desc['name']!r}  (id {desc['model_id']})",
        f"  vertices            {desc['num_vertices']:,}",
        f"  faces               {desc['num_faces']:,}",
        f"  shape components    {len(live)} live of {desc['num_betas']} slots"
        + (f" (betas {live[0]}..{live[-1]})" if live and live == list(range(live[0], live[-1] + 1)) else
           (f" (betas {', '.join(map(str, live))})" if live else "")),
        f"  pose correctives    {'yes' if desc['has_pose_correctives'] else 'none'}",
        f"  height              {desc['height_m']:.3f} m  ({shape})",
    ]
    for key, value in desc["provenance"].items():
        lines.append(f"  {key.replace('_', ' '):<19} {value}")
    lines.append(f"  hash (sha256)       {desc['hash']}")
    lines.append("  rest joints [m]            x        y        z   parent")
    for joint in desc["joints"]:
        x, y, z = (c if abs(c) >= 5e-4 else 0.0 for c in joint["position"])  # no "-0.000"
        lines.append(f"    {joint['name']:<18} {x:8.3f} {y:8.3f} {z:8.3f}   {joint['parent'] or '-'}")
    return "\n".join(lines)
