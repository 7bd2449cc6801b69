"""`simgen eval softtissue`: SoftSMPL models against their ground truth, beside the thesis (ch. 3).

- Table 3.1: reconstruction error of the soft-tissue autoencoder against PCA of the same size, on
  each held-out group (motions, shapes, both). PCA is computed here at 25, 50 and 100 dimensions
  and at each model's code size, from the training displacements (at most
  :data:`~simgen.learn.softtissue.models.PCA_FRAMES` frames, evenly strided, as the autoencoder's
  initialisation); each model's autoencoder is compared at its own size.
- The regressor on every held-out sequence: mean vertex error of Delta against the ground truth
  (the unposed frame; the rig's part is the same for both), beside "no soft tissue" (Delta = 0, the
  body model alone); the mean vertex speed of the predicted and true Delta against the shape's
  body-mass proxy (thesis Fig. 3.7: heavier bodies move more).
- Runtime per frame of the whole pipeline (``SoftSMPL.predict``; thesis 4.8 ms) and model sizes.

Errors are mean per-vertex Euclidean distances [mm] over frames and vertices (the thesis's Table
3.1 measure); speeds are mean |Delta_t - Delta_{t-1}| x fps [m/s] over frames and vertices.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from simgen.errors import InputError

__all__ = ["evaluate_softtissue", "plot_speed_vs_mass", "softtissue_runtime", "THESIS_TABLE_3_1", "PCA_SIZES"]

#: Thesis Table 3.1 (Dyna, held-out sequences): mean vertex error [mm] by subspace size.
THESIS_TABLE_3_1 = {"pca": {25: 3.82, 50: 3.17, 100: 2.38}, "ae": {25: 3.02, 50: 2.58, 100: 2.09}}
THESIS_RUNTIME_MS = 4.8
PCA_SIZES = (25, 50, 100)


def _error_mm(a: np.ndarray, b: np.ndarray) -> float:
    return float(1e3 * np.linalg.norm(np.asarray(a, np.float64) - np.asarray(b, np.float64), axis=-1).mean())


def _pca_table(train, groups: dict, sizes: list[int]) -> dict:
    """{size: {group: mm}} of PCA reconstructions (projection on the training basis)."""
    from simgen.learn.softtissue.models import pca_basis, pca_frames

    X = pca_frames([s.displacements for s in train.sequences])
    V = X.shape[1]
    bases = {}
    for k in sizes:
        mean, comps, scales = pca_basis(X, k)
        bases[k] = (mean, comps[scales > 1e-9 * max(scales[0], 1e-30)])   # the data's own directions only
    out = {k: {} for k in sizes}
    for name, g in groups.items():
        sums, n = dict.fromkeys(sizes, 0.0), 0
        for s in g.sequences:   # one sequence at a time: a held-out group may not fit in memory at once
            Y = s.displacements.reshape(len(s.displacements), 3 * V).astype(np.float64)
            for k, (mean, comps) in bases.items():
                R = Y - mean
                sums[k] += _error_mm(((R @ comps.T) @ comps).reshape(-1, V, 3), R.reshape(-1, V, 3)) * len(Y)
            n += len(Y)
        for k in sizes:
            out[k][name] = sums[k] / max(n, 1)
    return out


@torch.no_grad()
def _ae_row(model, groups: dict, batch: int = 256) -> dict:
    row = {}
    dev = model.device
    for name, g in groups.items():
        errs, n = 0.0, 0
        for s in g.sequences:
            d = torch.as_tensor(s.displacements, dtype=torch.float32, device=dev)
            for i in range(0, len(d), batch):
                rec = model.soft_ae(d[i:i + batch])
                errs += float(torch.linalg.norm(rec - d[i:i + batch], dim=-1).mean()) * len(d[i:i + batch])
                n += len(d[i:i + batch])
        row[name] = 1e3 * errs / max(n, 1)
    return row


def _regressor_rows(model, groups: dict, body, density: float) -> list[dict]:
    from simgen.softtissue.model import body_mass_proxy
    from simgen.softtissue.simulate import mean_speed

    rows = []
    for name, g in groups.items():
        for s in g.sequences:
            pred = model.predict(s.betas, s.poses, s.trans, s.fps).cpu().numpy()
            betas = body.check_betas(s.betas[:body.num_betas])[0]
            rows.append({"group": name, "sequence": s.name, "motion": s.motion, "subject": s.subject,
                         "body_mass_proxy": float(body_mass_proxy(body, betas, density)),
                         "error_mm": _error_mm(pred, s.displacements),
                         "no_soft_tissue_mm": _error_mm(np.zeros_like(s.displacements), s.displacements),
                         "speed_true_mps": mean_speed(s.displacements, s.fps),
                         "speed_pred_mps": mean_speed(pred, s.fps)})
    return rows


def _training(model) -> dict:
    """How the model's regressor was trained: epochs, pose input, motion transfer, base folder."""
    from simgen.learn.checkpoint import read_config

    training = read_config(model.folder / "regressor").get("training", {})
    c = training.get("config", {})
    soft = read_config(model.folder / "soft_ae").get("training", {})
    epochs = training.get("epochs")
    return {"reg_epochs": int(c.get("reg_epochs", 1) if epochs is None else epochs),
            "ae_epochs": soft.get("epochs", c.get("ae_epochs")),
            "pose_input": model.regressor.pose_input, "motion_transfer": bool(c.get("motion_transfer", True)),
            "base": c.get("base", "")}


def _speed_summary(rows: list[dict]) -> dict:
    """Fig. 3.7 in numbers: mean |dDelta/dt| [m/s] predicted and true at the lightest and the heaviest
    shape (body-mass proxy) among the held-out sequences, and their ratios (heavy / light)."""
    if not rows:
        return {}
    mass = sorted({round(r["body_mass_proxy"], 6) for r in rows})
    out = {}
    for label, m in (("light", mass[0]), ("heavy", mass[-1])):
        sel = [r for r in rows if round(r["body_mass_proxy"], 6) == m]
        out[label] = {"body_mass_proxy": m, "true_mps": float(np.mean([r["speed_true_mps"] for r in sel])),
                      "pred_mps": float(np.mean([r["speed_pred_mps"] for r in sel]))}
    for k in ("true", "pred"):
        light = out["light"][f"{k}_mps"]
        out[f"{k}_heavy_over_light"] = out["heavy"][f"{k}_mps"] / light if light > 0 else None
    return out


def softtissue_runtime(model, seq, frames: int) -> dict:
    """Runtime of a loaded SoftSMPL ``model`` on ``frames`` frames of ``seq`` (anything with betas, poses,
    trans, fps, num_frames): ``ms_per_frame`` streamed (:meth:`SoftSMPL.stream`,
    one frame at a time, each result waited for: an avatar's use, the thesis's 4.8 ms) and
    ``sequence_ms_per_frame`` (``predict`` on the whole clip at once, divided by its frames)."""
    T = min(frames, seq.num_frames)
    args = (seq.betas, seq.poses[:T], seq.trans[:T], seq.fps)
    sync = torch.cuda.synchronize if model.device.type == "cuda" else (lambda: None)
    model.predict(*args)                                   # warm-up (allocation, kernels)
    warm = model.stream(seq.betas, seq.fps)
    for t in range(min(T, 3)):
        warm.step(seq.poses[t], seq.trans[t])
    sync()
    t0 = time.perf_counter()
    model.predict(*args)
    sync()
    whole = time.perf_counter() - t0
    stream = model.stream(seq.betas, seq.fps)
    t0 = time.perf_counter()
    for t in range(T):
        stream.step(seq.poses[t], seq.trans[t])
        sync()
    streamed = time.perf_counter() - t0
    sizes = {name: sum(p.numel() for p in getattr(model, name).parameters())
             for name in ("pose_ae", "soft_ae", "regressor")}
    return {"device": str(model.device), "frames": T, "ms_per_frame": 1e3 * streamed / T,
            "sequence_ms_per_frame": 1e3 * whole / T, "parameters": sizes,
            "megabytes_float32": 4 * sum(sizes.values()) / 1e6}


def evaluate_softtissue(models, data, out, *, body, device: str = "cpu", timing_frames: int = 100) -> dict:
    """Evaluate trained SoftSMPL folders on ``data`` (:class:`SoftTissueData`), held out as the
    first model was (its split.json; every model must share it); write softtissue_eval.json and .md
    and speed_vs_mass.png into ``out``; return the report (module docstring)."""
    from simgen.learn.softtissue.models import PCA_FRAMES
    from simgen.learn.softtissue.train import load_softtissue_model
    from simgen.softtissue.params import FleshParams

    folders = [Path(m) for m in models]
    if not folders:
        raise InputError("--models needs at least one trained SoftSMPL folder")
    loaded, split = [], None
    for f in folders:
        m = load_softtissue_model(f, identity={"body": {"id": body.name, "hash": body.hash}}, device=device)
        s = json.loads((m.folder / "split.json").read_text())
        held = (sorted(s["test_motions"]), sorted(s["test_subjects"]))
        if split is not None and held != split:
            raise InputError(f"{f} was trained with held-out {held}, {folders[0]} with {split}: evaluate models of "
                             f"one split together")
        split = held
        loaded.append((f, m))
    train, groups = data.split(*split)
    if not groups:
        raise InputError(f"the models hold out nothing of this data (test motions {split[0]}, subjects {split[1]})")
    sizes = sorted(set(PCA_SIZES) | {m.soft_ae.latent for _, m in loaded})
    report = {"data": data.source, "held_out": {"motions": split[0], "subjects": split[1]},
              "train_frames": int(sum(s.num_frames for s in train.sequences)),
              "pca_frames": int(min(PCA_FRAMES, sum(s.num_frames for s in train.sequences))),
              "pca_mm": _pca_table(train, groups, sizes),
              "models": [], "thesis": {"table_3_1_mm": THESIS_TABLE_3_1, "runtime_ms": THESIS_RUNTIME_MS}}
    longest = max((s for g in groups.values() for s in g.sequences), key=lambda s: s.num_frames)
    for f, m in loaded:
        trained = _training(m)
        rows = _regressor_rows(m, groups, body, FleshParams().density) if trained["reg_epochs"] > 0 else []
        report["models"].append({"folder": str(f), "ae_latent": m.soft_ae.latent, "ae_mm": _ae_row(m, groups),
                                 "training": trained, "sequences": rows, "speed_vs_mass": _speed_summary(rows),
                                 "timing": softtissue_runtime(m, longest, timing_frames)})
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "softtissue_eval.json").write_text(json.dumps(report, indent=2) + "\n")
    (out / "softtissue_eval.md").write_text(_markdown(report))
    try:
        plot_speed_vs_mass(report, out / "speed_vs_mass.png")
    except ImportError:   # a machine without matplotlib: plot_speed_vs_mass(json report) draws it later
        pass
    return report


def _markdown(r: dict) -> str:
    groups = list(next(iter(r["pca_mm"].values())))
    lines = [f"# SoftSMPL on {r['data']}", "",
             f"Held out: motions {', '.join(r['held_out']['motions']) or '-'}; shapes "
             f"{', '.join(r['held_out']['subjects']) or '-'}. PCA from {r['pca_frames']} of {r['train_frames']} "
             f"training frames. Mean vertex error [mm] (Table 3.1 to 3 significant digits).", "",
             "## Table 3.1: soft-tissue subspace", "",
             "| dims | " + " | ".join(f"PCA {g}" for g in groups) + " | autoencoder (" + ", ".join(groups)
             + ") | thesis PCA / AE (Dyna) |", "|---" * (len(groups) + 3) + "|"]
    for k, row in r["pca_mm"].items():
        ae = [m for m in r["models"] if m["ae_latent"] == int(k)]
        # regressors trained on one base share its autoencoder: list each result once
        ae_text = "; ".join(dict.fromkeys(", ".join(f"{v:.3g}" for v in m["ae_mm"].values()) for m in ae)) or "-"
        th = THESIS_TABLE_3_1
        thesis = f"{th['pca'][int(k)]} / {th['ae'][int(k)]}" if int(k) in th["pca"] else "-"
        lines.append(f"| {k} | " + " | ".join(f"{row[g]:.3g}" for g in groups) + f" | {ae_text} | {thesis} |")
    lines += _fig_3_7_lines(r)
    for m in r["models"]:
        t = m["timing"]
        if not m["sequences"]:
            lines += ["", f"## {m['folder']}: autoencoder only (regressor not trained)"]
            continue
        lines += ["", f"## Regressor: {m['folder']}", "",
                  f"{t['ms_per_frame']:.2f} ms per frame streamed on {t['device']} (thesis {THESIS_RUNTIME_MS} ms), "
                  f"{t['sequence_ms_per_frame']:.3f} ms per frame for the whole clip at once; "
                  f"{sum(t['parameters'].values()):,} parameters ({t['megabytes_float32']:.1f} MB in float32: "
                  + ", ".join(f"{k} {v:,}" for k, v in t["parameters"].items()) + ").", "",
                  "| group | sequence | body-mass proxy | error mm | no soft tissue mm | speed true / predicted [cm/s] |",
                  "|---|---|---:|---:|---:|---:|"]
        for s in m["sequences"]:
            lines.append(f"| {s['group']} | {s['sequence']} | {s['body_mass_proxy']:.1f} | {s['error_mm']:.3f} | "
                         f"{s['no_soft_tissue_mm']:.3f} | {100 * s['speed_true_mps']:.2f} / "
                         f"{100 * s['speed_pred_mps']:.2f} |")
    return "\n".join(lines) + "\n"


def _fig_3_7_lines(r: dict) -> list[str]:
    """The regressors side by side: error, and speed at the lightest and heaviest held-out shape."""
    models = [m for m in r["models"] if m["sequences"]]
    if not models:
        return []
    lines = ["", "## Regressors side by side (Fig. 3.7: heavier bodies move more)", "",
             "| model | pose input | motion transfer | error mm | no soft tissue mm | speed light true / pred [cm/s] "
             "| speed heavy true / pred [cm/s] | heavy / light true / pred |", "|---|---|---|---:|---:|---:|---:|---:|"]
    for m in models:
        sv, t = m["speed_vs_mass"], m["training"]
        ratio = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        lines.append(
            f"| {Path(m['folder']).name} | {t['pose_input']} | {'yes' if t['motion_transfer'] else 'no'} | "
            f"{np.mean([s['error_mm'] for s in m['sequences']]):.3f} | "
            f"{np.mean([s['no_soft_tissue_mm'] for s in m['sequences']]):.3f} | "
            f"{100 * sv['light']['true_mps']:.2f} / {100 * sv['light']['pred_mps']:.2f} | "
            f"{100 * sv['heavy']['true_mps']:.2f} / {100 * sv['heavy']['pred_mps']:.2f} | "
            f"{ratio(sv['true_heavy_over_light'])} / {ratio(sv['pred_heavy_over_light'])} |")
    return lines


def plot_speed_vs_mass(r: dict, path: Path) -> None:
    """Mean vertex speed against body mass: the ground truth and each regressor, one point per held-out
    sequence and a line through each body mass's mean (thesis Fig. 3.7). r: the report
    (softtissue_eval.json); path: the PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = [m for m in r["models"] if m["sequences"]]
    if not models:
        return
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)

    def draw(rows, key, label, **style):
        mass = np.array([s["body_mass_proxy"] for s in rows])
        speed = 100 * np.array([s[key] for s in rows])
        line = ax.plot(*zip(*[(m, speed[mass == m].mean()) for m in np.unique(mass)]), label=label, **style)[0]
        ax.scatter(mass, speed, s=8, alpha=0.35, color=line.get_color())

    draw(models[0]["sequences"], "speed_true_mps", "ground truth (simulation)", color="k", lw=2.5, marker="o")
    for m in models:
        draw(m["sequences"], "speed_pred_mps", f"{Path(m['folder']).name} (AE {m['ae_latent']})", marker="x")
    ax.set_xlabel("body-mass proxy [kg/m^2]")
    ax.set_ylabel("mean vertex speed of Delta [cm/s]")
    ax.set_title("Soft-tissue speed against body mass, held-out sequences (thesis Fig. 3.7)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
