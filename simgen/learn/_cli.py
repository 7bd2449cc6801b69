"""The bodies of `simgen train fit|wrinkle|gru-l2`, `simgen eval garment|compare` and `simgen export usd
--compare` (kept here so that simgen/cli.py holds only the option declarations)."""

from __future__ import annotations

from pathlib import Path

from simgen.errors import InputError

__all__ = ["run_train", "run_train_gru_l2", "run_eval_garment", "run_eval_compare", "run_export_compare"]


def _body(spec: str | None):
    if spec is None:
        return None
    from simgen.body import load

    return load(spec)


def _load_data(dataset: str, progress_factory, *, body=None, max_frames: int | None = None):
    from simgen.learn.data import load_garment_data

    progress, update = progress_factory(f"reading {dataset}", 1)
    with progress:
        return load_garment_data(dataset, body=body, max_frames=max_frames, progress=update)


def _split(data, out: Path, split: str | None, test_shapes: str | None, validation_motions: int | None = None):
    from simgen.learn.data import SPLIT_MODES, make_split
    from simgen.learn.garment_model import load_split

    if split is not None and split not in SPLIT_MODES:
        raise InputError(f"--split must be one of {', '.join(SPLIT_MODES)}, got {split!r}")
    shapes = [s.strip() for s in test_shapes.split(",") if s.strip()] if test_shapes else None
    existing = load_split(out)
    if existing is not None and split is None and shapes is None and validation_motions is None:
        missing = [i for i in existing.train_sequences if i not in data.sequences]
        if missing:
            raise InputError(f"{out} was trained on sequence {missing[0]!r}, which dataset {data.source} lacks")
        return existing
    by = split or (existing.by if existing is not None else "motion")
    validation = validation_motions
    if existing is not None:   # what is not given comes from the folder's split
        if shapes is None and by == existing.by == "shape":
            shapes = existing.test_shapes
        if validation is None:
            validation = sorted({data.sequences[i].motion for i in existing.validation if i in data.sequences})
    return make_split(data, by, test_shapes=shapes, validation_motions=validation)


def run_train(kind: str, *, dataset: str, out: Path, device: str, epochs: int | None, batch_size: int | None,
              hidden: int | None, dropout: float | None, lr: float | None, window: int | None, features: str | None,
              split: str | None, test_shapes: str | None, time_budget: float | None, restart: bool,
              tensorboard: bool, seed: int, baselines: bool, val_every: int | None, grad_clip: float | None,
              max_frames: int | None, body: str | None, echo, progress_factory, validation_motions: int | None = None,
              patience: int | None = None) -> None:
    """Train the fit MLP or the wrinkle GRU (+ linear baselines) into OUT."""
    from dataclasses import replace

    from simgen.learn.features import FEATURE_MODES
    from simgen.learn.train import FitConfig, WrinkleConfig, fit_linear_baselines, train_fit, train_wrinkle

    for name, value, low in (("--epochs", epochs, 1), ("--batch-size", batch_size, 1), ("--hidden", hidden, 1),
                             ("--window", window, 1), ("--max-frames", max_frames, 1),
                             ("--val-motions", validation_motions, 0), ("--patience", patience, 0)):
        if value is not None and value < low:
            raise InputError(f"{name} must be at least {low}, got {value}")
    if dropout is not None and not 0.0 <= dropout < 1.0:
        raise InputError(f"--dropout must be in [0, 1), got {dropout}")
    if lr is not None and not lr > 0:
        raise InputError(f"--lr must be positive, got {lr}")
    if time_budget is not None and not time_budget > 0:
        raise InputError(f"--time-budget must be positive seconds, got {time_budget}")
    if features is not None and features not in FEATURE_MODES:
        raise InputError(f"--features must be one of {', '.join(FEATURE_MODES)}, got {features!r}")
    model_body = _body(body)
    data = _load_data(dataset, progress_factory, body=model_body, max_frames=max_frames)
    the_split = _split(data, out, split, test_shapes, validation_motions)
    given = {"epochs": epochs, "batch_size": batch_size, "hidden": hidden, "dropout": dropout, "lr": lr,
             "seed": seed}
    if kind == "fit":
        config = replace(FitConfig(), **{k: v for k, v in given.items() if v is not None})
        progress, update = progress_factory("training the garment fit MLP", config.epochs)
        with progress:
            result = train_fit(data, out, the_split, config=config, device=device, time_budget=time_budget,
                               resume=not restart, tensorboard=tensorboard, body=model_body,
                               progress=lambda e, total, info: update(e, total))
        echo(f"fit: {result.epochs} epochs ({result.stopped}), {result.seconds:.1f} s; train loss "
             f"{result.train_loss:.4g}" + (f", held-out shapes {result.val_error_cm:.3f} cm"
                                          if result.val_error_cm is not None else "") + f"; saved {result.folder}")
        return
    given.update(window=window, feature_mode=features, val_every=val_every, grad_clip=grad_clip, patience=patience)
    config = replace(WrinkleConfig(), **{k: v for k, v in given.items() if v is not None})
    progress, update = progress_factory("training the wrinkle GRU", config.epochs)
    with progress:
        result = train_wrinkle(data, out, the_split, config=config, device=device, time_budget=time_budget,
                               resume=not restart, tensorboard=tensorboard, body=model_body,
                               progress=lambda e, total, info: update(e, total))
    if result.val_error_cm is None:
        val = ""
    elif the_split.validation:
        at = "" if result.best_epoch is None else f", epoch {result.best_epoch}"
        val = f", validation {result.val_error_cm:.3f} cm (unposed; the saved weights{at})"
    else:
        val = f", held-out motions {result.val_error_cm:.3f} cm (unposed)"
    echo(f"wrinkle: {result.epochs} epochs ({result.stopped}), {result.steps} steps, {result.seconds:.1f} s; train "
         f"loss {result.train_loss:.4g}{val}; saved {result.folder}")
    if baselines:
        paths = fit_linear_baselines(data, out, the_split, feature_mode=config.feature_mode, body=model_body)
        echo("linear baselines: " + ", ".join(str(p) for p in paths.values()))


def run_train_gru_l2(*, dataset: str, out: Path, device: str, epochs: int | None, batch_size: int | None,
                     hidden: int | None, lr: float | None, features: str | None, split: str | None,
                     test_shapes: str | None, time_budget: float | None, restart: bool, seed: int | None,
                     max_frames: int | None, body: str | None, echo, progress_factory,
                     validation_motions: int | None = None) -> None:
    """Train SNUG's network with vertex L2 on a dataset's training sequences into OUT/snug/."""
    from dataclasses import replace

    from simgen.learn.gru_l2 import train_gru_l2
    from simgen.learn.snug import SnugConfig

    if time_budget is not None and not time_budget > 0:
        raise InputError(f"--time-budget must be positive seconds, got {time_budget}")
    if max_frames is not None and max_frames < 1:
        raise InputError(f"--max-frames must be at least 1, got {max_frames}")
    if validation_motions is not None and validation_motions < 0:
        raise InputError(f"--val-motions must be 0 or more, got {validation_motions}")
    given = {"epochs": epochs, "batch_size": batch_size, "hidden": hidden, "lr": lr, "feature_mode": features,
             "seed": seed}
    config = replace(SnugConfig(), **{k: v for k, v in given.items() if v is not None})
    config.check()
    model_body = _body(body)
    data = _load_data(dataset, progress_factory, body=model_body, max_frames=max_frames)
    the_split = _split(data, out, split, test_shapes, validation_motions)
    progress, update = progress_factory("training the vertex-L2 GRU", config.epochs)
    with progress:
        result = train_gru_l2(data, out, the_split, config=config, device=device, time_budget=time_budget,
                              resume=not restart, body=model_body,
                              progress=lambda done, total, info: update(int(done), total))
    echo(f"vertex-L2 GRU: {result.epochs} epochs, stopped: {result.stopped}, train loss {result.train_loss:.4g} cm^2"
         + ("" if result.val_loss is None else f", validation {result.val_loss:.4g} cm^2"))
    echo(f"model: {result.folder}")


def run_eval_compare(*, models: str, dataset: str, out: Path, test_shapes: str | None, device: str,
                     max_sequences: int | None, max_frames: int | None, inside_stride: int, timing_frames: int,
                     video: bool, body: str | None, echo, progress_factory) -> dict:
    """Compare model folders, LBS and the simulation on the held-out sequences; write tables, plot, USD, MP4."""
    from simgen.learn.comparison import compare_models
    from simgen.learn.comparison.run import compare_sequence_ids
    from simgen.learn.data import load_garment_data

    folders = [Path(m.strip()) for m in models.split(",") if m.strip()]
    if not folders:
        raise InputError("--models needs at least one model folder")
    for folder in folders:
        if not folder.is_dir():
            raise InputError(f"--models {folder} is not a folder")
    if max_frames is not None and max_frames < 1:
        raise InputError(f"--max-frames must be at least 1, got {max_frames}")
    shapes = [s.strip() for s in test_shapes.split(",") if s.strip()] if test_shapes else None
    model_body = _body(body)
    ids = compare_sequence_ids(dataset, shapes)
    progress, update = progress_factory(f"reading {dataset}", 1)
    with progress:
        data = load_garment_data(dataset, body=model_body, sequence_ids=ids, max_frames=max_frames, progress=update)
    progress, update = progress_factory("comparing", 1)
    with progress:
        results = compare_models(folders, data, out, test_shapes=shapes, device=device, body=model_body,
                                 max_sequences=max_sequences, inside_stride=inside_stride,
                                 timing_frames=timing_frames, video=video, progress=update)
    echo((Path(out) / "compare.md").read_text(encoding="utf-8"))
    for name in sorted({f for v in results["files"].values() for f in (v if isinstance(v, list) else [v])}):
        echo(f"wrote: {Path(out) / name}")
    return results


def run_eval_garment(*, model: Path, dataset: str, out: Path, device: str, timing: bool, timing_frames: int,
                     inside_stride: int, max_frames: int | None, body: str | None, echo, progress_factory,
                     solver_pp: str = "auto") -> dict:
    """Evaluate a model folder on a dataset; print the summary table; write metrics.json and plots."""
    from simgen.learn.evaluate import evaluate_garment, format_summary
    from simgen.learn.train import _device

    if inside_stride < 1:
        raise InputError(f"--inside-stride must be at least 1, got {inside_stride}")
    if timing_frames < 1:
        raise InputError(f"--timing-frames must be at least 1, got {timing_frames}")
    if solver_pp not in ("auto", "on", "off"):
        raise InputError(f"--solver-pp must be on, off or auto, got {solver_pp!r}")
    dev = _device(device)
    if not Path(model).is_dir():
        raise InputError(f"--model {model} is not a folder")
    model_body = _body(body)
    data = _load_data(dataset, progress_factory, body=model_body, max_frames=max_frames)
    progress, update = progress_factory("evaluating", 1)
    with progress:
        metrics = evaluate_garment(model, data, out, device=dev, body=model_body, timing=timing,
                                   timing_frames=timing_frames, inside_stride=inside_stride,
                                   solver_postprocess={"auto": None, "on": True, "off": False}[solver_pp],
                                   progress=update)
    echo(format_summary(metrics))
    echo(f"metrics: {Path(out) / 'metrics.json'}")
    for p in metrics.get("plots", []):
        echo(f"plot: {p}")
    return metrics


def run_export_compare(*, out: Path, model: Path | None, dataset: str | None, sequence: str | None,
                       frames: int | None, body: str | None, echo, progress_factory) -> Path:
    """Write ground truth, prediction and LBS side by side (coloured by error) as one USD file."""
    from simgen import __version__
    from simgen.io.usd import write_usd
    from simgen.learn.compare import compare_tracks
    from simgen.learn.data import body_for_identity, load_garment_data
    from simgen.learn.garment_model import FIT_DIR, load_garment_model, load_split
    from simgen.learn.snug import SNUG_DIR

    if model is None or dataset is None:
        raise InputError("--compare needs --model DIR (a trained model folder) and --dataset DIR (its dataset store)")
    if frames is not None and frames < 1:
        raise InputError(f"--frames must be at least 1, got {frames}")
    model_body = _body(body)
    from simgen.dataset import open_dataset

    ds = open_dataset(dataset)
    if sequence is None:
        split = load_split(model)
        held = (split.test.get("held_out_motion") if split is not None else None) or ds.sequence_ids("test") \
            or ds.sequence_ids()
        if not held:
            raise InputError(f"dataset {dataset} holds no sequence")
        sequence = sorted(held)[0]
    data = load_garment_data(dataset, body=model_body, sequence_ids=[sequence], max_frames=frames)
    loader = load_garment_model
    if (Path(model) / SNUG_DIR).is_dir() and not (Path(model) / FIT_DIR).is_dir():
        from simgen.learn.snug import load_snug_model as loader  # a SNUG folder (`simgen train snug`)
    garment_model = loader(model, identity=data.identity, body=body_for_identity(data.identity, model_body))
    progress, update = progress_factory(f"comparing on {sequence}", 1)
    with progress:
        tracks, meta, fps = compare_tracks(garment_model, data, sequence, frames=frames)
        update(1, 1)
    meta.update({"simgen_version": __version__, "model": str(model), "dataset": str(dataset),
                 "garment": data.garment_name})
    path = write_usd(out, tracks, fps=fps, metadata=meta)
    echo(f"usd: {path}")
    echo(f"mean vertex error over {tracks[1].num_frames} frames: ours {meta['mean_error_cm']['ours']:.2f} cm, "
         f"LBS {meta['mean_error_cm']['lbs']:.2f} cm")
    return path
