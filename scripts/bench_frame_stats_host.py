"""The host side of the generator's statistics: per pool frame and per finished sequence.

Each pool frame, :meth:`simgen.sim.frame_stats.FrameStats.measure` copies the busy slots' cloth,
skinned garment and body distances to the host and reduces them there with
:func:`simgen.sim.placement.placement_rows` (body share, LBS offset, support drop, lowest point);
each sequence that ends is reduced by :func:`simgen.dataset.quality.strain_summary` (every
triangle's strain at every frame) in a writer thread. This times the two alone, on the spec's
garment (its vertex count, support mask and triangles): ``--slots`` K random frames in float32,
as the device hands them over, and a sequence of ``--frames`` frames; medians of ``--repeats``
after one untimed call. The device's kernels are not involved, so any machine measures it.

    python scripts/bench_frame_stats_host.py --slots 128 --out host.json

Prints (and writes with --out) JSON with the machine, commit and sizes.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dataset_bench import _commit, _device, _emit  # noqa: E402  (scripts/ sibling: records and output)


def _median_s(call, repeats: int) -> float:
    """[s] The median wall time of ``call()`` over ``repeats`` calls after one untimed."""
    call()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--spec", default="thesis-tshirt", help="dataset preset whose garment and body to use")
    p.add_argument("--slots", type=int, nargs="+", default=[128, 32])
    p.add_argument("--frames", type=int, default=300, help="frames of the sequence strain_summary reduces")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)

    from simgen._warp_log import quiet_warp
    from simgen.dataset import load_spec
    from simgen.dataset.execute import _load_body, _load_garment
    from simgen.dataset.quality import strain_summary, triangle_rest_inverse
    from simgen.sim.placement import garment_reference, placement_rows

    quiet_warp()
    spec = load_spec(a.spec)
    body = _load_body(spec.body)
    garment = _load_garment(spec.garments[0], spec.body)
    support = garment_reference(garment, body).support
    V = len(garment.vertices)
    rng = np.random.default_rng(0)
    runs = []
    for k in a.slots:
        x, lbs, up = (rng.random((k, V, 3), dtype=np.float32) for _ in range(3))
        dist = rng.random((k, V), dtype=np.float32)
        runs.append({"slots": k, "placement_ms": 1e3 * _median_s(lambda: placement_rows(x, lbs, up, dist, support),
                                                                  a.repeats)})
    template = np.asarray(garment.vertices, dtype=np.float32)
    frames = template[None] + rng.normal(0.0, 1e-3, (a.frames, V, 3)).astype(np.float32)
    rest_inv = triangle_rest_inverse(garment.vertices, garment.faces)
    strain_s = _median_s(lambda: strain_summary(frames, garment.faces, rest_inv), a.repeats)
    result = {"benchmark": "frame_stats_host", "date": time.strftime("%Y-%m-%d"), "device": _device("cpu"),
              "commit": _commit(), "spec": spec.name,
              "sizes": {"garment": garment.name, "vertices": V, "triangles": int(len(garment.faces)),
                        "support_vertices": int(np.sum(support)), "sequence_frames": a.frames, "repeats": a.repeats},
              "runs": runs, "strain_summary_s": strain_s}
    _emit(result, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
