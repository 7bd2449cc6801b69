"""Train the supervised garment model (thesis ch. 4) on a dataset store, then evaluate it.

    python examples/train_and_evaluate.py                     # datasets/thesis-tshirt -> runs/thesis-tshirt
    python examples/train_and_evaluate.py --dataset datasets/tiny --out runs/tiny \\
        --fit-epochs 100 --epochs 10 --hidden 64 --window 4   # a CPU-sized run

Steps, all in one model folder OUT:
1. Read the store (``examples/generate_dataset.py`` or ``simgen dataset generate``) and compute its
   ground truth: rest-pose fit displacements (eq. 4.4) and per-frame wrinkle displacements (eq. 4.5).
2. Split it: by default the thesis's split, where the library's test motions are held out.
3. Train the garment fit MLP R_G(beta) into OUT/fit/ and the wrinkle GRU R_L(beta, theta) into
   OUT/wrinkle/. Then fit the linear-regression baselines into OUT/lr_pose/ and OUT/lr_shape_pose/.
   Rerunning the same command resumes a run that was stopped; more epochs continue a finished one.
4. Evaluate against LBS and linear regression: errors per test group, vertices inside the body,
   physics terms, inference time and model size. This writes OUT/eval/metrics.json and, unless
   --no-plots, the figures (error per frame, shape generalisation, training curves).

Full size (the defaults: 2000 epochs each, a 1500-unit GRU, TBPTT windows of 90 frames, batches of
128, on the full thesis-tshirt store from examples/generate_dataset.py): not timed in full. On an
80-sequence subset of that store, BENCHMARKS.md measured 2000 GRU epochs in 46 s (25 training
sequences) and the evaluation in 159 s on one H100. The full store has 340 sequences, about 270 of
them for training, so expect tens of minutes on one H100. On a CPU, shrink it: --dataset
datasets/tiny with the options in the example above trains and evaluates in about a minute on a
2-core CPU (40 s of it the evaluation: physics terms, inference timing, plots).

Public API used: simgen.learn.load_garment_data, make_split, train_fit, train_wrinkle,
fit_linear_baselines, evaluate_garment, format_summary, FitConfig and WrinkleConfig.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from simgen.learn import FitConfig, WrinkleConfig  # the library's training defaults are the options' defaults

_FIT, _WRINKLE = FitConfig(), WrinkleConfig()


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
    p.add_argument("--dataset", default="datasets/thesis-tshirt", help="the dataset store")
    p.add_argument("--out", type=Path, default=Path("runs/thesis-tshirt"),
                   help="model folder (evaluation in OUT/eval)")
    p.add_argument("--device", default="auto", help="torch device: auto (cuda when present), cpu, cuda or cuda:N")
    p.add_argument("--split", default="motion", choices=("motion", "shape"),
                   help="motion: hold out the test motions (thesis); shape: also hold out the extreme shapes")
    p.add_argument("--max-frames", type=int, default=None, help="use only the first N frames of every sequence")
    p.add_argument("--fit-epochs", type=int, default=_FIT.epochs, help="fit MLP epochs")
    p.add_argument("--epochs", type=int, default=_WRINKLE.epochs, help="wrinkle GRU epochs")
    p.add_argument("--hidden", type=int, default=_WRINKLE.hidden, help="GRU units")
    p.add_argument("--window", type=int, default=_WRINKLE.window, help="TBPTT window [frames]")
    p.add_argument("--batch-size", type=int, default=_WRINKLE.batch_size, help="sequences per GRU batch")
    p.add_argument("--time-budget", type=float, default=None,
                   help="seconds per model: stop training cleanly (everything saved) after this long")
    p.add_argument("--restart", action="store_true", help="discard a saved run in OUT instead of resuming it")
    p.add_argument("--timing-frames", type=int, default=100, help="frames timed per configuration (0: no timing)")
    p.add_argument("--inside-stride", type=int, default=5, help="test every N-th frame for cloth inside the body")
    p.add_argument("--physics-sequences", type=int, default=4,
                   help="held-out sequences scored with the physics terms (0: none)")
    p.add_argument("--no-plots", action="store_true", help="write metrics.json only, no figures")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    import torch

    from simgen.errors import InputError
    from simgen.learn import (evaluate_garment, fit_linear_baselines, format_summary, load_garment_data, make_split,
                              train_fit, train_wrinkle)

    device = ("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device
    try:
        t0 = time.perf_counter()
        # On a GPU the ground truth is computed there too (float64), much faster for large stores.
        data = load_garment_data(args.dataset, max_frames=args.max_frames,
                                 device=device if device.startswith("cuda") else None)
        split = make_split(data, args.split)
        frames = sum(s.num_frames for s in data.sequences.values())
        print(f"{args.dataset}: {data.garment_name}, {len(data.sequences)} sequences ({frames:,} frames), "
              f"{len(data.shapes)} shapes; {len(split.train_sequences)} training sequences, test groups "
              f"{', '.join(f'{k} ({len(v)})' for k, v in split.test.items())}; read in "
              f"{time.perf_counter() - t0:.1f} s")

        fit = train_fit(data, args.out, split, device=device, time_budget=args.time_budget, resume=not args.restart,
                        config=dataclasses.replace(_FIT, epochs=args.fit_epochs))
        print(f"fit MLP: {fit.epochs} epochs ({fit.stopped}) in {fit.seconds:.1f} s, train loss "
              f"{fit.train_loss:.4g}; saved {fit.folder}")
        wrinkle = train_wrinkle(data, args.out, split, device=device, time_budget=args.time_budget,
                                resume=not args.restart,
                                config=dataclasses.replace(_WRINKLE, epochs=args.epochs, hidden=args.hidden,
                                                           window=args.window, batch_size=args.batch_size))
        held = "" if wrinkle.val_error_cm is None else f", held-out motions {wrinkle.val_error_cm:.3f} cm (unposed)"
        print(f"wrinkle GRU: {wrinkle.epochs} epochs ({wrinkle.stopped}) in {wrinkle.seconds:.1f} s, train loss "
              f"{wrinkle.train_loss:.4g}{held}; saved {wrinkle.folder}")
        baselines = fit_linear_baselines(data, args.out, split)
        print("linear baselines: " + ", ".join(str(p) for p in baselines.values()))

        eval_dir = args.out / "eval"
        metrics = evaluate_garment(args.out, data, eval_dir, device=device, timing=args.timing_frames > 0,
                                   timing_frames=max(args.timing_frames, 1), inside_stride=args.inside_stride,
                                   physics_sequences=args.physics_sequences, plots=not args.no_plots)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(format_summary(metrics))
    print(f"model: {args.out}")
    print(f"metrics: {eval_dir / 'metrics.json'}")
    for plot in metrics.get("plots", []):
        print(f"plot: {plot}")
    ours = {g: round(m["error_cm"]["model"], 3) for g, m in metrics["groups"].items()}
    print("mean vertex error of the model [cm]: " + json.dumps(ours))
    return 0


if __name__ == "__main__":
    sys.exit(main())
