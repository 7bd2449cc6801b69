"""How well a broad-phase tree fits a garment's edge boxes: node boxes tested per query; prints JSON.

    python scripts/bvh_quality.py --garment tshirt --instances 64

The cloth's broad-phase trees (self-contact, impact filter) hold every instance of a batch, each
shifted onto the lattice of :func:`simgen.sim.warp_toolkit.instance_offsets` (50 m apart). Warp's
CUDA default, the LBVH, orders primitives by 10-bit Morton codes of their centres normalised over
the bounds of all of them: over a lattice 350 m wide a code cell is 0.34 m across x and y, so one
garment falls into a handful of cells and its tree sorts it mostly by depth. This script replays
both trees on one instance's edge boxes (each edge's box swept by a 1 mm random motion, padded
0.1 mm, as the impact filter's are) in numpy and counts, for every edge's own box as a query, the
node boxes the traversal tests:

- ``radix_own_bounds``: Karras's radix tree over Morton codes normalised over the garment alone
  (the LBVH of one instance);
- ``radix_lattice_bounds``: the same codes normalised over the lattice of ``--instances`` (the
  LBVH of a batch);
- ``median_split``: a top-down split at the median centre along the longest axis of the node's
  bounds (Warp's host "median" build; the simulation uses its "sah" build, which places splits by
  the surface-area cost instead and is not emulated here).

Traversal work per query is proportional to these counts; the pair tests after it are the same.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

MORTON_BITS = 10     # per axis, as Warp's CUDA LBVH


def edge_boxes(garment: str, motion: float = 1.0e-3, pad: float = 1.0e-4, seed: int = 0):
    """Swept, padded boxes of one garment's edges: lower, upper [m], (E, 3) each."""
    from simgen.garment import load_garment
    from simgen.garment.mesh import unique_edges

    g = load_garment(garment)
    x0 = np.asarray(g.vertices, dtype=np.float64)
    x1 = x0 + np.random.default_rng(seed).normal(scale=motion, size=x0.shape)
    e = unique_edges(np.asarray(g.faces))
    ends = np.stack([x0[e[:, 0]], x1[e[:, 0]], x0[e[:, 1]], x1[e[:, 1]]])
    return ends.min(axis=0) - pad, ends.max(axis=0) + pad


def morton(centres: np.ndarray, lower: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """30-bit Morton codes (E,) of box centres [m], (E, 3), normalised over [lower, lower + extent
    + 0.1 mm] as Warp's CUDA LBVH does (warp/native/bvh.cu, morton3: z in each triple's top bit)."""
    q = np.clip(((centres - lower) / (extent + 1.0e-4) * 2 ** MORTON_BITS).astype(np.int64),
                0, 2 ** MORTON_BITS - 1)
    code = np.zeros(len(q), dtype=np.int64)
    for b in range(MORTON_BITS):
        for axis in range(3):
            code |= ((q[:, axis] >> b) & 1) << (3 * b + axis)
    return code


def tests_per_query(lo: np.ndarray, hi: np.ndarray, split) -> float:
    """Mean node boxes tested per query in the tree that ``split`` builds over the boxes lo, hi [m],
    (E, 3) each, every box also a query; split(items) -> (left items, right items), or None for a
    leaf."""
    total = 0

    def visit(items: np.ndarray, queries: np.ndarray) -> None:
        nonlocal total
        total += len(queries)
        nlo, nhi = lo[items].min(axis=0), hi[items].max(axis=0)
        hits = queries[np.all((lo[queries] <= nhi) & (hi[queries] >= nlo), axis=1)]
        children = split(items) if len(hits) else None
        if children is not None:
            for child in children:
                visit(child, hits)

    visit(np.arange(len(lo)), np.arange(len(lo)))
    return total / len(lo)


def radix_split(code: np.ndarray):
    """Karras's split of items sorted by (code, index): at the highest bit where the range's first and
    last codes differ; a run of equal codes is halved (Warp breaks such ties by its own rule)."""
    def split(items):
        if len(items) == 1:
            return None
        items = items[np.lexsort((items, code[items]))]
        a, b = code[items[0]], code[items[-1]]
        if a == b:
            m = len(items) // 2
        else:
            bit = int(a ^ b).bit_length() - 1
            m = int(np.searchsorted((code[items] >> bit) & 1, 1))
        return items[:m], items[m:]
    return split


def median_split(lo: np.ndarray, hi: np.ndarray):
    """Top-down split at the median box centre along the longest axis of the node's bounds (Warp's
    host "median" build); boxes lo, hi [m], (E, 3)."""
    centres = 0.5 * (lo + hi)

    def split(items):
        if len(items) == 1:
            return None
        axis = int(np.argmax(hi[items].max(axis=0) - lo[items].min(axis=0)))
        items = items[np.argsort(centres[items, axis], kind="stable")]
        return items[:len(items) // 2], items[len(items) // 2:]
    return split


def main() -> int:
    from _record import commit
    from simgen.sim.warp_toolkit import instance_offsets

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--garment", default="tshirt")
    p.add_argument("--instances", type=int, default=64, help="the batch whose lattice the LBVH spans")
    p.add_argument("--out", type=Path, help="also write the JSON here")
    args = p.parse_args()
    sys.setrecursionlimit(100_000)
    lo, hi = edge_boxes(args.garment)
    centres = 0.5 * (lo + hi)
    offsets = instance_offsets(args.instances).astype(np.float64)
    own_lo, own_hi = lo.min(axis=0), hi.max(axis=0)
    lattice_lo, lattice_hi = own_lo + offsets.min(axis=0), own_hi + offsets.max(axis=0)
    own_codes = morton(centres, own_lo, own_hi - own_lo)
    lattice_codes = morton(centres, lattice_lo, lattice_hi - lattice_lo)
    row = {
        "benchmark": "bvh_quality", "commit": commit(), "garment": args.garment, "edges": len(lo),
        "instances": args.instances, "lattice_extent_m": (lattice_hi - lattice_lo).round(3).tolist(),
        "unique_codes": {"own_bounds": len(np.unique(own_codes)), "lattice_bounds": len(np.unique(lattice_codes))},
        "tests_per_query": {
            "radix_own_bounds": tests_per_query(lo, hi, radix_split(own_codes)),
            "radix_lattice_bounds": tests_per_query(lo, hi, radix_split(lattice_codes)),
            "median_split": tests_per_query(lo, hi, median_split(lo, hi)),
        },
    }
    text = json.dumps(row, indent=1)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
