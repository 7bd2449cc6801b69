"""Evaluation of a trained garment model against the thesis (section 4.4: Figs. 4.6, 4.7, Table 4.1).

:func:`evaluate_garment` compares, on the test groups of the split the model was trained on:

- per-vertex mean error [cm] per frame of the full model (with and without the collision
  post-process) beside the LBS baseline and the linear regressors (Fig. 4.7);
- error as the body shape leaves the training range, on a static pose (the rest-pose fit
  simulations S_c(beta, 0)) and on a motion (the held-out motion's sequences of every shape)
  (Fig. 4.6; the thesis sweeps the shape within one simulation, our stores hold one shape per
  simulation, so each point is one simulation);
- the share of garment vertices inside the body, counted as ``simgen dataset check`` counts its
  regular vertices (thesis Table 6.1): inside by the winding number and not at a self-intersection
  of the posed body (armpits, between the thighs: the solver's statistics' rule,
  :class:`simgen.learn.comparison.metrics.InsideCounter`), with and without the post-process, and
  of the simulation itself for reference;
- the energies of the predictions from ``simgen.physics`` (membrane, bending, gravity, contact)
  beside those of the simulation;
- the mean triangle strain of every sequence (:func:`triangle_strain`, thesis Table 6.2's
  "strain"), of the simulation and of each prediction, and the errors and strain per held-out
  clip, so that a clip with bad ground truth does not hide in a group's mean;
- inference time per frame (frame by frame, one garment, as the thesis's runtime loop) on the CPU
  and, when available, the GPU, with and without the post-process, and the model sizes, beside
  Table 4.1.

Everything goes into ``metrics.json``; :mod:`simgen.learn.plots` draws the figures from it.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from simgen._fileio import atomic_write_bytes
from simgen.errors import InputError
from simgen.learn.checkpoint import model_size_mb, read_config
from simgen.learn.comparison.metrics import InsideCounter
from simgen.learn.data import GarmentData, body_for_identity, make_split
from simgen.learn.features import motion_features
from simgen.learn.garment_model import (FIT_DIR, WRINKLE_DIR, GarmentModel, StreamState, lbs_baseline, linear_baseline, load_garment_model, load_linear_baselines,
                                        load_split)

__all__ = ["THESIS", "METHODS", "METHOD_LABELS", "evaluate_garment", "time_inference", "format_summary",
           "triangle_strain", "physics_terms", "cloth_rest", "METRICS_FILE"]

METRICS_FILE = "metrics.json"

#: Thesis Table 4.1 and section 4.4.3 (Intel Core i7-6700 CPU, Nvidia Titan X GPU; T-shirt of 8,710 triangles).
THESIS = {
    "ms_per_frame": {"without_postprocess": 1.51, "with_postprocess": 4.01},
    "ms_per_frame_std": {"without_postprocess": 0.28, "with_postprocess": 0.27},
    "size_mb": {"fit": 1.1, "wrinkle": 108.1},
    "hardware": "Intel Core i7-6700 CPU, Nvidia Titan X GPU",
    "garment_triangles": 8710,
    "epochs": 2000,
}

METHODS = ("model", "model_relaxed", "model_solver", "model_raw", "fit_only", "lbs", "lr_pose", "lr_shape_pose")
METHOD_LABELS = {
    "model": "ours: fit + wrinkle, post-processed",
    "model_relaxed": "ours: fit + wrinkle, metric post-process",
    "model_solver": "ours: fit + wrinkle, solver post-process",
    "model_raw": "ours: fit + wrinkle, no post-process",
    "fit_only": "ours: fit only (no wrinkle GRU)",
    "lbs": "LBS of the template",
    "lr_pose": "linear regression from pose (thesis LR)",
    "lr_shape_pose": "linear regression from shape + pose",
}
# The garments whose vertices inside the body and physics terms are reported, with their short labels.
SET_LABELS = {"ground_truth": "simulation (ground truth)", "model_raw": "ours, no post-process",
              "model": "ours, post-processed", "model_relaxed": "ours, metric post-process",
              "model_solver": "ours, solver post-process", "lbs": "LBS"}


def _vertex_error_cm(pred: torch.Tensor, gt: torch.Tensor) -> np.ndarray:
    """Mean over vertices of the Euclidean error, per frame [cm]: (T, V, 3) x2 -> (T,)."""
    return ((pred - gt).norm(dim=-1).mean(dim=-1) * 100).cpu().numpy().astype(np.float64)


def _identity(data: GarmentData) -> dict:
    return {"garment": dict(data.identity.get("garment", {})), "body": dict(data.identity.get("body", {}))}


# ------------------------------------------------------------------------------------ predictions
@torch.no_grad()
def _predict_all(model: GarmentModel, lrs: dict, betas, poses, trans, fps: float,
                 solver_post=None, body_vertices=None) -> dict[str, torch.Tensor]:
    """Every method's garment [m] (T, V, 3) for one sequence, plus 'moved' (T, V) of the post-process
    (the thesis's; "model_relaxed" is the metric post-process of the same raw prediction and
    "model_solver", with ``solver_post`` (a :class:`SolverPostProcess`), the solver's on the posed
    bodies ``body_vertices`` [m] (T, Vb, 3))."""
    dev = model.device
    b = torch.as_tensor(betas, dtype=torch.float32, device=dev)
    p = torch.as_tensor(poses, dtype=torch.float32, device=dev)
    t = torch.as_tensor(trans, dtype=torch.float32, device=dev)
    pred = model.predict(b, p, t, fps, postprocess=True)
    out = {"model": pred.vertices, "model_raw": pred.raw, "moved": pred.moved}
    out["model_relaxed"] = model.push_out_sequence(pred.raw, b, p, t, relax=True)[0]
    if solver_post is not None:
        out["model_solver"] = solver_post(pred.raw, body_vertices)
    a = pred.transforms
    out["fit_only"] = lbs_baseline_fit(model, b, a)
    out["lbs"] = lbs_baseline(model.template, b, a)
    for name, lr in lrs.items():
        f = motion_features(p, t, fps, lr.feature_mode)
        out[f"lr_{name}"] = linear_baseline(lr, model.template, b, f, a)
    return out


def _solver_post(data: GarmentData, body, warp_device: str, required: bool):
    """The :class:`SolverPostProcess` of ``data`` on its body; when the data lacks the solver's rest
    template, material or settings (data not read from a store): None, or the InputError if
    ``required``."""
    from simgen.learn.solver_post import SolverPostProcess

    try:
        return SolverPostProcess.from_data(data, body_for_identity(data.identity, body), device=warp_device)
    except InputError:
        if required:
            raise
        return None


def lbs_baseline_fit(model: GarmentModel, betas: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """T_c + R_G(beta) skinned: the model without its wrinkle regressor."""
    from simgen.learn.skinning import lbs_torch

    return lbs_torch(model.template.template_smoothed + model.fit(betas), model.template.skin_weights, transforms)


# ------------------------------------------------------------------------------------ physics
def physics_terms(data: GarmentData, runs: list[dict], body, device) -> dict:
    """Mean SNUG terms per frame [J] of the simulation and the predictions (``simgen.physics``).

    runs: [{"fps", "body_vertices" (T, Vb, 3), "sets": {name: positions (T, V, 3)}}]. The rest shape
    is the garment template the solver used, the contact term the solver's own parameters.
    Returns {name: {term: mean}} plus "terms_info".
    """
    from simgen.physics import BodySurface, evaluate_sequence
    from simgen.physics.sources import contact_params_from

    if data.material is None:
        return {"skipped": "the data carries no material (not read from a dataset store)"}
    solver = data.attrs.get("solver", {})
    params = contact_params_from(solver.get("config", solver))
    rest = cloth_rest(data)
    surface = BodySurface(body.faces, body.v_template)
    sums: dict[str, dict[str, list]] = {}
    for run in runs:
        for name, pos in run["sets"].items():
            report = evaluate_sequence(pos, run["body_vertices"], rest, surface, run["fps"], contact_params=params,
                                       device=device)
            for term, value in report.means().items():
                sums.setdefault(name, {}).setdefault(term, []).append(value)
    out = {name: {t: _mean(v) for t, v in terms.items()} for name, terms in sums.items()}
    out["terms_info"] = {"unit": "J per frame (mean over frames and sequences)", "sequences": len(runs),
                         "material": getattr(data.material, "name", str(data.material)),
                         "contact": {"margin": params.margin, "stiffness": params.stiffness, "power": params.power}}
    return out


def cloth_rest(data: GarmentData):
    """The garment's rest geometry as the solver had it (its rest template, else the template),
    float64; the material only sets the energies' stiffness (cotton when the data has none)."""
    from simgen.physics import ClothRest

    rest_shape = data.rest_template if data.rest_template is not None else data.template
    return ClothRest.from_mesh(rest_shape, data.faces, data.material or "cotton", dtype=torch.float64)


@torch.no_grad()
def triangle_strain(positions, rest) -> np.ndarray:
    """Mean triangle strain per frame, (T,), of positions [m] (T, V, 3): the mean over triangles of
    ||G||_F^2, G = (F^T F - I) / 2 the Green strain against ``rest`` (a ClothRest), the per-triangle
    term of thesis eq. 6.11, averaged as Table 6.2 reports "strain" (its definition is not stated
    there; this is ours). Dimensionless: a uniform stretch by s gives (s^2 - 1)^2 / 2."""
    from simgen.physics.membrane import green_strain

    g = green_strain(torch.as_tensor(positions).double(), rest)     # (T, F, 2, 2)
    return (g * g).sum(dim=(-1, -2)).mean(dim=-1).cpu().numpy()


def _per_clip(per_seq: dict, group: str) -> dict:
    """{motion: {sequences, frames, mean_error_cm, triangle_strain, inside_percent}} of one group's
    sequences, each a mean over the motion's sequences (one per shape) weighted by their frames (by
    their tested frames for inside_percent)."""
    clips: dict[str, list] = {}
    for row in per_seq.values():
        if row["group"] == group:
            clips.setdefault(row["motion"], []).append(row)
    out = {}
    for motion, rows in sorted(clips.items()):
        out[motion] = {"sequences": len(rows), "frames": int(sum(r["frames"] for r in rows))}
        for key, weight in (("mean_error_cm", "frames"), ("triangle_strain", "frames"),
                            ("inside_percent", "inside_frames")):
            w = np.array([r[weight] for r in rows], dtype=float)
            out[motion][key] = {m: float(np.dot(w, [r[key][m] for r in rows]) / w.sum()) for m in rows[0][key]}
    return out


# ------------------------------------------------------------------------------------ timing
@torch.no_grad()
def time_inference(model: GarmentModel, betas, poses, trans, fps: float, *, device, postprocess: bool,
                   relax: bool = False, frames: int = 100, warmup: int = 10, cuda_graph: bool = False) -> dict:
    """Milliseconds per frame of frame-by-frame inference of one garment (thesis Table 4.1).

    Per frame: body joint transforms, R_G, one GRU step, garment skinning; with the post-process
    also the posed body and the push-out (with ``relax``: the metric post-process). cuda_graph:
    replay the model's frame from a CUDA graph (:class:`simgen.learn.streaming.GraphedStream`; CUDA
    only), the inputs' copy into the graph included; the posed body and the post-process then run
    eagerly after it (:meth:`GarmentModel.finish_frame`). Returns {"mean_ms", "std_ms",
    "median_ms", "frames", "cuda_graph"}.
    """
    dev = torch.device(device)
    if cuda_graph and dev.type != "cuda":
        raise InputError("timing with a CUDA graph needs a CUDA device")
    if cuda_graph and postprocess and not hasattr(model, "finish_frame"):
        raise InputError(f"timing a {type(model).__name__} from a CUDA graph with a post-process needs a GarmentModel")
    model = model.to(dev)
    b = torch.as_tensor(betas, dtype=torch.float32, device=dev)
    p = torch.as_tensor(poses, dtype=torch.float32, device=dev)
    t = torch.as_tensor(trans, dtype=torch.float32, device=dev)
    n = len(p)
    if cuda_graph:
        from simgen.learn.streaming import GraphedStream

        stream = GraphedStream(model, fps)

        def frame(i):
            posed = stream.step(b[i:i + 1], p[i:i + 1], t[i:i + 1])
            if not postprocess:
                return posed
            return model.finish_frame(posed, model.body(b[i:i + 1], p[i:i + 1], t[i:i + 1])[0], relax=relax)
    else:
        state = StreamState()
        metric = {"relax": True} if relax else {}    # only GarmentModel.step has the metric post-process
        frame = lambda i: model.step(state, b[i:i + 1], p[i:i + 1], t[i:i + 1], fps,  # noqa: E731
                                     postprocess=postprocess, **metric)
    times = []
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    for k in range(warmup + frames):
        sync()
        t0 = time.perf_counter()
        frame(k % n)
        sync()
        if k >= warmup:
            times.append((time.perf_counter() - t0) * 1e3)
    a = np.asarray(times)
    return {"mean_ms": float(a.mean()), "std_ms": float(a.std()), "median_ms": float(np.median(a)),
            "frames": int(len(a)), "cuda_graph": bool(cuda_graph)}


# ------------------------------------------------------------------------------------ main entry
def _axis_of(betas: np.ndarray) -> tuple[int | None, float]:
    """(component, value) of a shape with at most one nonzero component; (None, 0) for others."""
    nz = np.flatnonzero(np.abs(betas) > 1e-6)
    if len(nz) == 0:
        return -1, 0.0
    if len(nz) == 1:
        return int(nz[0]), float(betas[nz[0]])
    return None, 0.0


def _spread(ids: list[str], data: GarmentData, limit: int | None) -> list[str]:
    """At most ``limit`` ids, taken round-robin over motions (every motion represented first)."""
    if limit is None or len(ids) <= limit:
        return ids
    by_motion: dict[str, list[str]] = {}
    for i in ids:
        by_motion.setdefault(data.sequences[i].motion, []).append(i)
    queues = [list(v) for _, v in sorted(by_motion.items())]
    out: list[str] = []
    while len(out) < limit:
        for q in queues:
            if q and len(out) < limit:
                out.append(q.pop(0))
    return sorted(out)


def _mean(values) -> float | None:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if v else None


def evaluate_garment(model_dir: str | Path, data: GarmentData, out_dir: str | Path | None = None, *, device="cpu",
                     body=None, timing: bool = True, timing_frames: int = 100, inside_stride: int = 5,
                     train_sequences: int = 4, physics_sequences: int = 4, max_sequences: int | None = None,
                     plots: bool = True, solver_postprocess: bool | None = None, progress=None) -> dict:
    """Evaluate the models in ``model_dir`` on ``data``; write OUT/metrics.json (and plots).

    device: where predictions run; inside_stride: test every N-th frame for vertices inside the body
    (a Warp winding-number query per frame); train_sequences: how many training sequences to score
    too (to see over-fitting); physics_sequences: how many held-out-motion sequences get the
    ``simgen.physics`` terms (0: none); max_sequences: at most this many sequences per test group
    (None: all); solver_postprocess: also score the solver post-process ("model_solver",
    :mod:`simgen.learn.solver_post`) where the data has the solver's settings (None: on a GPU only;
    on the CPU it takes about a second per frame of a 4k-vertex garment); progress(done, total) per
    sequence. Returns the metrics dict.
    """
    dev = torch.device(device)
    model = load_garment_model(model_dir, identity=_identity(data), body=body, device=dev)
    lrs = load_linear_baselines(model_dir, identity=_identity(data), device=dev)
    split = load_split(model_dir) or make_split(data, "motion")
    body_model = model.body
    warp_device = "cuda:0" if dev.type == "cuda" else "cpu"

    groups = {k: _spread([i for i in v if i in data.sequences], data, max_sequences) for k, v in split.test.items()}
    if train_sequences > 0:
        groups["train"] = _spread([i for i in split.train_sequences if i in data.sequences], data, train_sequences)
    groups = {k: v for k, v in groups.items() if v}
    if not groups:
        raise InputError("the dataset holds none of the model's test sequences")
    total = sum(len(v) for v in groups.values())

    wanted = dev.type == "cuda" if solver_postprocess is None else solver_postprocess
    solver_post = _solver_post(data, body, warp_device, solver_postprocess is True) if wanted else None
    methods = [m for m in METHODS if (not m.startswith("lr_") or m[3:] in lrs)
               and (m != "model_solver" or solver_post is not None)]
    per_seq: dict[str, dict] = {}
    group_frames: dict[str, dict[str, list]] = {}
    inside: dict[str, dict[str, list]] = {}
    physics_runs: list[dict] = []
    strain: dict[str, dict[str, list]] = {}
    rest = cloth_rest(data)
    body_np = body_for_identity(data.identity, body)  # the numpy BodyModel (body_model is its torch twin)
    inside_counter = InsideCounter(body_np, data.skin_weights, data.attrs.get("solver"), warp_device)
    done = 0
    for group, ids in groups.items():
        for sid in ids:
            s = data.sequences[sid]
            body_all = body_model(*(torch.as_tensor(a, device=dev) for a in (s.betas, s.poses, s.trans)))[0]
            preds = _predict_all(model, lrs, s.betas, s.poses, s.trans, s.fps, solver_post=solver_post,
                                 body_vertices=body_all)
            gt = torch.as_tensor(s.vertices, device=dev)
            errs = {m: _vertex_error_cm(preds[m], gt) for m in methods}
            moved = float(preds["moved"].float().mean()) if preds["moved"] is not None else 0.0
            per_seq[sid] = {"group": group, "motion": s.motion, "shape_id": s.shape_id,
                            "betas": [float(x) for x in s.betas[0]], "frames": s.num_frames, "fps": s.fps,
                            "error_cm_per_frame": {m: [round(float(x), 4) for x in e] for m, e in errs.items()},
                            "mean_error_cm": {m: float(e.mean()) for m, e in errs.items()},
                            "moved_by_postprocess": moved}
            for m, e in errs.items():
                group_frames.setdefault(group, {}).setdefault(m, []).extend(e.tolist())
            per_seq[sid]["triangle_strain"] = {}
            for m, x in (("ground_truth", gt), *((m, preds[m]) for m in methods)):
                frames_strain = triangle_strain(x, rest)
                per_seq[sid]["triangle_strain"][m] = float(frames_strain.mean())
                strain.setdefault(group, {}).setdefault(m, []).extend(frames_strain.tolist())
            # Vertices inside the body, every inside_stride-th frame.
            frames = list(range(0, s.num_frames, max(1, inside_stride)))
            bv = body_all[frames].cpu().numpy()
            seq_inside: dict[str, list] = {}
            for k, f in enumerate(frames):
                sets = {"ground_truth": s.vertices[f], **{m: preds[m][f].cpu().numpy() for m in SET_LABELS
                                                           if m != "ground_truth" and m in preds}}
                for m, frac in inside_counter.fractions(sets, bv[k]).items():
                    seq_inside.setdefault(m, []).append(frac)
                    inside.setdefault(group, {}).setdefault(m, []).append(frac)
            per_seq[sid]["inside_frames"] = len(frames)
            per_seq[sid]["inside_percent"] = {m: 100.0 * float(np.mean(v)) for m, v in seq_inside.items()}
            if group == "held_out_motion" and len(physics_runs) < physics_sequences:
                physics_runs.append({"fps": s.fps, "body_vertices": body_all.cpu().numpy(), "sets": {
                    "ground_truth": s.vertices, **{m: preds[m].cpu().numpy() for m in SET_LABELS if m in preds}}})
            done += 1
            if progress is not None:
                progress(done, total)

    summary = {}
    for group, by_method in group_frames.items():
        summary[group] = {"sequences": len(groups[group]), "frames": len(next(iter(by_method.values()))),
                          "error_cm": {m: float(np.mean(v)) for m, v in by_method.items()},
                          "inside_percent": {m: 100.0 * float(np.mean(v)) for m, v in inside.get(group, {}).items()},
                          "triangle_strain": {m: float(np.mean(v)) for m, v in strain[group].items()},
                          "per_clip": _per_clip(per_seq, group)}

    metrics = {
        "model_dir": str(model_dir), "dataset": data.source, "garment": data.identity.get("garment"),
        "body": data.identity.get("body"), "split": split.by, "test_shapes": split.test_shapes,
        "train_shapes": split.train_shapes, "methods": {m: METHOD_LABELS[m] for m in methods},
        "training": {name: read_config(Path(model_dir) / sub).get("training", {})
                     for name, sub in (("fit", FIT_DIR), ("wrinkle", WRINKLE_DIR))
                     if (Path(model_dir) / sub / "config.json").is_file()},
        "groups": summary, "sequences": per_seq,
        "shape_static": _shape_static(model, lrs, data, split, methods, solver_post=solver_post),
        "shape_motion": _shape_motion(per_seq, data, split, methods),
        "clearance_m": model.clearance,
        "thesis": THESIS,
    }
    if solver_post is not None:
        metrics["solver_postprocess"] = solver_post.report()
    if physics_sequences > 0:
        try:
            metrics["physics"] = physics_terms(data, physics_runs, body_np, dev) \
                if physics_runs else {"skipped": "no held-out-motion sequence"}
        except ImportError as exc:
            metrics["physics"] = {"skipped": f"simgen.physics is not available ({exc})"}
    metrics["size_mb"] = {"fit": model_size_mb(model.fit),
                          "wrinkle": model_size_mb(model.wrinkle) if model.wrinkle is not None else None,
                          **{f"lr_{k}": model_size_mb(v) for k, v in lrs.items()}}
    if timing:
        s = data.sequences[next(iter(groups.get("held_out_motion") or next(iter(groups.values()))))]
        devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
        metrics["timing"] = {}
        for d in devices:
            metrics["timing"][d] = {
                "without_postprocess": time_inference(model, s.betas, s.poses, s.trans, s.fps, device=d,
                                                      postprocess=False, frames=timing_frames),
                "with_postprocess": time_inference(model, s.betas, s.poses, s.trans, s.fps, device=d,
                                                   postprocess=True, frames=timing_frames),
                "with_metric_postprocess": time_inference(model, s.betas, s.poses, s.trans, s.fps, device=d,
                                                          postprocess=True, relax=True, frames=timing_frames),
                **({f"{key}_cuda_graph": time_inference(model, s.betas, s.poses, s.trans, s.fps, device=d,
                                                         postprocess=pp, relax=rx, frames=timing_frames,
                                                         cuda_graph=True)
                    for key, pp, rx in (("without_postprocess", False, False), ("with_postprocess", True, False),
                                        ("with_metric_postprocess", True, True))} if d == "cuda" else {}),
                "threads": torch.get_num_threads() if d == "cpu" else None,
                "device_name": torch.cuda.get_device_name() if d == "cuda" else _cpu_name(),
            }
        model.to(dev)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(out / METRICS_FILE, (json.dumps(metrics, indent=1) + "\n").encode())
        if plots:
            try:
                from simgen.learn.plots import plot_all

                metrics["plots"] = [str(p) for p in plot_all(metrics, out, model_dir=model_dir)]
            except ImportError as exc:  # e.g. no matplotlib on a GPU machine: draw them later from the JSON
                metrics["plots_skipped"] = f"{exc}"
    return metrics


def _cpu_name() -> str:
    import platform

    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


@torch.no_grad()
def _shape_static(model: GarmentModel, lrs: dict, data: GarmentData, split, methods, rest_frames: int = 30,
                  solver_post=None) -> dict:
    """Errors on the rest-pose fit simulations S_c(beta, 0) of every shape (Fig. 4.6, static pose).

    The wrinkle GRU is run for ``rest_frames`` frames of the rest pose and its last frame used (the
    static pose's steady state; the solver post-process runs on that frame alone).
    """
    rows = []
    dev = model.device
    for sid in sorted(data.shapes):
        entry = data.shapes[sid]
        if "vertices" not in entry:
            continue
        b = torch.as_tensor(entry["betas"], device=dev).reshape(1, -1)
        comp, value = _axis_of(entry["betas"])
        poses = np.zeros((rest_frames, 24, 3), dtype=np.float32)
        trans = np.zeros((rest_frames, 3), dtype=np.float32)
        preds = _predict_all(model, lrs, np.repeat(entry["betas"][None], rest_frames, 0), poses, trans, 30.0)
        if solver_post is not None:
            last = [torch.as_tensor(a[-1:], device=dev) for a in (poses, trans)]
            preds["model_solver"] = solver_post(preds["model_raw"][-1:], model.body(b, *last)[0])
        gt = torch.as_tensor(entry["vertices"], device=dev)[None]
        err = {m: float(_vertex_error_cm(preds[m][-1:], gt)[0]) for m in methods}
        rows.append({"shape_id": sid, "betas": [float(x) for x in entry["betas"]], "component": comp, "value": value,
                     "train": sid in split.train_shapes, "error_cm": err})
        del b
    return {"shapes": rows, "train_range": _train_range(data, split)}


def _train_range(data: GarmentData, split) -> dict:
    """Per shape component: [min, max] of its value over the training shapes."""
    if not split.train_shapes:
        return {}
    b = np.stack([data.shapes[s]["betas"] for s in split.train_shapes])
    return {str(c): [float(b[:, c].min()), float(b[:, c].max())] for c in range(b.shape[1])
            if np.any(np.abs(b[:, c]) > 1e-6)}


def _shape_motion(per_seq: dict, data: GarmentData, split, methods) -> dict:
    """Mean error per shape on the held-out motion with the most shapes (Fig. 4.6, on a motion)."""
    by_motion: dict[str, list[str]] = {}
    for sid, row in per_seq.items():
        if row["group"] in ("held_out_motion", "held_out_both"):
            by_motion.setdefault(row["motion"], []).append(sid)
    if not by_motion:
        return {}
    motion = max(sorted(by_motion), key=lambda m: len(by_motion[m]))
    rows = []
    for sid in sorted(by_motion[motion]):
        row = per_seq[sid]
        comp, value = _axis_of(np.asarray(row["betas"]))
        rows.append({"sequence": sid, "shape_id": row["shape_id"], "component": comp, "value": value,
                     "train": row["shape_id"] in split.train_shapes, "error_cm": row["mean_error_cm"]})
    return {"motion": motion, "shapes": rows, "train_range": _train_range(data, split)}


# ------------------------------------------------------------------------------------ text summary
def _cell(value, width: int, digits: int) -> str:
    """``value`` right-aligned in ``width`` characters with ``digits`` decimals, in exponent notation
    where the fixed form would not leave a blank before it (a diverged run's 1e20 stays readable)."""
    fixed = f"{value:{width}.{digits}f}"
    return fixed if fixed.startswith(" ") else f"{value:{width}.3e}"


def format_summary(metrics: dict) -> str:
    """A plain-text table of the headline numbers beside the thesis's."""
    lines = []
    groups = metrics.get("groups", {})
    names = list(groups)
    methods = list(metrics.get("methods", {}))
    head = f"{'mean vertex error [cm]':40s}" + "".join(f"{g:>18s}" for g in names)
    lines.append(head)
    lines.append("-" * len(head))
    for m in methods:
        lines.append(f"{METHOD_LABELS[m]:40s}" + "".join(
            _cell(groups[g]['error_cm'].get(m, float('nan')), 18, 3) for g in names))
    lines.append("")
    lines.append(f"{'vertices inside the body [%]':40s}" + "".join(f"{g:>18s}" for g in names))
    for m in SET_LABELS:
        lines.append(f"{SET_LABELS[m]:40s}" + "".join(
            _cell(groups[g].get('inside_percent', {}).get(m, float('nan')), 18, 3) for g in names))
    if all("triangle_strain" in groups[g] for g in names):
        lines.append("")
        lines.append(f"{'mean triangle strain ||G||_F^2':40s}" + "".join(f"{g:>18s}" for g in names))
        for m in ("ground_truth", *methods):
            label = "simulation (ground truth)" if m == "ground_truth" else METHOD_LABELS[m]
            lines.append(f"{label:40s}" + "".join(
                _cell(groups[g]['triangle_strain'].get(m, float('nan')), 18, 5) for g in names))
    clips = (groups.get("held_out_motion") or {}).get("per_clip") or {}
    if clips:
        lines.append("")
        lines.append(f"{'held-out clips (training shapes)':40s}{'ours [cm]':>14s}{'LBS [cm]':>14s}"
                     f"{'strain sim.':>14s}{'strain ours':>14s}{'ours, metric':>14s}{'ours, solver':>14s}"
                     f"{'inside sim.':>14s}{'inside raw':>14s}{'inside ours':>14s}")
        for motion, row in clips.items():
            err, st, ins = row["mean_error_cm"], row["triangle_strain"], row.get("inside_percent", {})
            lines.append(f"{motion:40s}{_cell(err['model'], 14, 3)}{_cell(err['lbs'], 14, 3)}" + "".join(
                _cell(st.get(k, float("nan")), 14, 5) for k in ("ground_truth", "model", "model_relaxed",
                                                                 "model_solver")) + "".join(
                _cell(ins.get(k, float("nan")), 14, 3) for k in ("ground_truth", "model_raw", "model")))
    phys = metrics.get("physics") or {}
    rows = [m for m in SET_LABELS if isinstance(phys.get(m), dict)]
    if rows:
        terms = ("strain", "bending", "collision", "inertia", "potential")
        lines.append("")
        lines.append(f"{'physics terms [J per frame]':40s}" + "".join(f"{t:>14s}" for t in terms))
        for m in rows:
            lines.append(f"{SET_LABELS[m]:40s}" + "".join(f"{phys[m].get(t, float('nan')):14.4g}" for t in terms))
    timing = metrics.get("timing") or {}
    if timing:
        lines.append("")
        lines.append(f"{'inference [ms/frame]':40s}{'w/o post-process':>18s}{'with post-process':>18s}"
                     f"{'metric p.-p.':>18s}")
        th = THESIS["ms_per_frame"]
        lines.append(f"{'thesis (i7-6700 + Titan X)':40s}{th['without_postprocess']:18.2f}{th['with_postprocess']:18.2f}"
                     f"{'-':>18s}")
        for d, row in timing.items():
            label = f"ours, {d} ({row.get('device_name') or ''})"[:40]
            metric = row.get("with_metric_postprocess", {}).get("mean_ms", float("nan"))
            lines.append(f"{label:40s}{row['without_postprocess']['mean_ms']:18.2f}"
                         f"{row['with_postprocess']['mean_ms']:18.2f}{metric:18.2f}")
            if "without_postprocess_cuda_graph" in row:
                graphed = [row.get(f"{k}_cuda_graph", {}).get("mean_ms", float("nan"))
                           for k in ("without_postprocess", "with_postprocess", "with_metric_postprocess")]
                lines.append(f"{'  the same, the model from a CUDA graph':40s}" + "".join(f"{v:18.2f}" for v in graphed))
    sp = metrics.get("solver_postprocess")
    if sp:
        lines.append("")
        lines.append(f"solver post-process: {sp['substeps']} substeps of {1e3 * sp['dt']:.2f} ms (simulated time) "
                     f"per frame; it took {sp['ms_per_frame']:.1f} ms per frame, {sp['chunk']} frames at a time; "
                     f"{sp.get('retried_frames', 0)} frames stepped again at half the substep, "
                     f"{sp['diverged_frames']} left raw; {sp.get('cg_per_substep', 0):.0f} CG iterations per "
                     f"substep")
    size = metrics.get("size_mb") or {}
    if size:
        lines.append("")
        lines.append(f"{'model size [MB]':40s}{'fit':>18s}{'wrinkle':>18s}")
        lines.append(f"{'thesis':40s}{THESIS['size_mb']['fit']:18.1f}{THESIS['size_mb']['wrinkle']:18.1f}")
        w = size.get("wrinkle")
        lines.append(f"{'ours':40s}{size['fit']:18.2f}{(w if w is not None else float('nan')):18.2f}")
    return "\n".join(lines)
