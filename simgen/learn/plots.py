"""Figures of the garment-model evaluation, drawn from ``metrics.json`` (matplotlib, Agg backend).

- ``error_per_frame.png``: per-vertex mean error [cm] per frame on held-out motions, the model
  beside LBS and the linear regressors (thesis Fig. 4.7);
- ``shape_generalization.png``: error against the shape coefficient on a static pose and on a
  motion, the training range shaded (thesis Fig. 4.6);
- ``training.png``: training curves from the model folder's log.csv files.

The figures only read the metrics dict, so a GPU run can ship metrics.json and the figures can be
drawn anywhere (``plot_all(json.load(...), out)``). matplotlib is imported lazily.
"""

from __future__ import annotations

import csv
from pathlib import Path

__all__ = ["plot_all", "plot_error_per_frame", "plot_shape_generalization", "plot_training"]

_STYLE = {
    "model": dict(color="tab:blue", lw=1.8),
    "model_raw": dict(color="tab:blue", lw=1.0, ls=":"),
    "fit_only": dict(color="tab:cyan", lw=1.0, ls="--"),
    "lbs": dict(color="tab:red", lw=1.4),
    "lr_pose": dict(color="tab:orange", lw=1.4),
    "lr_shape_pose": dict(color="tab:green", lw=1.2, ls="--"),
}
_SHORT = {"model": "ours", "model_raw": "ours (no post-process)", "fit_only": "ours (fit only)", "lbs": "LBS",
          "lr_pose": "LR (pose)", "lr_shape_pose": "LR (shape + pose)"}
_FIG47 = ("model", "lbs", "lr_pose", "lr_shape_pose")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    from simgen._fileio import temp_path_beside

    tmp = temp_path_beside(path)
    fig.savefig(tmp, dpi=120, bbox_inches="tight")
    tmp.replace(path)
    return path


def plot_error_per_frame(metrics: dict, path: str | Path, *, max_panels: int = 4) -> Path | None:
    """Fig. 4.7: one panel per held-out motion (its zero-shape sequence when there is one)."""
    seqs = metrics.get("sequences", {})
    picks: dict[str, str] = {}
    for sid, row in sorted(seqs.items()):
        if row["group"] != "held_out_motion":
            continue
        cur = picks.get(row["motion"])
        zero = all(abs(b) < 1e-6 for b in row["betas"])
        if cur is None or (zero and not all(abs(b) < 1e-6 for b in seqs[cur]["betas"])):
            picks[row["motion"]] = sid
    if not picks:
        return None
    plt = _pyplot()
    chosen = [picks[m] for m in sorted(picks)][:max_panels]
    fig, axes = plt.subplots(len(chosen), 1, figsize=(8, 2.2 + 2.4 * len(chosen)), squeeze=False,
                             layout="constrained")
    for ax, sid in zip(axes[:, 0], chosen):
        row = seqs[sid]
        fps = float(row.get("fps", 30.0))
        for m in _FIG47:
            e = row["error_cm_per_frame"].get(m)
            if e is None:
                continue
            ax.plot([i / fps for i in range(len(e))], e, label=f"{_SHORT[m]} ({row['mean_error_cm'][m]:.2f})",
                    **_STYLE[m])
        ax.set_title(f"{row['motion']} (shape {row['shape_id']}), held-out motion", fontsize=10)
        ax.set_ylabel("mean vertex error [cm]")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"Generalisation to new motions ({metrics.get('garment', {}).get('name', '')}), cf. thesis Fig. 4.7",
                 fontsize=11)
    out = _save(fig, Path(path))
    plt.close(fig)
    return out


def _shape_panel(ax, block: dict, title: str, methods) -> bool:
    rows = [r for r in block.get("shapes", []) if r["component"] is not None]
    comps = sorted({r["component"] for r in rows if r["component"] >= 0})
    if not comps:
        return False
    zero = [r for r in rows if r["component"] == -1]
    markers = "osd^v<>"
    for k, c in enumerate(comps):
        pts = sorted([r for r in rows if r["component"] == c] + zero, key=lambda r: r["value"])
        xs = [r["value"] for r in pts]
        for m in methods:
            if m not in pts[0]["error_cm"]:
                continue
            ax.plot(xs, [r["error_cm"][m] for r in pts], marker=markers[k % len(markers)], ms=4,
                    label=f"{_SHORT[m]}, beta[{c}]", **_STYLE[m])
    rng = block.get("train_range", {})
    if rng:
        lo = min(v[0] for v in rng.values())
        hi = max(v[1] for v in rng.values())
        ax.axvspan(lo, hi, color="0.85", zorder=0, label="training shapes' range")
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("shape coefficient value")
    ax.set_ylabel("mean vertex error [cm]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    return True


def plot_shape_generalization(metrics: dict, path: str | Path) -> Path | None:
    """Fig. 4.6: error against beta on the static pose (fit simulations) and on a held-out motion."""
    static, motion = metrics.get("shape_static") or {}, metrics.get("shape_motion") or {}
    plt = _pyplot()
    fig, axes = plt.subplots(2, 1, figsize=(8, 7.5), layout="constrained")
    # At rest (T-pose) the wrinkle GRU and the linear regressors are far outside their training
    # poses; the fit regressor R_G is the part of the model trained on the rest-pose fits.
    ok1 = _shape_panel(axes[0], static, "static rest pose: fit regressor vs the rest-pose simulations",
                       ("fit_only", "lbs"))
    ok2 = _shape_panel(axes[1], motion, f"motion {motion.get('motion', '')!s} (one simulation per shape)",
                       ("model", "lbs", "lr_shape_pose"))
    if not (ok1 or ok2):
        plt.close(fig)
        return None
    fig.suptitle("Generalisation to new body shapes, cf. thesis Fig. 4.6", fontsize=11)
    out = _save(fig, Path(path))
    plt.close(fig)
    return out


def _read_log(path: Path) -> list[dict]:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def plot_training(model_dir: str | Path, path: str | Path) -> Path | None:
    """Training loss (and validation error) against epochs from FIT and WRINKLE log.csv files."""
    logs = {name: Path(model_dir) / name / "log.csv" for name in ("fit", "wrinkle")}
    logs = {k: v for k, v in logs.items() if v.is_file()}
    if not logs:
        return None
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(logs), figsize=(5.5 * len(logs), 3.8), squeeze=False, layout="constrained")
    for ax, (name, p) in zip(axes[0], logs.items()):
        rows = _read_log(p)
        ep = [int(r["epoch"]) for r in rows]
        ax.semilogy(ep, [float(r["train_loss"]) for r in rows], label="train loss (standardised MSE)")
        ax.set_xlabel("epoch")
        ax.set_title(f"{name}", fontsize=10)
        ax.grid(alpha=0.3)
        key = "val_error_cm"
        vals = [(e, float(r[key])) for e, r in zip(ep, rows) if r.get(key)]
        if vals:
            ax2 = ax.twinx()
            ax2.plot([v[0] for v in vals], [v[1] for v in vals], color="tab:red", marker=".", label="validation [cm]")
            ax2.set_ylabel("validation error [cm]", color="tab:red")
        ax.legend(fontsize=8, loc="upper right")
    out = _save(fig, Path(path))
    plt.close(fig)
    return out


def plot_all(metrics: dict, out_dir: str | Path, *, model_dir: str | Path | None = None) -> list[Path]:
    """Draw every figure the metrics allow into OUT; returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [plot_error_per_frame(metrics, out / "error_per_frame.png"),
             plot_shape_generalization(metrics, out / "shape_generalization.png")]
    if model_dir is not None:
        paths.append(plot_training(model_dir, out / "training.png"))
    return [p for p in paths if p is not None]
