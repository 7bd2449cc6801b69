"""Is the garment on the body? The per-frame measures and the limits ``simgen dataset check`` applies.

A garment that has slid off the body has no penetration and little strain, so those checks pass
it; three measures per frame tell:

- ``body_share``: the share of garment vertices within :data:`ON_BODY_DISTANCE` (5 cm) of the posed
  body's surface;
- ``lbs_offset`` [m]: the median distance of the garment's *support* vertices from their skinned
  (LBS) position: the template carried to the body's shape by the diffused shape blendshape
  (:func:`simgen.garment.shape_offsets`) and posed by linear blend skinning with the garment's
  weights, the LBS baseline of ``simgen garment preview``. The support is the template's top
  :data:`SUPPORT_BAND` (5 cm): the part a garment hangs from, the waistband of a skirt, pants or
  shorts, the neckline and shoulders of a top or a dress;
- ``support_drop`` [m]: the median of how far the support sits *below* its skinned position,
  along the body's own up axis there (the skinned direction of +y): a garment that slides down
  the body (a waistband slipped to the hips, pants at the ankles) drops; cloth lower down that lags
  or rides beside its skinned position (a seat while the thigh swings, a swinging skirt, the chest
  of a shirt while the arms swing) is not support and does not count;
- ``min_height`` [m]: the lowest garment vertex (the floor is y = 0).

The check fails a sequence with a frame where the support has dropped more than
:data:`MAX_SUPPORT_DROP` below its LBS position, fewer than :data:`MIN_BODY_SHARE` of the vertices are on the body, or a
vertex is more than :data:`FLOOR_TOLERANCE` below the floor. The limits lie between what
garments that stayed on reached on the GPU and a waistband pushed down to the hip joints (docs/sim.md,
"Is the garment on the body"; BENCHMARKS.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ON_BODY_DISTANCE", "SUPPORT_BAND", "MIN_BODY_SHARE", "MAX_SUPPORT_DROP", "FLOOR_TOLERANCE",
           "PLACEMENT_KEYS", "GarmentReference", "garment_reference", "placement_row", "placement_rows",
           "placement_problems"]

ON_BODY_DISTANCE = 0.05        # [m] a vertex this close to the body surface is on the body
SUPPORT_BAND = 0.05            # [m] template vertices this close below its top are the support
MIN_BODY_SHARE = 0.25          # [-] fewer vertices on the body than this: the garment is off it
MAX_SUPPORT_DROP = 0.10        # [m] support this far below its LBS position: the garment has slipped
FLOOR_TOLERANCE = 1.0e-3       # [m] a vertex further below the floor has gone through it
PLACEMENT_KEYS = ("body_share", "lbs_offset", "support_drop", "min_height")


@dataclass
class GarmentReference:
    """What the measures need of one garment on one body model (host, float64).

    support, bool (V,): the support vertices; shape_dirs [m], (V, 3, B): the garment's shape
    blendshape (offset per unit beta); skin_joint, int (V, K) and skin_weight (V, K): each vertex's
    nonzero skinning weights, padded with weight 0 (the layout of the body's own LBS kernel).
    """

    support: np.ndarray
    shape_dirs: np.ndarray
    skin_joint: np.ndarray
    skin_weight: np.ndarray

    def rest_vertices(self, template: np.ndarray, betas: np.ndarray) -> np.ndarray:
        """The template [m] (V, 3) on bodies of shape betas (N, B') -> (N, V, 3)."""
        b = np.zeros((len(betas), self.shape_dirs.shape[2]))
        betas = np.asarray(betas, dtype=np.float64).reshape(len(betas), -1)
        b[:, :betas.shape[1]] = betas[:, :b.shape[1]]
        return template[None] + np.einsum("vcb,nb->nvc", self.shape_dirs, b)


_CACHE: dict = {}


def _reference(garment, body, device) -> GarmentReference:
    from simgen.garment.skinning import shape_offsets

    v = garment.vertices
    support = v[:, 1] > v[:, 1].max() - SUPPORT_BAND
    dirs = (np.moveaxis(shape_offsets(v, body, np.eye(body.num_betas), device=device), 0, 2) if body.num_betas
            else np.zeros((len(v), 3, 1)))
    w = garment.skin_weights
    nonzero = w != 0.0
    k = max(int(nonzero.sum(axis=1).max()), 1)
    order = np.argsort(~nonzero, axis=1, kind="stable")[:, :k]
    return GarmentReference(support=support, shape_dirs=dirs, skin_joint=order.astype(np.int32),
                            skin_weight=np.take_along_axis(w, order, axis=1))


def garment_reference(garment, body, device: str | None = "cpu") -> GarmentReference:
    """The :class:`GarmentReference` of ``garment`` on ``body``, its body queries on the Warp
    ``device`` (cached whatever the device: the shape blendshape of a dress takes seconds on the CPU)."""
    key = (garment.name, hash(garment.vertices.tobytes()), hash(garment.skin_weights.tobytes()), body.hash)
    if key not in _CACHE:
        if len(_CACHE) >= 8:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = _reference(garment, body, device)
    return _CACHE[key]


def placement_rows(positions, lbs_positions, lbs_up, distance_to_body, support) -> dict:
    """The measures of K frames (or instances) of one garment at once: positions, lbs_positions [m]
    (K, V, 3) and lbs_up (K, V, 3) (the skinned +y direction at each vertex, any length), the
    vertices' unsigned distance to the posed body [m] (K, V) (anything >= ON_BODY_DISTANCE where
    farther), support bool (V,). Returns each of :data:`PLACEMENT_KEYS` as (K,) float64:
    body_share, lbs_offset [m], support_drop [m], min_height [m]."""
    # The support vertices are taken out before anything is converted to float64 (a pool hands over
    # all of its slots' vertices in float32 every frame; the support is a small part of them).
    x = np.asarray(positions)
    idx = np.flatnonzero(support)
    d = x[:, idx].astype(np.float64) - np.asarray(lbs_positions)[:, idx]
    up = np.asarray(lbs_up)[:, idx].astype(np.float64)
    up_length = np.maximum(np.sqrt(np.einsum("kij,kij->ki", up, up)), 1e-12)
    none = np.zeros(len(x))
    return dict(body_share=np.mean(np.asarray(distance_to_body) < ON_BODY_DISTANCE, axis=1),
                lbs_offset=np.median(np.sqrt(np.einsum("kij,kij->ki", d, d)), axis=1) if len(idx) else none,
                support_drop=np.median(-np.einsum("kij,kij->ki", d, up) / up_length, axis=1) if len(idx) else none,
                min_height=x[:, :, 1].min(axis=1).astype(np.float64))


def placement_row(positions, lbs_positions, lbs_up, distance_to_body, support) -> dict:
    """The measures of one frame (:func:`placement_rows` of positions, lbs_positions, lbs_up (V, 3),
    distance_to_body (V,)), each a float."""
    rows = placement_rows(np.asarray(positions)[None], np.asarray(lbs_positions)[None], np.asarray(lbs_up)[None],
                          np.asarray(distance_to_body)[None], support)
    return {k: float(v[0]) for k, v in rows.items()}


def placement_problems(stats: dict, floor: float | None = 0.0, frames=None) -> list[str]:
    """Sentences naming the first frame where each limit is broken, for per-frame ``stats`` (the
    :data:`PLACEMENT_KEYS` arrays over frames); empty when the garment stays on the body.

    floor: the floor's height [m], or None (no floor). frames: the frame numbers the stats were
    measured on (default 0, 1, ...), for a check that measures every n-th frame."""
    out = []
    share, drop, low = (np.asarray(stats[k], dtype=np.float64) for k in ("body_share", "support_drop", "min_height"))
    frames = np.arange(len(drop)) if frames is None else np.asarray(frames)

    def where(bad):
        return f"on {len(bad)} of {len(frames)} frames from frame {int(frames[bad[0]])}"

    bad = np.flatnonzero(drop > MAX_SUPPORT_DROP)
    if len(bad):
        out.append(f"the garment slipped: its support sits {100 * drop.max():.1f} cm below its skinned position "
                   f"(limit {100 * MAX_SUPPORT_DROP:g} cm) {where(bad)}")
    bad = np.flatnonzero(share < MIN_BODY_SHARE)
    if len(bad):
        out.append(f"the garment left the body: {100 * share.min():.0f}% of its vertices within "
                   f"{100 * ON_BODY_DISTANCE:g} cm of it (limit {100 * MIN_BODY_SHARE:g}%) {where(bad)}")
    if floor is not None:
        bad = np.flatnonzero(low < floor - FLOOR_TOLERANCE)
        if len(bad):
            out.append(f"cloth {1e3 * (floor - low.min()):.1f} mm below the floor {where(bad)}")
    return out
