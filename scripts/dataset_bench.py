"""Time dataset generation and project the thesis's dataset size; prints (and saves) JSON.

    python scripts/dataset_bench.py                                   # the `tiny` preset on the CPU
    python scripts/dataset_bench.py --spec thesis-tshirt --out /tmp/tt --time-budget 480 --json tt.json
    CUDA_VISIBLE_DEVICES=0,1 python scripts/dataset_bench.py --spec thesis-tshirt --ray local   # 2 GPUs

A fresh store is generated (or an existing one resumed with --out): wall time, cloth-frames/s (every
simulated frame: protocol relax/ramp/rest + clip frames) and output frames/s (stored frames only),
then two projections for the thesis's dataset of 120,989 output frames (sec. 4.3.1; ARCSim needed
about 180 h): ``projected_thesis_s_frames_only`` = 120,989 / cloth-frames/s (no protocol), and
``projected_thesis_s`` = the same times the protocol overhead of the `thesis-tshirt` plan (cloth-
frames / output frames of that plan: 17 fits and 340 sequences, each with the 60-frame protocol).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

THESIS_FRAMES = 120_989  # output frames of the thesis's T-shirt dataset (56 CMU sequences x 17 shapes)
THESIS_ARCSIM_HOURS = 180


def _commit() -> str:
    """The git commit measured; the device machine's copy of the tree has no (or a stale) .git, so
    the caller passes the commit in SIMGEN_COMMIT there."""
    if os.environ.get("SIMGEN_COMMIT"):
        return os.environ["SIMGEN_COMMIT"]
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True).stdout.strip()
        return head + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _cpu_name() -> str:
    """The processor's model name (/proc/cpuinfo where there is one)."""
    try:
        with open("/proc/cpuinfo") as fh:
            return next(line.split(":", 1)[1].strip() for line in fh if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor()


def _device(name: str) -> dict:
    import warp as wp

    info = {"warp_device": name, "warp": wp.__version__, "python": platform.python_version(),
            "cpus": os.cpu_count(), "load_average_1min_before": os.getloadavg()[0], "cpu": _cpu_name()}
    if name.startswith("cuda"):
        info["gpu"] = wp.get_device(name).name
    return info


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--spec", default="tiny", help="preset name or TOML spec (default: tiny)")
    p.add_argument("--out", help="store folder (default: a temporary folder, removed afterwards)")
    p.add_argument("--device", help="override the spec's device (cpu, cuda, cuda:N)")
    p.add_argument("--max-sequences", type=int)
    p.add_argument("--shape-values", help="comma-separated values for the spec's 'axes' shapes instead of its own "
                   "(a larger store for scaling runs: --shape-values=-2,-1.5,-1,1,1.5,2 gives thesis-tshirt 25 "
                   "shapes; write it with '=': a value that starts with '-' is taken for an option otherwise)")
    p.add_argument("--time-budget", type=float, help="seconds")
    p.add_argument("--batch-size", type=int)
    p.add_argument("--no-overlap-writes", action="store_true",
                   help="write each batch before the next one simulates (execution.overlap_writes = false)")
    p.add_argument("--ray", help="run on Ray: 'local' (one worker per GPU of this machine) or a cluster address")
    p.add_argument("--json", help="also write the JSON to this file")
    a = p.parse_args(argv)

    from simgen.dataset import generate_dataset, load_spec
    from simgen.dataset._cli import plan_summary
    from simgen._warp_log import quiet_warp

    quiet_warp()
    spec = load_spec(a.spec).with_overrides(device=a.device, batch_size=a.batch_size,
                                            overlap_writes=False if a.no_overlap_writes else None)
    if a.shape_values:
        if spec.shapes_generator != "axes":
            raise SystemExit(f"--shape-values needs a spec with 'axes' shapes; {spec.name} has "
                             f"{spec.shapes_generator!r}")
        try:
            values = tuple(float(v) for v in a.shape_values.split(","))
        except ValueError:
            raise SystemExit(f"--shape-values must be comma-separated numbers, got {a.shape_values!r}") from None
        spec = replace(spec, shape_values=values)
    device = spec.resolved_device()
    thesis_plan = plan_summary(load_spec("thesis-tshirt"))[0]
    overhead = thesis_plan["cloth_frames"] / thesis_plan["output_frames"]
    info = _device(device)
    tmp = None
    out = a.out
    if out is None:
        tmp = tempfile.mkdtemp(prefix="simgen-bench-")
        out = str(Path(tmp) / "store")
    try:
        t0 = time.perf_counter()
        last = [0.0]

        def progress(done, total):
            # A line every 15 s on stderr, so that a long run on the device machine shows it is alive.
            now = time.perf_counter()
            if now - last[0] >= 15.0 or done == total:
                last[0] = now
                print(f"[{now - t0:7.1f} s] {done}/{total} cloth-frames ({done / max(now - t0, 1e-9):.1f}/s)",
                      file=sys.stderr, flush=True)

        reports = generate_dataset(spec, out, ray=a.ray, max_sequences=a.max_sequences, time_budget=a.time_budget,
                                   progress=progress)
        wall = time.perf_counter() - t0
        r = reports[0]
        from simgen.dataset import open_dataset

        ds = open_dataset(r.path)
        out_frames = sum(ds.sequence_info(s)["frames"] for s in ds.sequence_ids())
        rate = r.cloth_frames_per_second
        result = {
            "benchmark": "dataset_generate",
            "date": time.strftime("%Y-%m-%d"),
            "device": info,
            "commit": _commit(),
            "spec": spec.name,
            "sizes": {"garment": ds.garment_name, "vertices": ds.attrs["garment"]["vertices"],
                      "triangles": ds.attrs["garment"]["triangles"], "shapes": len(spec.shapes()),
                      "shape_values": list(spec.shape_values), "motions": len(spec.motions()),
                      "planned_sequences": r.planned_sequences,
                      "sequences_done": len(ds.sequence_ids()), "sequences_written_now": r.written,
                      "substeps": spec.substeps, "batch_size": spec.batch_size, "pool_slots": r.slots,
                      "overlap_writes": spec.overlap_writes,
                      "protocol_frames": spec.protocol_frames()},
            "cloth_frames": r.cloth_frames,
            "wall_s": r.wall,
            "run_wall_s": wall,
            "cloth_frames_per_s": rate,
            # Where the wall time went (summed over pools): the solver's stepping, the rest of the
            # pools' frames (posing, per-frame statistics, host copies), writing the nodes, the part
            # of the writes done in the background while the pool stepped (overlap_writes; 0
            # without), and what is left (planning, loading, waiting):
            # wall = solver_steps + simulate_other + write - write_hidden + other.
            "time_split_s": {"solver_steps": r.step_wall, "simulate_other": r.simulate_wall - r.step_wall,
                             "write": r.write_wall, "write_hidden": r.write_wall - r.write_wait,
                             "other": r.wall - r.simulate_wall - r.write_wait},
            # Jobs simulated again (diverged, or a strain or depth outlier: execution.retry_*_outliers),
            # what their later attempts cost (included above), and why and when each attempt failed.
            "retries": {"jobs": r.retried, "cloth_frames": r.retry_cloth_frames,
                        "simulate_s": r.retry_simulate_wall, "failed_attempts": r.failed_attempts},
            "output_frames_stored": out_frames,
            "stopped": r.stopped,
            # Ray: the workers (one per GPU) and each pool task's timeline [s from the run's start];
            # start-up = until the last first-round pool was built, of which Ray's own start
            # (executor_ready_s) comes first.
            "ray": a.ray,
            "executor_ready_s": r.executor_ready,
            "workers": len({json.dumps(t["worker"]) for t in r.tasks if t["worker"]}) or None,
            "startup_s": r.startup_s,
            "startup_share": r.startup_s / wall if r.startup_s is not None else None,
            # Everything from the call to the end (Ray's start, loading, the last write).
            "cloth_frames_per_s_end_to_end": r.cloth_frames / wall,
            "tasks": r.tasks,
            "thesis_tshirt_plan": thesis_plan,
            "protocol_overhead_thesis_tshirt": overhead,
            "projected_thesis_s_frames_only": THESIS_FRAMES / rate if rate else None,
            "projected_thesis_s": THESIS_FRAMES * overhead / rate if rate else None,
            "projected_thesis_tshirt_s": thesis_plan["cloth_frames"] / rate if rate else None,
            "thesis_arcsim_s": THESIS_ARCSIM_HOURS * 3600,
        }
        # Warp's memory pool at its fullest in any pool's process [bytes] (the slots and the rest).
        highs = [t["gpu_memory_high_bytes"] for t in r.tasks if t["gpu_memory_high_bytes"] is not None]
        result["gpu_memory_high_bytes"] = max(highs) if highs else None
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    _emit(result, a.json)
    return 0


def _emit(result: dict, path: str | None) -> None:
    """Print the benchmark's JSON, and write it to ``path`` too when given."""
    text = json.dumps(result, indent=2)
    print(text)
    if path:
        Path(path).write_text(text + "\n")


if __name__ == "__main__":
    sys.exit(main())
