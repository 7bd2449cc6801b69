"""SoftSMPL on a soft-tissue store in one command (thesis ch. 3, issue 25): the autoencoders at every
code size of Table 3.1, the regressor and its Fig. 3.7 ablations, leave-one-motion-out, and the
evaluation -- each phase within a time budget, every run resumable.

    python scripts/softtissue_thesis.py --data st-store --work st-runs --out st-report --device cuda

Phases (each run a `simgen train softtissue` process, the regressors several at once, spread over
``--gpus 0,1,...`` where a machine has several; a rerun with the same --work resumes each run where
it stopped and skips finished ones):

1. autoencoders: the pose AE and the soft-tissue AE at each ``--ae-sizes`` (100, 50, 25), the
   store's held-out motions held out, each stage for at most ``--ae-budget`` seconds (`simgen
   train softtissue --stage-budget`): a stage the budget ends before its epochs (thesis: 20 and
   1000) keeps the epochs it reached, and the report says how many.
2. regressors, each on the autoencoders of the largest size (``--base``: only the regressor trains,
   100 epochs at most, ``--reg-budget`` seconds): ``full``; the ablations of Fig. 3.7
   ``no_static`` (raw joint rotations instead of the pose code), ``no_dynamic`` (one shape per clip,
   no motion transfer) and ``neither``; and ``lomo_<motion>`` for each held-out motion (trained on
   every other motion, the other held-out ones included; the autoencoders saw none of them).
3. evaluation: `simgen eval softtissue` on the main split (Table 3.1 at every size, the regressors
   side by side, speed against body mass) and each leave-one-motion-out fold on its own motion.

--out gets summary.json and summary.md, the evaluation's tables and plot, and each run's log.csv.
On a machine without matplotlib the plots are drawn afterwards with ``--out DIR --plot-only``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

REGRESSOR_VARIANTS = {"full": [], "no_static": ["--pose-input", "pose"], "no_dynamic": ["--no-motion-transfer"],
                      "neither": ["--pose-input", "pose", "--no-motion-transfer"]}


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def _epochs(folder: Path) -> dict:
    """{stage: epochs logged} of a run folder (OUT/softtissue/log.csv)."""
    log = folder / "softtissue" / "log.csv"
    out: dict = {}
    if log.is_file():
        for row in csv.DictReader(open(log)):
            out[row["stage"]] = max(out.get(row["stage"], 0), int(row["epoch"]))
    return out


def _finished(folder: Path) -> bool:
    return (folder / "softtissue" / "regressor" / "config.json").is_file()


def _train_all(runs: dict, common: list[str], work: Path, budget: float, jobs: int, gpus: list[str]) -> dict:
    """Run `simgen train softtissue` for each {name: extra args} not finished yet, ``jobs`` at a time
    on each of ``gpus`` (CUDA device indices; [] leaves the device alone), each on the GPU running
    the fewest, ``budget`` seconds per stage; {name: {"seconds", "returncode", "gpu"}}."""
    todo = [(n, a) for n, a in runs.items() if not _finished(work / n)]
    slots = gpus or [None]
    # several processes on one machine: each gets its share of the cores (the PCA's SVD and torch's
    # CPU ops spin all cores in every process otherwise, and side by side they starve each other)
    threads = str(max(1, (os.cpu_count() or 1) // (jobs * len(slots))))
    done, running = {}, []
    while todo or running:
        while todo and len(running) < jobs * len(slots):
            name, extra = todo.pop(0)
            gpu = min(slots, key=lambda g: (sum(r[4] == g for r in running), slots.index(g)))
            env = dict(os.environ, OMP_NUM_THREADS=threads, OPENBLAS_NUM_THREADS=threads, MKL_NUM_THREADS=threads)
            if gpu is not None:
                env["CUDA_VISIBLE_DEVICES"] = gpu
            cmd = [sys.executable, "-m", "simgen.cli", "train", "softtissue", *common, "--out", str(work / name),
                   "--stage-budget", str(budget), *extra]
            logf = open(work / f"{name}.log", "a")
            running.append((name, subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, env=env),
                            time.monotonic(), logf, gpu))
            _log(f"started {name}" + ("" if gpu is None else f" on GPU {gpu}"))
        time.sleep(1.0)
        for item in list(running):
            name, proc, t0, logf, gpu = item
            if proc.poll() is not None:
                logf.close()
                running.remove(item)
                done[name] = {"seconds": round(time.monotonic() - t0, 1), "returncode": proc.returncode, "gpu": gpu}
                _log(f"{name} ended ({proc.returncode}) after {done[name]['seconds']} s: {_epochs(work / name)}")
                if proc.returncode != 0:
                    print((work / f"{name}.log").read_text()[-3000:], file=sys.stderr)
    return done


def _phase(runs: dict, common: list[str], work: Path, budget: float, jobs: int, gpus: list[str]) -> dict:
    """Train ``runs`` ({name: extra args}), each stage of each run for at most ``budget`` seconds (a
    stage the budget ends keeps the epochs it reached); the phase's record for summary.json."""
    t0 = time.monotonic()
    ran = _train_all(runs, common, work, budget, jobs, gpus)
    return {"wall_s": round(time.monotonic() - t0, 1), "stage_budget_s": budget,
            "runs": {n: {**ran.get(n, {}), "epochs": _epochs(work / n), "finished": _finished(work / n)}
                     for n in runs}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", help="soft-tissue store (`simgen dataset generate softtissue`)")
    p.add_argument("--work", help="run folders (kept: a rerun resumes)")
    p.add_argument("--out", required=True, help="report folder")
    p.add_argument("--device", default="cuda")
    p.add_argument("--ae-sizes", type=int, nargs="+", default=[100, 50, 25])
    p.add_argument("--ae-budget", type=float, default=420.0, help="seconds per autoencoder stage")
    p.add_argument("--reg-budget", type=float, default=240.0, help="seconds per regressor")
    p.add_argument("--gpus", default="", help="CUDA device indices to spread the runs over, comma-separated "
                   "(e.g. 0,1; each run sees one); empty: every run on --device")
    p.add_argument("--ae-jobs", type=int, default=1, help="autoencoder runs at once per GPU")
    p.add_argument("--reg-jobs", type=int, default=4, help="regressor runs at once per GPU")
    p.add_argument("--phases", default="ae,reg,eval", help="which phases to run, comma-separated")
    p.add_argument("--timing-frames", type=int, default=240)
    p.add_argument("--plot-only", action="store_true", help="only draw --out's plots from its JSON (for a GPU "
                   "machine without matplotlib)")
    a = p.parse_args(argv)
    if a.plot_only:
        from simgen.learn.softtissue.evaluate import plot_speed_vs_mass

        for j in sorted(Path(a.out).glob("*/softtissue_eval.json")):
            plot_speed_vs_mass(json.loads(j.read_text()), j.parent / "speed_vs_mass.png")
            _log(f"drew {j.parent / 'speed_vs_mass.png'}")
        return 0
    if not (a.data and a.work):
        p.error("--data and --work are needed (all but --plot-only)")

    work, out = Path(a.work), Path(a.out)
    work.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    phases = set(a.phases.split(","))
    gpus = [g.strip() for g in a.gpus.split(",") if g.strip()]
    if gpus and not a.device.startswith("cuda"):
        p.error(f"--gpus {a.gpus} needs --device cuda, got {a.device}")
    summary_path = out / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    summary.update(data=str(a.data), device=a.device, commit=os.environ.get("SIMGEN_COMMIT", "unknown"))
    # each run sees only its GPU as cuda:0 under --gpus
    common = ["--data", str(a.data), "--device", "cuda" if gpus else a.device]
    sizes = sorted(set(a.ae_sizes), reverse=True)
    base = work / f"ae{sizes[0]}"

    if "ae" in phases:
        names = {f"ae{k}": ["--ae-latent", str(k), "--reg-epochs", "0"] for k in sizes}
        summary["autoencoders"] = _phase(names, common, work, a.ae_budget, a.ae_jobs, gpus)
        summary_path.write_text(json.dumps(summary, indent=1) + "\n")

    if not _finished(base):
        _log(f"{base} has not finished its autoencoders (run the 'ae' phase first): nothing more to do")
        return 1
    test_motions = json.loads((base / "softtissue" / "split.json").read_text())["test_motions"]
    if "reg" in phases:
        runs = {**REGRESSOR_VARIANTS, **{f"lomo_{m}": ["--test-motions", m] for m in test_motions}}
        runs = {n: ["--base", str(base), *x] for n, x in runs.items()}
        summary["regressors"] = _phase(runs, common, work, a.reg_budget, a.reg_jobs, gpus)
        summary_path.write_text(json.dumps(summary, indent=1) + "\n")

    if "eval" in phases:
        summary["eval"] = _evaluate(a, work, out, sizes, test_motions)
        summary_path.write_text(json.dumps(summary, indent=1) + "\n")
    for folder in sorted(work.iterdir()):
        if (folder / "softtissue" / "log.csv").is_file():
            shutil.copy(folder / "softtissue" / "log.csv", out / f"log_{folder.name}.csv")
    (out / "summary.md").write_text(_markdown(summary, out))
    _log(f"report: {out / 'summary.md'}")
    return 0


def _evaluate(a, work: Path, out: Path, sizes: list[int], test_motions: list[str]) -> dict:
    from simgen._warp_log import quiet_warp
    from simgen.learn.softtissue._cli import load_softtissue_source
    from simgen.learn.softtissue.evaluate import evaluate_softtissue

    quiet_warp()
    t0 = time.monotonic()
    data, body = load_softtissue_source(str(a.data), None)
    _log(f"read the store in {time.monotonic() - t0:.0f} s")
    candidates = [work / n for n in REGRESSOR_VARIANTS] + [work / f"ae{k}" for k in sizes[1:]]
    main_models = [m for m in candidates if _finished(m)]
    left_out = [m.name for m in candidates if not _finished(m)]
    if left_out:
        _log(f"not evaluated (not finished): {', '.join(left_out)}")
    if not (work / "full") in main_models:
        raise SystemExit("the 'full' regressor has not finished: run the 'reg' phase first")
    rep = evaluate_softtissue(main_models, data, out / "main", body=body, device=a.device,
                              timing_frames=a.timing_frames)
    full = {r["sequence"]: r for r in rep["models"][0]["sequences"]}
    lomo = []
    for m in test_motions:
        if not _finished(work / f"lomo_{m}"):
            left_out.append(f"lomo_{m}")
            continue
        fold = evaluate_softtissue([work / f"lomo_{m}"], data, out / f"lomo_{m}", body=body, device=a.device,
                                   timing_frames=10)
        rows = [r for r in fold["models"][0]["sequences"] if r["group"] == "held_out_motion"]
        lomo.append({"motion": m, "sequences": len(rows),
                     "error_mm": float(sum(r["error_mm"] for r in rows) / len(rows)),
                     "main_split_error_mm": float(sum(full[r["sequence"]]["error_mm"] for r in rows) / len(rows)),
                     "no_soft_tissue_mm": float(sum(r["no_soft_tissue_mm"] for r in rows) / len(rows))})
        _log(f"lomo {m}: {lomo[-1]}")
    return {"seconds": round(time.monotonic() - t0, 1), "not_evaluated": left_out, "main": {
        "pca_mm": rep["pca_mm"], "held_out": rep["held_out"], "train_frames": rep["train_frames"],
        "models": [{k: v for k, v in m.items() if k != "sequences"} |
                   {"error_mm": (sum(s["error_mm"] for s in m["sequences"]) / len(m["sequences"])
                                 if m["sequences"] else None)} for m in rep["models"]]},
        "leave_one_motion_out": lomo}


def _markdown(s: dict, out: Path) -> str:
    lines = [f"# SoftSMPL on {s.get('data')} ({s.get('device')}, commit {s.get('commit')})", ""]
    for phase in ("autoencoders", "regressors"):
        if phase in s:
            lines += [f"## {phase}: {s[phase]['wall_s']} s (at most {s[phase]['stage_budget_s']} s per stage)", "",
                      "| run | seconds | epochs reached |", "|---|---:|---|"]
            for n, r in s[phase]["runs"].items():
                lines.append(f"| {n} | {r.get('seconds', '-')} | "
                             + ", ".join(f"{k} {v}" for k, v in r["epochs"].items())
                             + ("" if r.get("finished") else " (not finished)") + " |")
            lines.append("")
    ev = s.get("eval")
    if ev:
        main_md = out / "main" / "softtissue_eval.md"
        if main_md.is_file():
            lines += [main_md.read_text().replace("# SoftSMPL on", "## Main split: SoftSMPL on", 1), ""]
        lines += ["## Leave one motion out (the autoencoders saw none of these motions)", "",
                  "| motion | sequences | error mm (fold) | error mm (all held-out motions out) | no soft tissue mm |",
                  "|---|---:|---:|---:|---:|"]
        for r in ev["leave_one_motion_out"]:
            lines.append(f"| {r['motion']} | {r['sequences']} | {r['error_mm']:.3f} | {r['main_split_error_mm']:.3f} "
                         f"| {r['no_soft_tissue_mm']:.3f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
