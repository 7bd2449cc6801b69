"""Waistbands: what holds skirts, pants and shorts on the body.

A top or a dress hangs from the shoulders and rests on them. A garment worn round the waist rests
on nothing: a real one is held by its waistband, which is made to the wearer's waist, closed by a
button or an elastic, and kept there by the hips below it and by friction. The simulated body
cannot hold a band that way for every body and motion: skinning without soft tissue pushes the
belly into the thighs in a deep squat, and one band cannot fit the waist of every shape of a
dataset. Measured on the CPU with an elastic band (rest circumference 75% of the body's girth, E h =
600 N/m, gripping by friction): the band held on the mean body, but pants and shorts slid off the
heavy shape (beta 2 = +2) in ``squat`` and the skirt sat 6-10 cm low on the hips of the slim one
(beta 2 = -2) (docs/garments.md, "Waistbands").

So simgen attaches the waistband to the body, as HOOD pins the waist of lower garments: every
vertex within ``width_m`` of the waist opening (along the mesh's edges) is tied by a spring to the
point of the body surface closest to it on the template body at rest (that point's triangle and
barycentric coordinates, and the vertex's height above the triangle along its normal: the band's
ease as the template was made). The point moves with the body's shape, pose and skinning, so the
band stays at the waist while everything below it hangs, swings and collides freely. The springs
are as stiff as lets the garment's own weight pull the band down by ``sag_m`` (1 mm): a stiff tie,
soft enough for the Newton steps to take.

``metadata["waistband"]`` (written by :func:`waistband_metadata` when a template is built):
``opening`` (the opening the band runs along), ``width_m`` [m] and ``sag_m`` [m]. An imported
garment gets one by adding that entry to its JSON.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simgen.errors import InputError

__all__ = ["Waistband", "WAISTBANDS", "Attachment", "waistband_metadata", "band_vertices", "waistband_attachment",
           "triangle_frame_coordinates"]

GRAVITY = 9.81  # [m/s^2]


@dataclass(frozen=True)
class Waistband:
    """A template's waistband recipe: the opening it runs along, its width [m] from that opening
    along the cloth, and the sag [m] of its springs under the garment's weight."""

    opening: str = "waist"
    width: float = 0.03
    sag: float = 1.0e-3


#: The waistband of each template worn round the waist.
WAISTBANDS: dict[str, Waistband] = {"skirt": Waistband(), "pants": Waistband(), "shorts": Waistband()}


@dataclass
class Attachment:
    """Vertices tied to points of the body surface (what the cloth model takes).

    vertices, int (A,): the garment's attached vertices; body_faces, int (A,): the body triangle of
    each one's point; bary (A, 3): the point's barycentric coordinates in it; offset [m] (A, 3): the
    vertex's rest position relative to that point in the triangle's frame (t1 along its first edge,
    n its normal, t2 = n x t1; so the tie is at rest on the template and turns with the triangle);
    stiffness [N/m] (A,): the springs'.
    """

    vertices: np.ndarray
    body_faces: np.ndarray
    bary: np.ndarray
    offset: np.ndarray
    stiffness: np.ndarray

    def __post_init__(self) -> None:
        a = len(self.vertices)
        if not (self.body_faces.shape == (a,) and self.bary.shape == (a, 3) and self.offset.shape == (a, 3)
                and self.stiffness.shape == (a,)):
            raise InputError(f"an attachment of {a} vertices needs {a} body faces, (A, 3) barycentric "
                             "coordinates and offsets, and stiffnesses")
        if not (np.all(np.isfinite(self.offset)) and np.all(self.stiffness > 0)):
            raise InputError("attachment offsets must be finite and stiffnesses > 0")


def _opening_loop(garment, name: str) -> np.ndarray:
    """Vertex indices of the boundary loop of opening ``name`` (matched by its recorded centroid)."""
    from simgen.garment.mesh import boundary_loops

    openings = {o["name"]: o for o in (garment.metadata or {}).get("openings", [])}
    if name not in openings:
        raise InputError(f"garment {garment.name!r}: its waistband runs along opening {name!r}, which its "
                         f"metadata does not list (openings: {', '.join(openings) or 'none'})")
    loops = boundary_loops(garment.faces)
    target = np.asarray(openings[name]["centroid_m"], dtype=np.float64)
    centroids = np.array([garment.vertices[loop].mean(axis=0) for loop in loops])
    return loops[int(np.argmin(np.linalg.norm(centroids - target, axis=1)))]


def triangle_frame_coordinates(vectors, corners) -> np.ndarray:
    """Coordinates (A, 3) of vectors (A, 3) in the frames (t1, n, t2) of triangles with corners
    (A, 3, 3): t1 along the first edge, n the unit normal (counter-clockwise), t2 = n x t1."""
    e1 = corners[:, 1] - corners[:, 0]
    n = np.cross(e1, corners[:, 2] - corners[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t1 = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([np.einsum("ac,ac->a", vectors, t) for t in (t1, n, t2)], axis=1)


def waistband_metadata(band: Waistband) -> dict:
    """The ``metadata["waistband"]`` entry of a recipe."""
    return {"opening": band.opening, "width_m": band.width, "sag_m": band.sag}


def _entry(garment) -> dict | None:
    entry = (garment.metadata or {}).get("waistband")
    if entry is None:
        return None
    where = f"garment {garment.name!r}"
    if not isinstance(entry, dict):
        raise InputError(f"{where}: metadata 'waistband' must be a table, got {type(entry).__name__}")
    for key in ("width_m", "sag_m"):
        value = entry.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:
            raise InputError(f"{where}: waistband field {key!r} must be a number in (0, 1) [m], got {value!r}")
    return entry


def band_vertices(garment) -> np.ndarray:
    """Indices of the garment's waistband vertices (within ``width_m`` of the opening along the
    mesh's edges), empty when it has no waistband."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    from simgen.garment.mesh import unique_edges

    entry = _entry(garment)
    if entry is None:
        return np.zeros(0, dtype=np.int64)
    loop = _opening_loop(garment, str(entry.get("opening", "waist")))
    x, e = garment.vertices, unique_edges(garment.faces)
    n = len(x)
    graph = coo_matrix((np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1), (e[:, 0], e[:, 1])), shape=(n, n))
    distance = dijkstra(graph.tocsr(), directed=False, indices=loop, min_only=True)
    return np.flatnonzero(distance <= float(entry["width_m"]))


def waistband_attachment(garment, body, mass: float) -> Attachment | None:
    """The :class:`Attachment` of the garment's waistband on ``body`` (the model it was made on,
    template at rest), for a garment of ``mass`` [kg]; None when it has no waistband."""
    from simgen.garment.skinning import closest_body_points

    vertices = band_vertices(garment)
    if len(vertices) == 0:
        return None
    entry = _entry(garment)
    points = closest_body_points(garment.vertices[vertices], body)
    corners = body.v_template[body.faces[points.face]]
    offset = triangle_frame_coordinates(garment.vertices[vertices] - np.einsum("ak,akc->ac", points.bary, corners),
                                        corners)
    k = mass * GRAVITY / (len(vertices) * float(entry["sag_m"]))
    return Attachment(vertices=vertices, body_faces=points.face.astype(np.int64), bary=points.bary, offset=offset,
                      stiffness=np.full(len(vertices), k))
