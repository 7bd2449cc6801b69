"""Thesis ch. 4 on a GPU machine in one call: generate the thesis-tshirt store (in full with
--full, else a subset), train the garment fit MLP and the wrinkle GRU on one or both splits,
evaluate against LBS and linear regression, return metrics, plots and the small fit model --
everything inside one time budget.

Phases (each bounded; the store, the models and the training state stay in --work, so a second run
on the same machine resumes generation and training instead of starting over):

1. generate: ``simgen.dataset.generate_dataset`` on the preset: with --full every motion, shape and
   frame; else a motion and shape subset with a frame cap, test motions first so that a budget cut
   still leaves held-out motions; stops starting jobs after --gen-budget seconds;
2. per split of --splits (motion: the thesis's held-out motions; shape: the extreme shapes held out
   as well), in WORK/model_<split>: the fit MLP (2000 epochs, thesis), then the wrinkle GRU with
   --val-motions training motions kept out of training: every --val-every epochs their
   error picks the saved weights, and --patience validations in a row without a 1% gain stop it
   (else --epochs or the split's share of the time left; checkpointed every minute), then the
   linear baselines;
3. evaluate each split: ``simgen.learn.evaluate_garment`` (per-frame errors, shape generalisation,
   vertices inside the body, physics terms, ms/frame on the CPU and the GPU, model sizes).

What comes back in --out: metrics.json (per split under "splits"), summary.txt, per split the plots
(``*_<split>.png``, if matplotlib is there; otherwise draw them on the CPU machine with
``--plots-from``, into DIR/<split>/), fit_model_<split>.tar (template/, fit/, split.json, both training logs, the
wrinkle model's config without its ~110 MB of weights) and compare_<split>.npz (--compare-sequences
held-out sequences of different motions: simulation, model, LBS and the body, float16, for USD,
MP4 and stills on the CPU machine with ``--usd-from``). No usd-core or pyvista is imported here.

    # on the GPU machine (after the warp install recipe of ../shared/gpu/README.md):
    python scripts/train_thesis.py --full --splits motion shape --total-budget 1800 --gen-budget 600 \\
        --out results --work thesis-run --device cuda
    # back on the CPU machine:
    python scripts/train_thesis.py --plots-from OUTDIR            # plots from metrics.json + logs
    python scripts/train_thesis.py --usd-from OUTDIR/compare_motion.npz --usd-out compare --video
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tarfile
import time
import traceback
from pathlib import Path

import numpy as np

# Test motions first (the library's held-out clips), then training motions, so that a generation
# cut by the time budget still holds held-out motions and several training motions.
DEFAULT_MOTIONS = ["walk_fast", "dance", "lunge", "cmu_131_03_hop", "walk", "jumping_jacks", "squat", "arm_swings",
                   "run", "side_step", "bend_and_reach", "torso_twist", "kick", "jump", "cmu_131_02_walk",
                   "idle_sway", "turn_in_place", "arm_raises", "walk_curve", "cmu_131_01_walk_start_stop"]
# The thesis's shape design on the first two components (the preset has four): zero and +-1, +-2.
DEFAULT_SHAPES = ["zero", "b0m2", "b0m1", "b0p1", "b0p2", "b1m2", "b1m1", "b1p1", "b1p2"]


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def _write_json(path: Path, obj) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(obj, indent=1, default=str) + "\n")
    tmp.replace(path)


def _tar_fit_model(model_dir: Path, path: Path) -> None:
    """The small model (everything but the wrinkle GRU's weights) as one tar file."""
    with tarfile.open(path, "w") as tar:
        for rel in ("split.json", "template/config.json", "template/model.pt", "fit/config.json", "fit/model.pt",
                    "fit/log.csv", "wrinkle/config.json", "wrinkle/log.csv"):
            p = model_dir / rel
            if p.is_file():
                tar.add(p, arcname=f"model/{rel}")


def _compare_ids(data, split, count: int) -> list[str]:
    """Up to ``count`` held-out sequences of different motions, at the zero shape where there is one."""
    ids = split.test.get("held_out_motion") or split.test.get("held_out_both") or []
    by_motion: dict = {}
    for sid in sorted(ids, key=lambda i: (data.sequences[i].shape_id != "zero", i)):
        by_motion.setdefault(data.sequences[sid].motion, sid)
    return sorted(by_motion.values())[:count]


def _compare_npz(model, data, split, path: Path, frames: int, count: int) -> dict:
    """Held-out sequences (:func:`_compare_ids`), their first ``frames`` frames: simulation, model
    (post-processed), LBS and the posed body [m], float16, (S, T, V, 3) each."""
    import torch

    from simgen.learn.garment_model import lbs_baseline

    ids = _compare_ids(data, split, count)
    if not ids:
        return {}
    n = min([frames] + [data.sequences[i].num_frames for i in ids])
    dev = model.device
    arrays: dict = {"ground_truth": [], "ours": [], "lbs": [], "body": []}
    for sid in ids:
        s = data.sequences[sid]
        b, p, t = (torch.as_tensor(x[:n], device=dev) for x in (s.betas, s.poses, s.trans))
        with torch.no_grad():
            pred = model.predict(b, p, t, s.fps, postprocess=True)
            arrays["lbs"].append(lbs_baseline(model.template, b, pred.transforms).cpu().numpy())
            arrays["body"].append(model.body(b, p, t)[0].cpu().numpy())
        arrays["ground_truth"].append(s.vertices[:n])
        arrays["ours"].append(pred.vertices.cpu().numpy())
    arrays = {k: np.stack(v).astype(np.float16) for k, v in arrays.items()}
    np.savez_compressed(path, sequence=np.array(ids), garment_faces=model.template.faces.cpu().numpy().astype(np.int32),
                        body_faces=model.body.faces.cpu().numpy().astype(np.int32),
                        fps=np.float32(data.sequences[ids[0]].fps), **arrays)
    return {"sequences": ids, "frames": n, "bytes": path.stat().st_size}


def _generate(args, work: Path, left, phase) -> Path:
    """Phase 1: the store in WORK/dataset (the preset in full with --full, else the subset), within
    --gen-budget and what the later phases need; a later run resumes it."""
    from simgen.dataset import generate_dataset, load_spec

    spec = load_spec(args.spec)
    if not args.full:
        spec = spec.with_overrides(motions=args.motions, shapes=args.shapes, max_frames=args.max_frames)
    spec = spec.with_overrides(batch_size=args.gen_batch, substeps=args.substeps)
    store = work / "dataset"
    gen_budget = min(args.gen_budget, left() - len(args.splits) * (args.min_train + args.eval_reserve))
    if gen_budget > 5:
        _log(f"generating into {store} for at most {gen_budget:.0f} s")
        reports = generate_dataset(spec, out=str(store), time_budget=gen_budget, log=_log)
        phase("generate", budget_s=round(gen_budget, 1), stores=[r.to_dict() for r in reports])
    else:
        phase("generate", skipped="no time left for generation; using what the store holds")
    return store


def _train_split(args, data, by: str, work: Path, out: Path, device: str, budget: float, phase) -> dict:
    """Phases 2-3 for one split: the fit MLP, the wrinkle GRU (to convergence on the validation
    motions or the budget), the baselines, then the evaluation; WORK/model_<by> keeps the run."""
    import shutil

    from simgen.learn import (FitConfig, WrinkleConfig, evaluate_garment, fit_linear_baselines, load_garment_model,
                              make_split, train_fit, train_wrinkle)

    t0 = time.monotonic()
    motions = {data.sequences[i].motion for i in make_split(data, by).train_sequences}
    kept = min(args.val_motions, max(len(motions) - 1, 0))   # a budget-cut store may have few
    if kept < args.val_motions:
        _log(f"split {by}: {len(motions)} training motions, so {kept} kept out for validation")
    split = make_split(data, by, validation_motions=kept)
    counts = {k: len(v) for k, v in split.test.items()}
    frames = sum(data.sequences[i].num_frames for i in split.train_sequences)
    _log(f"split {by}: train {len(split.train_sequences)} sequences ({frames} frames), validation "
         f"{len(split.validation)}, test {counts}")
    phase(f"load_{by}", train_sequences=len(split.train_sequences), train_frames=frames, test=counts,
          validation=len(split.validation), test_shapes=split.test_shapes)
    model_dir = work / f"model_{by}"
    old_split = model_dir / "split.json"
    if old_split.is_file() and json.loads(old_split.read_text()) != split.to_dict():
        _log(f"the dataset grew since the last run: the {by} split's training starts over")
        shutil.rmtree(model_dir)
    fit = train_fit(data, model_dir, split, config=FitConfig(epochs=args.fit_epochs), device=device,
                    time_budget=max(5.0, min(args.fit_budget, budget - args.eval_reserve - 30)))
    phase(f"train_fit_{by}", **fit.to_dict())
    wr_budget = budget - (time.monotonic() - t0) - args.eval_reserve - 20  # 20 s: baselines + packing
    wcfg = WrinkleConfig(hidden=args.hidden, window=args.window, batch_size=args.batch_size, epochs=args.epochs,
                         feature_mode=args.features, val_every=args.val_every,
                         patience=args.patience if split.validation else 0)
    _log(f"training the wrinkle GRU ({by} split) for at most {wr_budget:.0f} s")
    wr = train_wrinkle(data, model_dir, split, config=wcfg, device=device, time_budget=max(5.0, wr_budget),
                       checkpoint_every=60.0,
                       progress=lambda e, n, info: _log(f"epoch {e}: loss {info['loss']:.4g}, validation "
                                                        f"{info['val_cm']}") if e % 50 == 0 else None)
    phase(f"train_wrinkle_{by}", **wr.to_dict())
    fit_linear_baselines(data, model_dir, split, feature_mode=args.features)
    ev_dir = work / f"eval_{by}"
    metrics = evaluate_garment(model_dir, data, ev_dir, device=device, timing_frames=args.timing_frames,
                               inside_stride=args.inside_stride, max_sequences=args.eval_sequences)
    phase(f"evaluate_{by}")
    model = load_garment_model(model_dir, identity=data.identity, device=device)
    metrics["compare"] = _compare_npz(model, data, split, out / f"compare_{by}.npz", args.compare_frames,
                                      args.compare_sequences)
    _tar_fit_model(model_dir, out / f"fit_model_{by}.tar")
    for name in ("error_per_frame.png", "shape_generalization.png", "training.png"):
        if (ev_dir / name).is_file():
            (out / name.replace(".png", f"_{by}.png")).write_bytes((ev_dir / name).read_bytes())
    metrics.pop("plots", None)
    return metrics


def run(args) -> int:
    t0 = time.monotonic()
    deadline = t0 + args.total_budget
    out, work = Path(args.out), Path(args.work)
    out.mkdir(parents=True, exist_ok=True)
    work.mkdir(parents=True, exist_ok=True)
    report: dict = {"args": vars(args), "phases": {}, "splits": {}, "commit": os.environ.get("SIMGEN_COMMIT", "unknown")}

    def left() -> float:
        return deadline - time.monotonic()

    def phase(name: str, **info) -> None:
        report["phases"][name] = {"seconds": round(time.monotonic() - phase.start, 2), **info}
        phase.start = time.monotonic()
        _write_json(out / "metrics.json", report)

    phase.start = t0
    try:
        import torch

        torch.backends.cuda.matmul.allow_tf32 = True  # the 1500 x 13k output layer; fp32 accumulate
        torch.backends.cudnn.allow_tf32 = True
        device = args.device if args.device != "cuda" else "cuda:0"
        report["device"] = torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu"
        report["torch"] = torch.__version__
        store = _generate(args, work, left, phase)

        from simgen.learn import format_summary, load_garment_data

        data = load_garment_data(store, device=device)
        _log(f"data: {len(data.sequences)} sequences, {len(data.shapes)} shapes")
        phase("load", sequences=len(data.sequences), shapes=len(data.shapes), vertices=data.num_vertices)
        summaries = []
        for k, by in enumerate(args.splits):
            budget = left() / (len(args.splits) - k)      # what is left, shared by the splits still to run
            report["splits"][by] = _train_split(args, data, by, work, out, device, budget, phase)
            summaries.append(f"== split {by}\n" + format_summary(report["splits"][by]))
            _write_json(out / "metrics.json", report)
        phase("package")
        summary = "\n\n".join(summaries)
        (out / "summary.txt").write_text(summary + "\n\n" + json.dumps(report["phases"], indent=1) + "\n")
        print(summary)
        status = 0
    except Exception as exc:  # report what was done; the JSON says where it stopped
        report["error"] = f"{type(exc).__name__}: {exc}"
        report["traceback"] = traceback.format_exc()
        print(report["traceback"], file=sys.stderr)
        status = 1
    report["total_seconds"] = round(time.monotonic() - t0, 1)
    _write_json(out / "metrics.json", report)
    _log(f"done in {report['total_seconds']} s; results in {out}")
    return status


def plots_from(folder: Path) -> None:
    """Draw each split's plots from a returned metrics.json and fit_model_<split>.tar into
    FOLDER/<split>/ (CPU machine)."""
    from simgen.learn.plots import plot_all

    metrics = json.loads((folder / "metrics.json").read_text())
    # A folder from before --splits: one split's metrics at the top, fit_model.tar, plots into FOLDER.
    runs = metrics.get("splits") or {"": metrics}
    for by, split_metrics in runs.items():
        model_dir = None
        tar_path = folder / (f"fit_model_{by}.tar" if by else "fit_model.tar")
        if tar_path.is_file():
            with tarfile.open(tar_path) as tar:
                tar.extractall(folder / f"unpacked_{by}", filter="data")
            model_dir = folder / f"unpacked_{by}" / "model"
        (folder / by).mkdir(exist_ok=True)
        for p in plot_all(split_metrics, folder / by if by else folder, model_dir=model_dir):
            print(p)


def _compare_sequences(npz_path: Path) -> list[dict]:
    """The sequences of a compare_<split>.npz as float32 arrays [m]; a file from before several
    sequences (one sequence, no leading axis) reads as one."""
    z = np.load(npz_path)
    ids = np.atleast_1d(z["sequence"])
    names = ("ground_truth", "ours", "lbs", "body")
    stacked = {k: z[k].astype(np.float32).reshape((len(ids),) + z[k].shape[-3:]) for k in names}
    return [{"id": str(sid), **{k: stacked[k][i] for k in names}, "garment_faces": z["garment_faces"],
             "body_faces": z["body_faces"], "fps": float(z["fps"])} for i, sid in enumerate(ids)]


def usd_from(npz_path: Path, out: Path, video: bool) -> None:
    """Per sequence of a compare_<split>.npz: OUT/<stem>_<sequence>.usdc with simulation, model and
    LBS side by side, coloured by error; with ``video`` also the MP4 and a PNG of its middle frame
    (1920x720, from the front; needs pyvista and OpenGL)."""
    from simgen.io.usd import write_usd
    from simgen.learn.compare import side_by_side_tracks

    out.mkdir(parents=True, exist_ok=True)
    for c in _compare_sequences(npz_path):
        tracks, meta = side_by_side_tracks(c["body"], c["body_faces"], c["garment_faces"], c["ground_truth"],
                                           {"ours": c["ours"], "lbs": c["lbs"]})
        base = out / f"{npz_path.stem}_{c['id']}"
        err = meta["mean_error_cm"]
        print(write_usd(base.with_suffix(".usdc"), tracks, fps=c["fps"], metadata={"sequence": c["id"], **meta}))
        if video:
            from simgen.io.render import follow_cameras, render_frame, render_sequence

            size = (1920, 720)
            cams = follow_cameras(tracks, aspect=size[0] / size[1], fps=c["fps"], azimuth=0.0, elevation=5.0)
            title = (f"{c['id']}. Left: simulation; middle: ours, post-processed ({err['ours']:.2f} cm); right: LBS "
                     f"({err['lbs']:.2f} cm). Error: grey 0, orange 2 cm, red 4 cm")
            print(render_sequence(base.with_suffix(".mp4"), tracks, fps=c["fps"], size=size, camera=cams, title=title))
            mid = len(cams) // 2
            print(render_frame(base.with_suffix(".png"), tracks, camera=cams[mid], size=size, title=title, frame=mid,
                               fps=c["fps"]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, help="folder whose files come back (small)")
    ap.add_argument("--work", type=Path, default=Path("simgen-thesis"), help="store, models, state (stays)")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--spec", default="thesis-tshirt")
    ap.add_argument("--motions", nargs="+", default=DEFAULT_MOTIONS)
    ap.add_argument("--shapes", nargs="+", default=DEFAULT_SHAPES)
    ap.add_argument("--max-frames", type=int, default=150, help="frames kept per clip")
    ap.add_argument("--gen-batch", type=int, default=None, help="sequences per batched solver call")
    ap.add_argument("--substeps", type=int, default=None)
    ap.add_argument("--full", action="store_true", help="the preset's whole store (every motion, shape and frame)")
    ap.add_argument("--splits", nargs="+", default=["shape"], choices=["motion", "shape"],
                    help="trained and evaluated one after the other, each in WORK/model_<split>")
    ap.add_argument("--val-motions", type=int, default=2,
                    help="training motions kept out to pick the GRU's weights and stop it (0: none)")
    ap.add_argument("--patience", type=int, default=8, help="validations without a 1%% gain before the GRU stops")
    ap.add_argument("--total-budget", type=float, default=560.0, help="seconds for everything")
    ap.add_argument("--gen-budget", type=float, default=240.0)
    ap.add_argument("--min-train", type=float, default=120.0, help="seconds generation leaves to training at least")
    ap.add_argument("--fit-budget", type=float, default=30.0)
    ap.add_argument("--eval-reserve", type=float, default=240.0, help="seconds kept for evaluation and packing")
    ap.add_argument("--fit-epochs", type=int, default=2000)
    ap.add_argument("--epochs", type=int, default=2000, help="wrinkle GRU epochs (the budget usually ends it)")
    ap.add_argument("--hidden", type=int, default=1500)
    ap.add_argument("--window", type=int, default=90)
    ap.add_argument("--batch-size", type=int, default=128)
    ap.add_argument("--features", default="pose_velocity", choices=["pose", "pose_velocity"])
    ap.add_argument("--val-every", type=int, default=25)
    ap.add_argument("--timing-frames", type=int, default=100)
    ap.add_argument("--inside-stride", type=int, default=5)
    ap.add_argument("--eval-sequences", type=int, default=68,
                    help="at most this many sequences per test group (68: the 4 held-out motions at 17 shapes)")
    ap.add_argument("--compare-frames", type=int, default=60)
    ap.add_argument("--compare-sequences", type=int, default=2, help="held-out sequences in compare_<split>.npz")
    ap.add_argument("--plots-from", type=Path, help="CPU machine: draw the plots from a returned folder")
    ap.add_argument("--usd-from", type=Path, help="CPU machine: a compare_<split>.npz to turn into USD")
    ap.add_argument("--usd-out", type=Path, default=Path("compare"), help="folder of the USD (and MP4, PNG) files")
    ap.add_argument("--video", action="store_true", help="with --usd-from: also an MP4 and a PNG per sequence")
    args = ap.parse_args()
    if args.plots_from is not None:
        plots_from(args.plots_from)
        return 0
    if args.usd_from is not None:
        usd_from(args.usd_from, args.usd_out, args.video)
        return 0
    if args.out is None:
        ap.error("--out is required")
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
