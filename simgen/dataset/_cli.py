"""The bodies of ``simgen dataset generate|check|info`` (kept here so cli.py stays a thin layer).

Also used by ``python -m simgen.dataset`` (plain argparse, no typer/rich needed: the device machine).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from simgen.errors import InputError

__all__ = ["run_generate", "run_check", "run_info", "plan_summary"]


def _plain_progress(label: str, total: int, every: float = 10.0):
    """A progress printer for machines without rich: one stderr line every ``every`` seconds."""
    t0 = time.perf_counter()
    last = [0.0]

    class _Ctx:
        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    def update(done: int, total_: int | None = None) -> None:
        now = time.perf_counter()
        tot = total_ or total
        if now - last[0] >= every or done >= tot:
            last[0] = now
            el = now - t0
            eta = f"{el / done * (tot - done):.0f} s" if done else "?"
            print(f"{label}: {done}/{tot} ({el:.0f} s, ETA {eta})", file=sys.stderr, flush=True)

    return _Ctx(), update


def plan_summary(spec) -> list[dict]:
    """Per garment: shapes, motions, jobs and cloth-frames (protocol included) of the full plan."""
    from simgen.dataset.execute import _load_body, job_cloth_frames
    from simgen.dataset.generate import plan_jobs

    body = _load_body(spec.body)
    rows = []
    for g in spec.garments:
        jobs = plan_jobs(spec, g, body)
        seqs = [j for j in jobs if j.kind == "sequence"]
        rows.append({"garment": g, "shapes": len(spec.shapes()), "motions": len({j.motion for j in seqs}),
                     "sequences": len(seqs), "output_frames": sum(j.frames for j in seqs),
                     "test_sequences": sum(j.split == "test" for j in seqs),
                     "cloth_frames": job_cloth_frames(spec, jobs)})
    return rows


def run_generate(spec_arg, *, out=None, ray=None, max_sequences=None, time_budget=None, report=None, dry_run=False,
                 console=None, progress_factory=None, overrides=None) -> int:
    """Generate; print a summary; return the exit code (0 done or stopped by a limit, 1 failed jobs)."""
    from simgen.dataset.generate import GenerationError, generate_dataset
    from simgen.dataset.softtissue import is_softtissue_spec
    from simgen.dataset.spec import load_spec

    if is_softtissue_spec(spec_arg):
        return _generate_softtissue(spec_arg, out=out, ray=ray, max_sequences=max_sequences, time_budget=time_budget,
                                    report=report, dry_run=dry_run, progress_factory=progress_factory,
                                    overrides=overrides)
    spec = load_spec(spec_arg).with_overrides(**(overrides or {}))
    if dry_run:
        rows = plan_summary(spec)
        for r in rows:
            r["store"] = spec.output_path(r["garment"], out)
        print(json.dumps(rows, indent=2))
        return 0
    make = progress_factory or _plain_progress
    bar, update = make(f"dataset {spec.name}", 1)
    log = (lambda msg: console.print(msg, highlight=False, markup=False)) if console is not None else \
        (lambda msg: print(msg, file=sys.stderr))
    t0 = time.perf_counter()
    try:
        with bar:
            reports = generate_dataset(spec, out, ray=ray, max_sequences=max_sequences, time_budget=time_budget,
                                       progress=update, log=log)
    except GenerationError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    wall = time.perf_counter() - t0
    code = 0
    out_reports = []
    for r in reports:
        d = r.to_dict()
        d["run_wall"] = wall
        out_reports.append(d)
        state = "complete" if r.pending == 0 else f"{r.pending} sequences pending (rerun to continue)"
        print(f"{r.path}: {r.garment}: {r.written} sequences written now, "
              f"{r.planned_sequences - r.pending} of {r.planned_sequences} done, {state}; "
              f"{r.cloth_frames} cloth-frames in {r.wall:.1f} s ({r.cloth_frames_per_second:.1f}/s)"
              + (f"; {r.retried} jobs simulated again ({r.retry_cloth_frames} cloth-frames, "
                 f"{r.retry_simulate_wall:.1f} s)" if r.retried else "")
              + (f"; stopped: {r.stopped}" if r.stopped else ""))
        for key, msg in r.failed.items():
            print(f"failed: {key}: {msg}", file=sys.stderr)
            code = 1
    if report is not None:
        from simgen._fileio import atomic_write_bytes

        Path(report).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(report, json.dumps(out_reports, indent=2).encode())
    return code


def _generate_softtissue(spec_arg, *, out, ray, max_sequences, time_budget, report, dry_run, progress_factory,
                         overrides) -> int:
    from simgen.dataset.softtissue import generate_softtissue, load_softtissue_spec

    spec = load_softtissue_spec(spec_arg)
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    extra = (["--ray"] if ray is not None else []) + ["--" + k.replace("_", "-") for k in sorted(set(given) - {"device"})]
    if extra:
        raise InputError(f"a soft-tissue spec takes only --out, --device, --max-sequences, --time-budget, --report "
                         f"and --dry-run (got {', '.join(extra)})")
    if "device" in given:
        from dataclasses import replace

        spec = replace(spec, device=given["device"])
    if dry_run:
        print(json.dumps({"store": spec.output_path(out), "shapes": len(spec.shapes), "motions": len(spec.motions),
                          "sequences": len(spec.plan()) * len(spec.shapes)}, indent=2))
        return 0
    bar, update = (progress_factory or _plain_progress)(f"soft tissue {spec.name}", 1)
    with bar:
        r = generate_softtissue(spec, out, max_sequences=max_sequences, time_budget=time_budget, progress=update,
                                log=lambda msg: print(msg, file=sys.stderr))
    state = "complete" if r.pending == 0 else f"{r.pending} sequences pending (rerun to continue)"
    print(f"{r.path}: {r.written} soft-tissue sequences written now, {r.planned - r.pending} of {r.planned} done, "
          f"{state}; {r.frames} frames in {r.wall:.1f} s" + (f"; stopped: {r.stopped}" if r.stopped else ""))
    for node, msg in r.failed.items():
        print(f"failed: {node}: {msg}", file=sys.stderr)
    if report is not None:
        from simgen._fileio import atomic_write_bytes

        Path(report).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(report, json.dumps([r.to_dict()], indent=2).encode())
    return 1 if r.failed else 0


def run_check(path, *, stride=1, max_depth=None, max_strain=None, require_complete=False, as_json=False,
              progress_factory=None, device="auto", workers=0) -> int:
    from simgen.dataset.check import check_dataset
    from simgen.dataset.quality import DEFAULT_MAX_DEPTH, DEFAULT_MAX_STRAIN
    from simgen.dataset.softtissue import check_softtissue_store, is_softtissue_store

    make = progress_factory or _plain_progress
    max_depth = DEFAULT_MAX_DEPTH if max_depth is None else max_depth
    max_strain = DEFAULT_MAX_STRAIN if max_strain is None else max_strain
    if is_softtissue_store(path):
        if (stride, max_depth, max_strain) != (1, DEFAULT_MAX_DEPTH, DEFAULT_MAX_STRAIN):
            raise InputError(f"{path} is a soft-tissue store: --stride, --max-depth and --max-strain check cloth")
        bar, update = make("checking", 1)
        with bar:
            rep = check_softtissue_store(path, require_complete=require_complete, progress=update)
        print(json.dumps(rep, indent=2) if as_json else _format_softtissue_check(rep))
        return 0 if rep["passed"] else 1
    bar, update = make("checking", 1)
    with bar:
        rep = check_dataset(path, stride=stride, max_depth=max_depth, max_strain=max_strain,
                            require_complete=require_complete, progress=update, device=device, workers=workers)
    print(json.dumps(rep.to_dict(), indent=2) if as_json else rep.format())
    return 0 if rep.passed else 1


def _format_softtissue_check(rep: dict) -> str:
    head = (f"{rep['path']}: {'PASSED' if rep['passed'] else 'FAILED'}: {rep['sequences']} soft-tissue sequences, "
            f"{rep['frames']} frames; largest displacement {100 * rep['max_peak_m']:.2f} cm, smallest tetrahedron "
            f"det {rep['min_det'] if rep['min_det'] is None else format(rep['min_det'], '.3f')}")
    return "\n".join([head] + [f"problem: {p}" for p in rep["problems"]] + [f"failed: {f}" for f in rep["failed"]])


def _softtissue_info(path, as_json: bool) -> None:
    from simgen.dataset.softtissue import read_store_rows

    head, rows = read_store_rows(path)
    if as_json:
        print(json.dumps({"dataset": head, "sequences": rows}, indent=2))
        return
    print(f"{head['path']}: soft tissue on body {head['body']['id']} ({head['mesh']['nodes']:,} nodes, "
          f"{head['mesh']['tets']:,} tetrahedra); {head['sequences']} sequences ({head['test']} test), "
          f"{head['frames']:,} frames at {head['fps']:g} fps; shapes {', '.join(head['shapes'])}")
    for r in rows:
        print(f"  {r['id']:<40} {r['split']:<5} {r['frames']:>5} frames  peak {100 * r['peak_m']:5.2f} cm  "
              f"mean speed {100 * r['mean_speed_mps']:6.2f} cm/s  min det {r['min_det']:.3f}")


def run_info(path, *, as_json=False) -> None:
    from simgen.dataset.reader import open_dataset
    from simgen.dataset.softtissue import is_softtissue_store

    if is_softtissue_store(path):
        return _softtissue_info(path, as_json)
    ds = open_dataset(path)
    rows = []
    for sid in ds.sequence_ids():
        e = ds.sequence_info(sid)
        a = ds.loc.node_attrs(f"sequences/{sid}") or {}
        st = a.get("stats", {})
        rows.append({"id": sid, "motion": e.get("motion"), "shape": e.get("shape_id"), "split": e.get("split"),
                     "frames": e.get("frames"), "max_penetration_mm": _mm(st.get("max_penetration")),
                     "strain_mean": st.get("strain_mean"), "strain_max": st.get("strain_max"),
                     "retries": st.get("solver_retries"), "attempts": st.get("attempts"),
                     "crossing_frames": st.get("crossing_frames"), "max_crossing_edges": st.get("max_crossing_edges"),
                     "wall_time": st.get("wall_time")})
    at = ds.attrs
    head = {"path": ds.path, "garment": at["garment"], "body": at["body"], "material": at["material"]["name"],
            "fps": at["solver"]["fps"], "substeps": at["solver"]["substeps"],
            "protocol": [at["solver"]["relax_frames"], at["solver"]["ramp_frames"], at["solver"]["rest_frames"]],
            "shapes": ds.shape_ids(), "template": ds.manifest["template"] is not None,
            "sequences": len(rows), "frames": sum(r["frames"] or 0 for r in rows),
            "failed": sorted(ds.manifest.get("failed", {})), "simgen_version": at.get("simgen_version"),
            # Stores made before the crossing counter have no counts (None).
            "sequences_with_crossings": (sum(1 for r in rows if r["crossing_frames"])
                                         if all(r["crossing_frames"] is not None for r in rows) else None)}
    if as_json:
        print(json.dumps({"dataset": head, "sequences": rows}, indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"{ds.path}", show_header=False)
    t.add_column("field")
    t.add_column("value")
    g = at["garment"]
    t.add_row("garment", f"{g['name']} ({g['vertices']:,} vertices, {g['triangles']:,} triangles)")
    t.add_row("body", f"{at['body']['id']} ({at['body'].get('num_betas')} shape components)")
    t.add_row("material", head["material"])
    t.add_row("solver", f"{head['fps']:g} fps x {head['substeps']} substeps; protocol relax/ramp/rest "
                        f"{'/'.join(map(str, head['protocol']))} frames")
    t.add_row("shapes (fits)", ", ".join(head["shapes"]) or "-")
    t.add_row("sequences", f"{head['sequences']} ({sum(r['split'] == 'test' for r in rows)} test), "
                           f"{head['frames']:,} frames")
    if head["failed"]:
        t.add_row("failed", ", ".join(head["failed"]))
    if head["sequences_with_crossings"] is not None:
        t.add_row("cloth through itself", f"{head['sequences_with_crossings']} sequences have frames with crossing "
                                          f"edges (`dataset check` lists them)")
    c = Console()
    c.print(t)
    s = Table(title=f"{len(rows)} sequences (id = motion__shape)")
    s.add_column("id", overflow="fold", min_width=min(max((len(r["id"]) for r in rows), default=2), 40))
    for col in ("split", "frames", "max pen. [mm]", "strain mean", "strain max", "retries", "crossing frames",
                "wall [s]"):
        s.add_column(col, justify="right")
    for r in rows:
        crossing = "-" if r["crossing_frames"] is None else f"{r['crossing_frames']} (max {r['max_crossing_edges']})"
        s.add_row(r["id"], str(r["split"]), str(r["frames"]), _fmt(r["max_penetration_mm"], ".2f"),
                  _fmt(r["strain_mean"], ".3f"), _fmt(r["strain_max"], ".3f"), str(r["retries"]), crossing,
                  _fmt(r["wall_time"], ".1f"))
    c.print(s)


def _mm(v):
    return None if v is None else 1e3 * float(v)


def _fmt(v, f):
    return "-" if v is None else format(v, f)


def _names(words):
    """Names given as words and/or comma-separated ("a,b c" -> [a, b, c]); None when not given."""
    return None if not words else [n for w in words for n in w.split(",") if n]


def main(argv=None) -> int:
    """``python -m simgen.dataset generate|check|plan ...`` without typer/rich (for the device machine)."""
    import argparse

    from simgen.dataset.quality import DEFAULT_MAX_DEPTH, DEFAULT_MAX_STRAIN

    p = argparse.ArgumentParser(prog="python -m simgen.dataset", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="generate or resume a dataset")
    g.add_argument("spec")
    g.add_argument("--out")
    g.add_argument("--device")
    g.add_argument("--batch-size", type=int)
    g.add_argument("--substeps", type=int)
    g.add_argument("--max-frames", type=int)
    g.add_argument("--motions", nargs="+", help="'a,b' or 'a b'")
    g.add_argument("--shapes", nargs="+", help="'a,b' or 'a b'")
    g.add_argument("--max-sequences", type=int)
    g.add_argument("--time-budget", type=float)
    g.add_argument("--report")
    g.add_argument("--dry-run", action="store_true")
    k = sub.add_parser("pack", help="a few sequences as one small float16 .npz (view with `simgen dataset export`)")
    k.add_argument("path")
    k.add_argument("sequences", nargs="+")
    k.add_argument("--out", required=True)
    c = sub.add_parser("check", help="check a dataset store")
    c.add_argument("path")
    c.add_argument("--stride", type=int, default=1)
    c.add_argument("--max-depth", type=float, default=DEFAULT_MAX_DEPTH)
    c.add_argument("--max-strain", type=float, default=DEFAULT_MAX_STRAIN)
    c.add_argument("--require-complete", action="store_true")
    c.add_argument("--json", action="store_true")
    c.add_argument("--device", default="auto")
    c.add_argument("--workers", type=int, default=0, help="processes checking the sequences (0: one per core, "
                                                           "at most 16 and one per 16 sequences)")
    a = p.parse_args(argv)
    try:
        if a.cmd == "generate":
            return run_generate(a.spec, out=a.out, max_sequences=a.max_sequences, time_budget=a.time_budget,
                                report=a.report, dry_run=a.dry_run,
                                overrides=dict(device=a.device, batch_size=a.batch_size, substeps=a.substeps,
                                               max_frames=a.max_frames,
                                               motions=_names(a.motions), shapes=_names(a.shapes)))
        if a.cmd == "pack":
            from simgen.dataset.export import pack_sequences

            print(pack_sequences(a.path, a.sequences, a.out))
            return 0
        return run_check(a.path, stride=a.stride, max_depth=a.max_depth, max_strain=a.max_strain,
                         require_complete=a.require_complete, as_json=a.json, device=a.device,
                         workers=a.workers)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
