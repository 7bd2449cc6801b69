"""Time `simgen dataset check` on one store with one process and with several; prints JSON.

    python scripts/check_bench.py STORE [--workers 1,2] [--stride 30] [--device auto]

Each worker count checks the whole store once (the first run also warms Warp's kernel cache, so
the single-process run goes first and again last: the two bound the cache's effect). Records the
device, the commit, the store's size and, per run, the wall time, sequences per second and whether
the report equals the single-process one.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import commit  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("store")
    p.add_argument("--workers", default="1,2", help="comma-separated worker counts (1 is run first and last)")
    p.add_argument("--stride", type=int, default=1)
    p.add_argument("--device", default="auto")
    p.add_argument("--json", help="also write the JSON to this file")
    a = p.parse_args(argv)
    from simgen.dataset import open_dataset
    from simgen.dataset.check import check_dataset

    counts = [int(w) for w in a.workers.split(",")]
    order = [1] + [w for w in counts if w != 1] + [1]
    ds = open_dataset(a.store)
    runs, reference = [], None
    for w in order:
        t = time.perf_counter()
        rep = check_dataset(a.store, stride=a.stride, device=a.device, workers=w)
        wall = time.perf_counter() - t
        d = rep.to_dict()
        reference = reference or d
        runs.append({"workers": w, "wall_s": wall, "sequences_per_s": rep.sequences / wall,
                     "passed": rep.passed, "same_report": d == reference})
    out = {"benchmark": "dataset_check", "commit": commit(), "date": time.strftime("%Y-%m-%d"),
           "device": {"check_device": a.device, "cpus": os.cpu_count(),
                      "cpu": platform.processor() or platform.machine()},
           "sizes": {"sequences": len(ds.sequence_ids()), "frames": d["frames"], "stride": a.stride},
           "runs": runs}
    text = json.dumps(out, indent=2)
    print(text)
    if a.json:
        Path(a.json).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
