"""What the viewer measures on a :class:`~simgen.view.sources.Scene`: per-vertex colour fields and
the per-frame physics terms. Every measure comes from the package that owns it; nothing is
re-implemented here.

Fields (one value per garment vertex and frame; :data:`FIELDS`):

    error     [m]  distance to the reference track's vertex (ground truth), where the scene has one
    strain    [-]  largest principal stretch - 1 of the triangles around the vertex (mean), from the
                   membrane's Green strain G (:func:`simgen.physics.green_strain`): sqrt(1 + 2 max eig G) - 1
    distance  [m]  signed distance to the posed body, < 0 inside (:func:`simgen.body.surface.project_to_surface`,
                   the Warp body-surface query, winding-number sign)

Colours: error and strain on :func:`simgen.learn.compare.error_colors`' scale (light grey at 0,
red at ``scale`` and beyond: the colours of ``export usd --compare``), distance on a diverging map
(red inside, white on the surface, blue at ``scale`` and farther out).

Terms: :func:`frame_terms` runs :func:`simgen.physics.evaluate_sequence` on every track (strain,
bending, gravity, inertia, collision, potential [J per frame]).
"""

from __future__ import annotations

import numpy as np

__all__ = ["FIELDS", "FIELD_UNITS", "DEFAULT_SCALES", "available_fields", "vertex_error", "vertex_strain",
           "body_distance", "field_colors", "frame_terms", "TERMS"]

FIELDS = ("none", "error", "strain", "distance")
FIELD_UNITS = {"error": "m", "strain": "-", "distance": "m"}
#: Value shown in full colour, per field (error: the compare USD's 4 cm).
DEFAULT_SCALES = {"error": 0.04, "strain": 0.10, "distance": 0.02}
#: The energies of :func:`simgen.physics.evaluate_sequence` the plot offers [J per frame].
TERMS = ("potential", "strain", "bending", "gravity", "inertia", "collision")


def available_fields(scene) -> list[str]:
    """The fields the scene supports: error needs a reference track, strain a rest shape."""
    return [f for f in FIELDS if (f != "error" or scene.reference) and (f != "strain" or scene.rest is not None)]


def vertex_error(scene, label: str, frame: int) -> np.ndarray:
    """Per-vertex distance [m] (V,) of track ``label`` to the reference track at ``frame``."""
    a = scene.track(label).positions[frame]
    b = scene.track(scene.reference).positions[frame]
    return np.linalg.norm(a.astype(np.float64) - b, axis=-1)


def vertex_strain(positions, rest) -> np.ndarray:
    """Largest principal stretch - 1 [-] per vertex (V,): the mean over its triangles.

    positions [m] (V, 3); rest: the garment's :class:`simgen.physics.ClothRest`.
    """
    import torch

    from simgen.physics import green_strain

    with torch.no_grad():
        g = green_strain(torch.as_tensor(np.asarray(positions), dtype=rest.dtype), rest)
        stretch = torch.sqrt(torch.clamp(1.0 + 2.0 * torch.linalg.eigvalsh(g)[..., -1], min=0.0)) - 1.0
    faces = rest.faces.cpu().numpy()
    total = np.zeros(rest.num_vertices)
    count = np.zeros(rest.num_vertices)
    for k in range(3):
        np.add.at(total, faces[:, k], stretch.cpu().numpy())
        np.add.at(count, faces[:, k], 1.0)
    return total / np.maximum(count, 1.0)


def body_distance(positions, body_vertices, body_faces) -> np.ndarray:
    """Signed distance [m] (V,) of garment vertices [m] (V, 3) to the posed body [m] (Vb, 3)."""
    from simgen.body.surface import project_to_surface

    return project_to_surface(positions, body_vertices, body_faces, sign="winding").signed_distance


def field_colors(name: str, values: np.ndarray, scale: float) -> np.ndarray:
    """RGB in [0, 1] (V, 3) of a field's values (module doc), full colour at ``scale`` (> 0)."""
    from simgen.learn.compare import error_colors

    if name in ("error", "strain"):
        return error_colors(np.maximum(values, 0.0), scale)
    import matplotlib

    t = np.clip(0.5 + 0.5 * np.asarray(values) / scale, 0.0, 1.0)
    return matplotlib.colormaps["RdBu"](t)[:, :3].astype(np.float32)


def frame_terms(scene, progress=None) -> dict[str, dict[str, np.ndarray]]:
    """{track label: {column: (F,) values}} of :func:`simgen.physics.evaluate_sequence` (energies in
    J per frame, inertia NaN on frames 0 and 1); {} when the scene has no rest shape or material.

    progress(done_frames, total_frames), over all tracks, after every chunk of frames; an exception
    it raises stops the computation (the viewer cancels this way).
    """
    import torch

    from simgen.params import ContactParams
    from simgen.physics import BodySurface, ClothRest, evaluate_sequence

    if scene.rest is None or scene.material is None:
        return {}
    rest = ClothRest.from_mesh(scene.rest, scene.garment_faces, scene.material, dtype=torch.float64)
    surface = BodySurface(scene.body_faces, scene.body_vertices[0])
    F, total = scene.num_frames, scene.num_frames * len(scene.tracks)
    out = {}
    for k, track in enumerate(scene.tracks):
        def step(done: int, _frames: int, before: int = k * F) -> None:
            progress(before + done, total)

        report = evaluate_sequence(track.positions, scene.body_vertices, rest, surface, scene.fps,
                                   contact_params=scene.contact or ContactParams(), name=track.label,
                                   progress=step if progress is not None else None)
        out[track.label] = report.values
    return out
