"""Training of the garment fit MLP, the wrinkle GRU and the linear baselines (thesis section 4.3.2).

Both networks: Adam, learning rate 1e-3, dropout 0.2, training data shuffled every epoch, mean
squared error on standardised displacements. The GRU is trained with truncated backpropagation
through time: a batch holds up to 128 whole sequences side by side; they are cut into consecutive
90-frame windows, each window is one optimiser step, and the GRU's hidden state is carried from one
window to the next (detached, so gradients stop at the window's start) -- exactly how the model
runs at inference, where the hidden state flows through the whole sequence.

Runs write into the model folder (see :mod:`simgen.learn.garment_model`): the model (weights +
config.json) at every checkpoint and at the end, ``log.csv`` (one row per epoch), optionally
TensorBoard events, and ``train_state.pt`` (model, optimiser, epoch, random state) from which a
run resumes. A time budget stops a run cleanly at a step boundary with everything saved.
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from simgen._fileio import atomic_write_bytes
from simgen.errors import InputError
from simgen.learn.checkpoint import save_model
from simgen.learn.data import GarmentData, Split, body_for_identity, garment_shape_directions, stack_sequences
from simgen.learn.features import feature_size, motion_features
from simgen.learn.garment_model import FIT_DIR, LR_DIRS, SPLIT_FILE, TEMPLATE_DIR, WRINKLE_DIR
from simgen.learn.models import GarmentFitMLP, GarmentTemplate, LinearRegressor, WrinkleGRU

__all__ = ["FitConfig", "WrinkleConfig", "TrainResult", "train_fit", "train_wrinkle", "fit_linear_baselines", "tbptt_batch",
           "save_template", "write_split", "STATE_FILE", "LOG_FILE"]

STATE_FILE = "train_state.pt"
LOG_FILE = "log.csv"


@dataclass
class FitConfig:
    """Garment fit MLP training (thesis defaults): hidden units, dropout, Adam learning rate,
    epochs (the thesis trains 2000), batch size (shapes per step), random seed."""

    hidden: int = 20
    dropout: float = 0.2
    lr: float = 1e-3
    epochs: int = 2000
    batch_size: int = 128
    seed: int = 0


@dataclass
class WrinkleConfig:
    """Wrinkle GRU training (thesis defaults): hidden units, dropout, Adam learning rate, epochs,
    batch size (sequences per batch), TBPTT window [frames], motion descriptor, seed, gradient-norm
    clip (None: no clipping, as the thesis), validation every N epochs (0: never), patience: with a
    validation split, stop once this many validations in a row have not lowered the validation
    error by CONVERGED_GAIN of its value at the last such gain (0: run every epoch)."""

    hidden: int = 1500
    dropout: float = 0.2
    lr: float = 1e-3
    epochs: int = 2000
    batch_size: int = 128
    window: int = 90
    feature_mode: str = "pose_velocity"
    seed: int = 0
    grad_clip: float | None = None
    val_every: int = 10
    patience: int = 0


#: A validation error this share below the reference counts as progress (WrinkleConfig.patience).
CONVERGED_GAIN = 0.01


@dataclass
class TrainResult:
    """What a run did: folder, epochs completed (in total, resumed ones included), optimiser steps of
    this call, seconds of this call, why it stopped ("epochs", "time budget" or "converged"), last
    training loss, the validation error [cm] of the saved model (with a validation split: the best,
    whose weights are saved, reached after best_epoch epochs; else the last held-out one)."""

    folder: Path
    epochs: int
    steps: int
    seconds: float
    stopped: str
    train_loss: float
    val_error_cm: float | None
    best_epoch: int | None = None

    def to_dict(self) -> dict:
        d = asdict(self)
        d["folder"] = str(self.folder)
        return d


# ------------------------------------------------------------------------------------ shared pieces
def _identity(data: GarmentData) -> dict:
    return {"garment": dict(data.identity.get("garment", {})), "body": dict(data.identity.get("body", {}))}


def save_template(data: GarmentData, out: str | Path, *, body=None) -> GarmentTemplate:
    """Write OUT/template/ (once; an existing one must be for the same garment and body)."""
    from simgen.learn.checkpoint import check_identity, read_config

    folder = Path(out) / TEMPLATE_DIR
    if (folder / "config.json").is_file():
        check_identity(read_config(folder), _identity(data), folder)
        from simgen.learn.checkpoint import load_model

        return load_model(folder, kind="garment_template")
    model = body_for_identity(data.identity, body)
    directions = garment_shape_directions(data.template, model)
    tpl = GarmentTemplate.from_arrays(data.template, data.template_smoothed, data.faces, data.skin_weights,
                                      directions)
    save_model(tpl, folder, identity=_identity(data), training={"dataset": data.source})
    return tpl


def write_split(split: Split, out: str | Path) -> None:
    """Write OUT/split.json; a folder whose models were trained on another split is refused."""
    path = Path(out) / SPLIT_FILE
    if path.is_file():
        old = json.loads(path.read_text(encoding="utf-8"))
        if old != split.to_dict():
            raise InputError(f"{path.parent} already holds models trained on another split ({old.get('by')!r}, "
                             f"{len(old.get('train_sequences', []))} training sequences); use a new --out folder")
        return
    Path(out).mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, (json.dumps(split.to_dict(), indent=2) + "\n").encode())


class _Logger:
    """CSV rows (appended across resumes) and optional TensorBoard scalars."""

    def __init__(self, folder: Path, fields: list[str], tensorboard: bool):
        self.path = folder / LOG_FILE
        self.fields = fields
        new = not self.path.is_file()
        self.fh = open(self.path, "a", newline="", encoding="utf-8")
        self.writer = csv.DictWriter(self.fh, fieldnames=fields)
        if new:
            self.writer.writeheader()
        self.tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except ImportError:
                raise InputError("--tensorboard needs the 'tensorboard' package: pip install tensorboard") from None
            self.tb = SummaryWriter(str(folder / "tensorboard"))

    def row(self, values: dict) -> None:
        self.writer.writerow({k: values.get(k, "") for k in self.fields})
        self.fh.flush()
        if self.tb is not None:
            for k, v in values.items():
                if k != "epoch" and isinstance(v, (int, float)) and math.isfinite(v):
                    self.tb.add_scalar(k, v, values["epoch"])

    def close(self) -> None:
        self.fh.close()
        if self.tb is not None:
            self.tb.close()


def _load_state(folder: Path, settings: dict, resume: bool, device) -> dict | None:
    path = folder / STATE_FILE
    if not path.is_file():
        return None
    if not resume:
        path.unlink()
        (folder / LOG_FILE).unlink(missing_ok=True)
        return None
    state = torch.load(path, map_location=device, weights_only=True)
    old = json.loads(state["settings"])

    def comparable(d: dict) -> dict:  # more (or fewer) epochs, another patience: the same run continues
        d = json.loads(json.dumps(d))
        d.get("config", {}).pop("epochs", None)
        d.get("config", {}).pop("patience", None)
        return d

    if comparable(old) != comparable(settings):
        old, settings = comparable(old), comparable(settings)
        flat_old = {**{k: v for k, v in old.items() if k != "config"}, **old.get("config", {})}
        flat_new = {**{k: v for k, v in settings.items() if k != "config"}, **settings.get("config", {})}
        diff = sorted(k for k in set(flat_old) | set(flat_new) if flat_old.get(k) != flat_new.get(k))
        raise InputError(f"{folder} holds a run with other settings ({', '.join(diff)} differ); pass --restart to "
                         f"start over or use a new --out folder")
    return state


def _save_state(folder: Path, model, optimizer, epoch: int, settings: dict, generator: torch.Generator,
                extra: dict | None = None) -> None:
    import io

    buf = io.BytesIO()
    torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(), "epoch": epoch,
                "settings": json.dumps(settings), "rng": generator.get_state(),
                "torch_rng": torch.get_rng_state(), **(extra or {})}, buf)
    atomic_write_bytes(folder / STATE_FILE, buf.getvalue())


def _device(device) -> torch.device:
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise InputError(f"--device {device!r} is not a torch device (cpu, cuda, cuda:N)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda was asked for but torch sees no CUDA device")
    return dev


# ------------------------------------------------------------------------------------ garment fit
def train_fit(data: GarmentData, out: str | Path, split: Split, *, config: FitConfig | None = None, device="cpu",
              time_budget: float | None = None, resume: bool = True, tensorboard: bool = False, body=None,
              progress=None) -> TrainResult:
    """Train R_G on the fit ground truth of the split's training shapes; write OUT/fit/.

    progress(epoch, epochs, info) after every epoch. Returns :class:`TrainResult`.
    """
    config = config or FitConfig()
    dev = _device(device)
    out = Path(out)
    write_split(split, out)
    save_template(data, out, body=body)
    folder = out / FIT_DIR
    folder.mkdir(parents=True, exist_ok=True)
    if not split.train_shapes:
        raise InputError("no training shapes with fit ground truth in the dataset")
    betas = torch.tensor(np.stack([data.shapes[s]["betas"] for s in split.train_shapes]), device=dev)
    fits = torch.tensor(np.stack([data.shapes[s]["fit"] for s in split.train_shapes]), device=dev)
    val_b = val_f = None
    if split.test_shapes:
        val_b = torch.tensor(np.stack([data.shapes[s]["betas"] for s in split.test_shapes]), device=dev)
        val_f = torch.tensor(np.stack([data.shapes[s]["fit"] for s in split.test_shapes]), device=dev)
    settings = {"config": asdict(config), "split": split.to_dict(), "identity": _identity(data)}
    torch.manual_seed(config.seed)
    model = GarmentFitMLP(betas.shape[1], data.num_vertices, hidden=config.hidden, dropout=config.dropout).to(dev)
    model.set_normalization(betas, fits)
    targets = model.normalize_targets(fits)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    generator = torch.Generator().manual_seed(config.seed)
    state = _load_state(folder, settings, resume, dev)
    start = 0
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        generator.set_state(state["rng"].cpu())
        torch.set_rng_state(state["torch_rng"].cpu())
        start = int(state["epoch"])
    log = _Logger(folder, ["epoch", "train_loss", "train_error_cm", "val_error_cm", "seconds"], tensorboard)
    t0, steps, stopped, loss_value, val_cm = time.monotonic(), 0, "epochs", float("nan"), None
    epochs_done = start
    try:
        for epoch in range(start, config.epochs):
            model.train()
            perm = torch.randperm(len(betas), generator=generator).to(dev)
            total = 0.0
            for s in range(0, len(perm), config.batch_size):
                idx = perm[s:s + config.batch_size]
                loss = (model.forward_normalized(betas[idx]) - targets[idx]).pow(2).mean()
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                total += float(loss.detach()) * len(idx)
                steps += 1
            loss_value = total / len(betas)
            epochs_done = epoch + 1
            model.eval()
            with torch.no_grad():
                train_cm = float((model(betas) - fits).norm(dim=-1).mean()) * 100
                if val_b is not None:
                    val_cm = float((model(val_b) - val_f).norm(dim=-1).mean()) * 100
            elapsed = time.monotonic() - t0
            log.row({"epoch": epochs_done, "train_loss": loss_value, "train_error_cm": train_cm,
                     "val_error_cm": val_cm if val_cm is not None else "", "seconds": round(elapsed, 3)})
            if progress is not None:
                progress(epochs_done, config.epochs, {"loss": loss_value, "train_cm": train_cm})
            if time_budget is not None and elapsed >= time_budget:
                stopped = "time budget"
                break
        _save_state(folder, model, optimizer, epochs_done, settings, generator)
        save_model(model, folder, identity=_identity(data), training={
            "dataset": data.source, "split": split.by, "epochs": epochs_done, "config": asdict(config),
            "train_shapes": split.train_shapes, "train_loss": loss_value, "val_error_cm": val_cm})
    finally:
        log.close()
    return TrainResult(folder, epochs_done, steps, time.monotonic() - t0, stopped, loss_value, val_cm)


# ------------------------------------------------------------------------------------ wrinkle GRU
@torch.no_grad()
def _wrinkle_val_error(model: WrinkleGRU, batch) -> float:
    """Mean per-vertex error [cm] of the unposed wrinkle prediction, each sequence run from rest."""
    model.eval()
    pred, _ = model(batch.betas, batch.features)
    err = (pred - batch.targets).norm(dim=-1).mean(dim=-1)  # (N, T)
    return float(err[batch.mask].mean()) * 100


def tbptt_batch(model: WrinkleGRU, inputs: torch.Tensor, targets: torch.Tensor, mask: torch.Tensor, optimizer, *,
                window: int, grad_clip: float | None = None, deadline: float | None = None):
    """Truncated backpropagation through time over one batch of sequences.

    inputs (N, T, B+F) and standardised targets (N, T, V*3) of N sequences side by side, mask
    (N, T) bool (False on padding). The sequences are cut into consecutive windows of ``window``
    frames; each window is one optimiser step; the GRU's hidden state is carried from one window
    into the next but detached, so the gradient stops at the window's start. deadline: a
    ``time.monotonic()`` value after which no new step starts. Returns (sum of loss x frames,
    frames, steps, stopped by the deadline).
    """
    hidden = None
    total, count, steps = 0.0, 0, 0
    for w0 in range(0, inputs.shape[1], window):
        sl = slice(w0, w0 + window)
        mw = mask[:, sl]
        frames = int(mw.sum())
        if frames == 0:
            break  # only padding is left
        z, hidden = model.forward_normalized(inputs[:, sl], hidden)
        hidden = hidden.detach()  # truncation: the state flows on, its gradient stops here
        loss = (z - targets[:, sl]).pow(2).mean(dim=-1)[mw].mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if grad_clip is not None:
            torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
        optimizer.step()
        total += float(loss.detach()) * frames
        count += frames
        steps += 1
        if deadline is not None and time.monotonic() >= deadline:
            return total, count, steps, True
    return total, count, steps, False


class _Selection:
    """The best validation so far (its error [cm], epoch and weights, kept on the model's device) and
    the count of validations since the error last fell by CONVERGED_GAIN (WrinkleConfig.patience)."""

    def __init__(self) -> None:
        self.best, self.best_epoch, self.weights = None, None, None
        self.reference, self.stale = None, 0

    def update(self, error: float, epoch: int, model) -> None:
        if self.best is None or error < self.best:
            self.best, self.best_epoch = error, epoch
            self.weights = {k: v.detach().clone() for k, v in model.state_dict().items()}
        if self.reference is None or error < self.reference * (1.0 - CONVERGED_GAIN):
            self.reference, self.stale = error, 0
        else:
            self.stale += 1

    def state(self) -> dict:
        return {"selection": {"best": self.best, "best_epoch": self.best_epoch, "reference": self.reference,
                              "stale": self.stale}, "best_model": self.weights or {}}

    def load(self, state: dict) -> None:
        sel = state.get("selection")
        if sel:
            self.best, self.best_epoch = sel["best"], sel["best_epoch"]
            self.reference, self.stale = sel["reference"], sel["stale"]
            self.weights = dict(state["best_model"]) or None


def train_wrinkle(data: GarmentData, out: str | Path, split: Split, *, config: WrinkleConfig | None = None,
                  device="cpu", time_budget: float | None = None, resume: bool = True, tensorboard: bool = False,
                  body=None, progress=None, checkpoint_every: float = 120.0) -> TrainResult:
    """Train R_L on the wrinkle ground truth of the split's training sequences; write OUT/wrinkle/.

    Validation error (unposed, cm) every ``config.val_every`` epochs: with ``split.validation`` on
    those sequences, which pick the saved weights (the best validation's) and, with
    ``config.patience``, stop the run ("converged"); without, on the held-out-motion sequences,
    logged only. progress(epoch, epochs, info) after every epoch.
    checkpoint_every [s]: save the model and the run state at the first epoch end after this long
    (and always at the end). A time-budget stop in the middle of an epoch keeps the weights of the
    steps done; a resumed run starts that epoch again.
    """
    config = config or WrinkleConfig()
    if config.window < 1 or config.batch_size < 1:
        raise InputError(f"window and batch size must be at least 1, got {config.window} and {config.batch_size}")
    dev = _device(device)
    out = Path(out)
    write_split(split, out)
    save_template(data, out, body=body)
    folder = out / WRINKLE_DIR
    folder.mkdir(parents=True, exist_ok=True)
    train = stack_sequences(data, split.train_sequences, feature_mode=config.feature_mode, target="wrinkle",
                            device=dev)
    if config.patience and not split.validation:
        raise InputError("a wrinkle GRU patience needs a split with validation motions (make_split's "
                         "validation_motions, --val-motions)")
    selecting = bool(split.validation)
    val_ids = [i for i in (split.validation if selecting else split.test.get("held_out_motion", []))
               if data.sequences[i].wrinkle is not None]
    val = stack_sequences(data, val_ids, feature_mode=config.feature_mode, target="wrinkle",
                          device=dev) if val_ids else None
    if config.patience and (val is None or config.val_every <= 0):
        raise InputError("a wrinkle GRU patience needs validations: val_every of at least 1 and validation "
                         "sequences with wrinkle ground truth")
    settings = {"config": asdict(config), "split": split.to_dict(), "identity": _identity(data)}
    torch.manual_seed(config.seed)
    model = WrinkleGRU(data.num_betas, feature_size(config.feature_mode), data.num_vertices, hidden=config.hidden,
                       dropout=config.dropout, feature_mode=config.feature_mode).to(dev)
    inputs = torch.cat([train.betas, train.features], dim=-1)
    model.set_normalization(inputs[train.mask], train.targets[train.mask])
    targets = model.normalize_targets(train.targets)  # (N, T, V*3)
    train.targets = None  # the standardised copy is all training needs
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    generator = torch.Generator().manual_seed(config.seed)
    state = _load_state(folder, settings, resume, dev)
    start, selection = 0, _Selection()
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        generator.set_state(state["rng"].cpu())
        torch.set_rng_state(state["torch_rng"].cpu())
        start = int(state["epoch"])
        selection.load(state)
    log = _Logger(folder, ["epoch", "steps", "train_loss", "val_error_cm", "seconds"], tensorboard)
    t0, steps, stopped, loss_value, val_cm = time.monotonic(), 0, "epochs", float("nan"), None
    lengths = torch.tensor(train.lengths)
    epochs_done = start

    def save() -> None:
        _save_state(folder, model, optimizer, epochs_done, settings, generator, selection.state())
        training = {"dataset": data.source, "split": split.by, "epochs": epochs_done, "config": asdict(config),
                    "train_sequences": len(split.train_sequences), "train_frames": int(lengths.sum()),
                    "train_loss": loss_value, "val_error_cm": val_cm,
                    "validation": ({"motions": sorted({data.sequences[i].motion for i in split.validation}),
                                    "sequences": len(split.validation), "best_epoch": selection.best_epoch}
                                   if selecting else None)}   # None: val_error_cm is the held-out motions'
        if selection.weights is None:
            save_model(model, folder, identity=_identity(data), training=training)
            return
        current = {k: v.detach().clone() for k, v in model.state_dict().items()}
        model.load_state_dict(selection.weights)      # the saved model is the best validation's
        try:
            save_model(model, folder, identity=_identity(data), training={**training, "val_error_cm": selection.best})
        finally:
            model.load_state_dict(current)            # training goes on from where it is

    out_of_time, last_save = False, t0
    try:
        for epoch in range(start, config.epochs):
            if config.patience and selection.stale >= config.patience:
                stopped = "converged"
                break
            model.train()
            perm = torch.randperm(len(lengths), generator=generator)
            total, count = 0.0, 0
            for s in range(0, len(perm), config.batch_size):
                idx = perm[s:s + config.batch_size]
                t_len = int(lengths[idx].max())
                idx_d = idx.to(dev)
                x, y, m = inputs[idx_d, :t_len], targets[idx_d, :t_len], train.mask[idx_d, :t_len]
                deadline = None if time_budget is None else t0 + time_budget
                b_total, b_count, b_steps, out_of_time = tbptt_batch(model, x, y, m, optimizer, window=config.window,
                                                                     grad_clip=config.grad_clip, deadline=deadline)
                total, count, steps = total + b_total, count + b_count, steps + b_steps
                if out_of_time:
                    break
            loss_value = total / max(count, 1)
            if not out_of_time:
                epochs_done = epoch + 1
            val_now = None
            if val is not None and config.val_every > 0 and (epochs_done % config.val_every == 0 or out_of_time
                                                             or epochs_done == config.epochs):
                val_cm = val_now = _wrinkle_val_error(model, val)
                if selecting and not out_of_time:     # whole epochs only: a resumed run redoes a cut one
                    selection.update(val_now, epochs_done, model)
            log.row({"epoch": epochs_done, "steps": steps, "train_loss": loss_value,
                     "val_error_cm": val_now if val_now is not None else "",
                     "seconds": round(time.monotonic() - t0, 3)})
            if progress is not None:
                progress(epochs_done, config.epochs, {"loss": loss_value, "val_cm": val_cm})
            if out_of_time:
                stopped = "time budget"
                break
            if time.monotonic() - last_save >= checkpoint_every:
                save()
                last_save = time.monotonic()
        save()
    finally:
        log.close()
    if selection.best is not None:
        val_cm = selection.best
    return TrainResult(folder, epochs_done, steps, time.monotonic() - t0, stopped, loss_value, val_cm,
                       selection.best_epoch)


# ------------------------------------------------------------------------------------ linear baselines
def fit_linear_baselines(data: GarmentData, out: str | Path, split: Split, *, feature_mode: str = "pose_velocity",
                         ridge: float = 1e-3, body=None) -> dict[str, Path]:
    """Fit the linear regressors from pose (thesis LR) and from shape + pose on the training
    sequences (target: the unposed displacement Delta_G + Delta_L); write OUT/lr_pose/ and
    OUT/lr_shape_pose/. Returns {inputs: folder}."""
    out = Path(out)
    write_split(split, out)
    save_template(data, out, body=body)
    ids = list(split.train_sequences)

    def chunks():
        for sid in ids:
            s = data.sequences[sid]
            feats = motion_features(torch.from_numpy(s.poses).double(), torch.from_numpy(s.trans).double(), s.fps,
                                    feature_mode).float()
            y = torch.from_numpy(np.asarray(s.wrinkle + data.shape_fit(s.shape_id)[None], dtype=np.float32))
            yield torch.from_numpy(s.betas), feats, y

    paths = {}
    for inputs, sub in LR_DIRS.items():
        lr = LinearRegressor(data.num_betas, feature_size(feature_mode), data.num_vertices, inputs=inputs,
                             feature_mode=feature_mode)
        lr.fit(chunks, ridge=ridge)
        paths[inputs] = save_model(lr, out / sub, identity=_identity(data), training={
            "dataset": data.source, "split": split.by, "ridge": ridge, "train_sequences": len(ids),
            "solver": "closed-form ridge least squares"})
    return paths
