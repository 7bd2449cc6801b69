"""Body parts (torso, arms, legs) from SMPL's skinning weights, for collision where the body meets itself.

A skinned body without pose correctives intersects itself when limbs press against it: the arms
sink into the torso in the clips' rest poses, the thighs into each other at the crotch. Cloth
caught there cannot be outside both parts. The solver's contact keeps such cloth on the part it
belongs to (the part rule of :mod:`simgen.body.surface_query`); this module says which part that is, for body
vertices and faces (from the body's weights) and for garment vertices (from the garment's
skinning weights, which follow the same joints).

A face of one part lies at a *seam* of another where the body surface runs continuously from one
to the other (the shoulder, the hip): within ``seam_width`` of the other part along the surface.
There the two parts are one surface, not two sheets pressed together, and contact must not tell
them apart; :func:`face_part_masks` marks such faces as belonging to both.
"""

from __future__ import annotations

import numpy as np

from simgen.body.model import NUM_JOINTS, SMPL_JOINT_NAMES
from simgen.errors import InputError

__all__ = ["BODY_PARTS", "JOINT_PARTS", "DEFAULT_SEAM_WIDTH", "vertex_parts", "face_parts", "face_part_masks"]

BODY_PARTS = ("torso", "left_arm", "right_arm", "left_leg", "right_leg")

_PART_JOINTS = {
    "torso": ("pelvis", "spine1", "spine2", "spine3", "neck", "left_collar", "right_collar", "head"),
    "left_arm": ("left_shoulder", "left_elbow", "left_wrist", "left_hand"),
    "right_arm": ("right_shoulder", "right_elbow", "right_wrist", "right_hand"),
    "left_leg": ("left_hip", "left_knee", "left_ankle", "left_foot"),
    "right_leg": ("right_hip", "right_knee", "right_ankle", "right_foot"),
}

# JOINT_PARTS[j]: index into BODY_PARTS of SMPL joint j.
JOINT_PARTS = np.array([next(p for p, name in enumerate(BODY_PARTS) if joint in _PART_JOINTS[name])
                        for joint in SMPL_JOINT_NAMES], dtype=np.int32)

# [m] along the surface: wide enough to cover the shoulder's and the hip's transition between
# parts, narrow next to the distance between two sheets that press together (arm on torso side).
DEFAULT_SEAM_WIDTH = 0.03


def vertex_parts(weights) -> np.ndarray:
    """Body part of each vertex: the part with the largest summed skinning weight.

    weights: (V, 24) SMPL skinning weights (body or garment). Returns (V,) int32 indices into
    :data:`BODY_PARTS`.
    """
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != NUM_JOINTS:
        raise InputError(f"skinning weights must have shape (V, {NUM_JOINTS}), got {w.shape}")
    per_part = np.zeros((len(w), len(BODY_PARTS)))
    np.add.at(per_part.T, JOINT_PARTS, w.T)
    return per_part.argmax(axis=1).astype(np.int32)


def face_parts(weights, faces) -> np.ndarray:
    """Body part of each face (the part of the summed weights of its three vertices), (F,) int32."""
    faces = np.asarray(faces, dtype=np.int64)
    w = np.asarray(weights, dtype=np.float64)
    return vertex_parts(w[faces[:, 0]] + w[faces[:, 1]] + w[faces[:, 2]])


def face_part_masks(vertices, faces, parts, *, seam_width: float = DEFAULT_SEAM_WIDTH) -> np.ndarray:
    """Per face, the bit mask of the parts it belongs to for contact: bit p is set if the face is of
    part p or lies within ``seam_width`` [m] of a face of part p along the surface (face-adjacency
    graph, centroid-to-centroid distances).

    vertices [m] (V, 3), faces (F, 3), parts (F,) from :func:`face_parts`. Returns (F,) int32.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    parts = np.asarray(parts, dtype=np.int64)
    if not (isinstance(seam_width, (int, float)) and np.isfinite(seam_width) and seam_width >= 0):
        raise InputError(f"seam_width must be a finite number >= 0, got {seam_width!r}")
    centroids = v[f].mean(axis=1)
    # Faces sharing an edge: sort each face's three edges and pair equal keys.
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    owner = np.tile(np.arange(len(f)), 3)
    key = edges[:, 0] * (len(v) + 1) + edges[:, 1]
    order = np.argsort(key, kind="stable")
    same = key[order[1:]] == key[order[:-1]]
    a, b = owner[order[:-1]][same], owner[order[1:]][same]
    length = np.linalg.norm(centroids[a] - centroids[b], axis=1)
    graph = coo_matrix((np.r_[length, length], (np.r_[a, b], np.r_[b, a])), shape=(len(f), len(f))).tocsr()
    mask = np.zeros(len(f), dtype=np.int64)
    for p in np.unique(parts):
        sources = np.flatnonzero(parts == p)
        dist = dijkstra(graph, indices=sources, min_only=True, limit=seam_width * 1.0001)
        mask[dist <= seam_width] |= 1 << int(p)
    return mask.astype(np.int32)
