"""Generate a garment dataset into a Zarr store, then check the store.

    python examples/generate_dataset.py                                   # thesis-tshirt (GPU-sized)
    python examples/generate_dataset.py --spec tiny --out datasets/tiny   # CPU-sized: ~15 s on 2 cores
    python examples/generate_dataset.py --garment tshirt_1k --motions walk_fast,jumping_jacks \\
        --shapes zero,b0p2 --max-frames 30 --out datasets/small           # thesis-tshirt cut down

A spec (a bundled preset name or a TOML file, docs/dataset.md) names a garment, body shapes and
motions. Every (motion, shape) pair is simulated with the thesis's start protocol and written,
with the template and the rest-pose fit of every shape, into one resumable Zarr store per
garment. Rerunning the same command resumes an interrupted run. Then every store is checked:
NaN, cloth inside the re-posed body, strain outliers, missing frames, manifest against store. The
exit code is 1 when a check fails or a job failed.

Full size (the default, thesis-tshirt: 340 sequences, 76,007 stored frames, 97,147 simulated
cloth-frames of the 8,598-triangle T-shirt): 22 minutes on one H100 (BENCHMARKS.md). On a CPU it
would take days (examples/simulate_garment.py runs that T-shirt at about one cloth-frame per second
on 2 cores), so use --spec tiny there: 2 shapes x 2 clips x 5 frames of tshirt_1k, about 15 s on a
2-core CPU and the check 2 s more.

Public API used: simgen.dataset.load_spec, DatasetSpec.with_overrides, generate_dataset,
check_dataset and open_dataset.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time


def _names(text: str | None) -> list[str] | None:
    return [s.strip() for s in text.split(",") if s.strip()] if text else None


class HelpFormatter(argparse.HelpFormatter):
    """--help shows each option's default, except for options without one."""

    def _get_help_string(self, action):
        text = action.help or ""
        if action.default not in (None, False, argparse.SUPPRESS) and "%(default)" not in text:
            text += " (default: %(default)s)"
        return text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter)
    p.add_argument("--spec", default="thesis-tshirt",
                   help="a preset (tiny, thesis-tshirt, thesis-dress, all-garments, ...) or a TOML spec file")
    p.add_argument("--out", default=None,
                   help="store folder or fsspec URL (default: the spec's output.path, else datasets/SPEC)")
    p.add_argument("--garment", default=None,
                   help="simulate this garment instead of the spec's (e.g. tshirt_1k, the ~1k-triangle variant)")
    p.add_argument("--motions", default=None, help="comma-separated library motions to keep (default: the spec's)")
    p.add_argument("--shapes", default=None, help="comma-separated shape ids of the spec to keep (default: all)")
    p.add_argument("--max-frames", type=int, default=None, help="frames kept per clip (default: the spec's)")
    p.add_argument("--substeps", type=int, default=None, help="solver steps per frame (default: the spec's)")
    p.add_argument("--batch-size", type=int, default=None,
                   help="sequences per batched solver call (default: the spec's)")
    p.add_argument("--device", default=None, help="Warp device: auto, cpu, cuda or cuda:N (default: the spec's)")
    p.add_argument("--ray", default=None, help="run batches as Ray tasks: 'local' or a cluster address")
    p.add_argument("--max-sequences", type=int, default=None, help="write at most N new sequences in this run")
    p.add_argument("--time-budget", type=float, default=None, help="seconds: start no batch that would not finish")
    p.add_argument("--check-stride", type=int, default=1,
                   help="check cloth against the re-posed body on every N-th frame (strain, NaN: every frame)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    from simgen.dataset import check_dataset, generate_dataset, load_spec, open_dataset
    from simgen.errors import InputError

    try:
        spec = load_spec(args.spec).with_overrides(
            device=args.device, batch_size=args.batch_size, substeps=args.substeps, max_frames=args.max_frames,
            motions=_names(args.motions), shapes=_names(args.shapes))
        if args.garment is not None:
            spec = dataclasses.replace(spec, garments=[args.garment])
        print(f"spec {spec.name}: garment {', '.join(spec.garments)}, {len(spec.shapes())} shapes, "
              f"{len(spec.motions())} motions; writing to {spec.output_path(spec.garments[0], args.out)}")
        t0 = time.perf_counter()
        last = [t0]

        def progress(done, total=None):
            now = time.perf_counter()
            if now - last[0] > 10.0:
                last[0] = now
                print(f"  {done}/{total} cloth-frames, {now - t0:.0f} s", flush=True)

        reports = generate_dataset(spec, args.out, ray=args.ray, max_sequences=args.max_sequences,
                                   time_budget=args.time_budget, progress=progress, log=print)
        code = 0
        for r in reports:
            print(f"{r.path}: {r.written} sequences written now, {r.planned_sequences - r.pending} of "
                  f"{r.planned_sequences} done; {r.cloth_frames} cloth-frames in {r.wall:.1f} s "
                  f"({r.cloth_frames_per_second:.1f}/s)")
            for key, message in r.failed.items():
                print(f"failed: {key}: {message}", file=sys.stderr)
                code = 1
            if r.pending:
                print(f"{r.pending} sequences pending: rerun the same command to continue")
            check = check_dataset(r.path, stride=args.check_stride)
            print(check.format())
            if not check.passed:
                code = 1
            ds = open_dataset(r.path)
            print(f"store: {r.path} ({len(ds.sequence_ids('train'))} train and {len(ds.sequence_ids('test'))} "
                  f"test sequences, shapes {', '.join(ds.shape_ids())})")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return code


if __name__ == "__main__":
    sys.exit(main())
