"""compare_models(): the body of ``simgen eval compare``.

Every model folder given, LBS and the simulation itself are run on the held-out sequences of a
dataset store (its test motions; with ``test_shapes`` also the training motions on those shapes)
and measured the same way (no collision post-process on any method):

- vertex error [cm] per frame and the share of garment vertices inside the body (:mod:`.metrics`);
- the mean-curvature error [1/m] per frame against the simulation;
- the physics terms [J per frame] of :func:`simgen.learn.evaluate.physics_terms` (the store's own
  material and contact parameters, the solver's rest shape);
- inference time per frame (:func:`simgen.learn.evaluate.time_inference`, with warm-up), model
  size, training time (log.csv) and data-generation time (the store's metadata).

The results dict is JSON-ready; :mod:`.tables` turns it into the tables, :mod:`.outputs` writes them.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import torch

from simgen.errors import InputError
from simgen.learn.comparison import metrics as M
from simgen.learn.comparison.contestants import SIMULATION, lbs_contestant, load_contestants

__all__ = ["compare_models", "held_out_groups", "compare_sequence_ids", "pick_clips"]


def held_out_groups(data, test_shapes=None, max_sequences: int | None = None):
    """(split, {group: sequence ids}) of the comparison: the store's test motions ("held_out_motion")
    and, with test_shapes (shape ids), the training motions on those shapes ("held_out_shape") and
    the test motions on them ("held_out_both") (:func:`simgen.learn.data.make_split`); at most
    max_sequences per group, spread over motions."""
    from simgen.learn.data import make_split
    from simgen.learn.evaluate import _spread

    if not any(s.split == "test" for s in data.sequences.values()):
        raise InputError(f"dataset {data.source} holds no test motions to compare on (generate it with some of "
                         f"the library's test clips, `simgen motion list --split test`)")
    if max_sequences is not None and max_sequences < 1:
        raise InputError(f"--max-sequences must be at least 1, got {max_sequences}")
    split = make_split(data, "shape" if test_shapes else "motion", test_shapes=test_shapes or None,
                       require_train=False)
    groups = {g: _spread(ids, data, max_sequences) for g, ids in split.test.items() if g != "shape_sweep" and ids}
    return split, groups


def compare_sequence_ids(store, test_shapes=None) -> list[str]:
    """The sequences of a store that ``held_out_groups`` can use: its test motions and, with
    test_shapes, every sequence of those shapes (from the manifest; read only these)."""
    from simgen.dataset import open_dataset

    ds = open_dataset(store)
    if not ds.sequence_ids("test"):
        raise InputError(f"dataset {store} holds no test motions to compare on (generate it with some of the "
                         f"library's test clips, `simgen motion list --split test`)")
    shapes = set(test_shapes or ())
    return [i for i in ds.sequence_ids() if ds.sequence_info(i).get("split") == "test"
            or ds.sequence_info(i).get("shape_id") in shapes]


def pick_clips(groups: dict, data, count: int = 2) -> list[str]:
    """Up to ``count`` held-out clips for the USD and the video: different motions first, the
    zero shape (else the first) of each, held-out motions before held-out shapes."""
    picks, seen = [], set()
    for ids in groups.values():
        by_motion: dict[str, list[str]] = {}
        for sid in ids:
            by_motion.setdefault(data.sequences[sid].motion, []).append(sid)
        for motion, sids in sorted(by_motion.items()):
            zero = [i for i in sids if not np.any(np.abs(data.sequences[i].betas[0]) > 1e-6)]
            if motion not in seen and len(picks) < count:
                picks.append((zero or sids)[0])
                seen.add(motion)
    for ids in groups.values():  # fewer motions than clips: other shapes
        for sid in ids:
            if len(picks) < count and sid not in picks:
                picks.append(sid)
    return picks


def _aggregate(per_seq: dict, ids: list[str], keys: list[str]) -> dict:
    """Means over the frames of ``ids`` (errors, curvature, inside) and over the sequences (physics)."""
    out = {"sequences": len(ids), "frames": int(sum(per_seq[i]["frames"] for i in ids))}
    for field, src in (("error_cm", "error_cm_per_frame"), ("curvature_error", "curvature_error_per_frame")):
        out[field] = {k: M.finite_mean(v for i in ids for v in per_seq[i][src].get(k, [])) for k in keys
                      if any(k in per_seq[i][src] for i in ids)}
    out["inside_percent"] = {k: M.finite_mean(v for i in ids for v in per_seq[i]["_inside"].get(k, []))
                             for k in [SIMULATION, *keys]}
    out["inside_percent"] = {k: (None if v is None else 100.0 * v) for k, v in out["inside_percent"].items()}
    out["mean_abs_curvature"] = M.finite_mean(per_seq[i]["mean_abs_curvature"] for i in ids)
    phys = [per_seq[i]["physics"] for i in ids if per_seq[i].get("physics")]
    if phys:
        out["physics"] = {k: {t: M.finite_mean(p[k].get(t) for p in phys if k in p) for t in phys[0][k]}
                          for k in phys[0]}
    return out


def compare_models(model_dirs, data, out_dir: str | Path | None = None, *, test_shapes=None, device="cpu",
                   body=None, max_sequences: int | None = None, inside_stride: int = 1, timing_frames: int = 50,
                   warmup: int = 10, video: bool = True, progress=None) -> dict:
    """Compare model folders, LBS and the simulation on a dataset's held-out sequences; write OUT.

    model_dirs: folders of ``simgen train snug``, ``simgen train gru-l2`` or ``simgen train
    fit|wrinkle``; data: :class:`~simgen.learn.data.GarmentData` of a store (``load_garment_data``);
    test_shapes: shape ids held out too (else only the test motions); device: where the models run
    (and are timed); body: the BodyModel of the store (default: the bundled one, hash-checked);
    max_sequences: at most this many sequences per group; inside_stride: count vertices inside the
    body every N-th frame; timing_frames / warmup: frames timed after warm-up frames; video: also
    render compare.mp4; progress(done, total) per sequence. out_dir None: compute only.

    Returns the results dict (also OUT/compare.json with the tables): contestants, split, per
    sequence and per group errors [cm], curvature errors [1/m], inside [%], physics [J per frame],
    timing [ms/frame], generation time [s].
    """
    from simgen.learn.comparison.outputs import (OTHER_FILES, plot_error_per_frame, publish, staging, write_results,
                                                 write_tables, write_usd_and_video)
    from simgen.learn.comparison.tables import build_tables
    from simgen.learn.data import body_for_identity
    from simgen.learn.evaluate import time_inference
    from simgen.learn.train import _device

    if inside_stride < 1 or timing_frames < 1 or warmup < 0:
        raise InputError(f"--inside-stride and --timing-frames must be at least 1 and the warm-up at least 0, got "
                         f"{inside_stride}, {timing_frames}, {warmup}")
    dev = _device(device)
    split, groups = held_out_groups(data, test_shapes, max_sequences)
    body_model = body_for_identity(data.identity, body)
    contestants = load_contestants(model_dirs, data.identity, body=body_model, device=dev)
    contestants.append(lbs_contestant(data, body_model, dev))
    ids = [i for g in groups.values() for i in g]
    warnings = []
    motions = {data.sequences[i].motion for i in ids}
    for c in contestants:  # a model that saw what it is tested on is flagged under the error table
        seen = sorted(set(c.split.train_sequences) & set(ids)) if c.split is not None else []
        if seen:
            warnings.append(f"Warning: {c.label} was trained on {len(seen)} of the compared sequences (e.g. "
                            f"{seen[0]}): its split.json holds them out differently.")
        if c.kind == "snug" and motions & set(c.facts.get("motions") or ()):
            warnings.append(f"Warning: {c.label} was trained on the held-out motion(s) "
                            f"{', '.join(sorted(motions & set(c.facts['motions'])))}.")
    stage = staging(Path(out_dir)) if out_dir is not None else None  # a bad --out fails before the work
    try:
        results = _measure(data, split, groups, contestants, body_model, dev, inside_stride, progress)
        clips = results.pop("_clips")
        first = data.sequences[ids[0]]
        results["timing"] = {"device": str(dev), "device_name": _device_name(dev), "frames": timing_frames,
                             "warmup": warmup, "sequence": ids[0], "threads": torch.get_num_threads(),
                             "methods": {c.key: time_inference(c.stepper(), first.betas, first.poses, first.trans,
                                                               first.fps, device=dev, postprocess=False,
                                                               frames=timing_frames, warmup=warmup)
                                         for c in contestants}}
        if dev.type == "cuda":
            results["timing"]["methods_cuda_graph"] = {
                c.key: time_inference(c.stepper(), first.betas, first.poses, first.trans, first.fps, device=dev,
                                      postprocess=False, frames=timing_frames, warmup=warmup, cuda_graph=True)
                for c in contestants}
        results["generation"] = M.generation_seconds(data.source) if data.source else {
            "seconds": None, "reason": "the data was not read from a store"}
        results.update(warnings=warnings, inside_stride=inside_stride)
        for c, row in zip(contestants, results["contestants"]):
            row["train_seconds"] = M.training_seconds(c.logs) if c.logs else None
        results["criterion"] = _criterion(results)
        tables = build_tables(results)
        if stage is None:
            return results
        files = write_tables(tables, results, stage)
        try:
            files["plot"] = plot_error_per_frame(results, stage / "error_per_frame.png").name
        except ImportError as exc:  # no matplotlib: the tables still stand
            results["plot_skipped"] = str(exc)
        labels = {c.key: c.label for c in contestants}
        files.update(write_usd_and_video(clips, np.asarray(body_model.faces), data.faces, [c.key for c in contestants],
                                         labels, stage, video=video, identity=data.identity,
                                         video_order=[c.key for c in contestants if not c.ablation],
                                         meta={"dataset": str(data.source), "garment": data.garment_name}))
        files["results"] = "compare.json"
        results.update(files=files, usd_sequence=clips[0]["id"], video_clips=[c["id"] for c in clips])
        write_results(results, tables, stage)
        publish(stage, Path(out_dir), owned=[f"{t.name}{ext}" for t in tables for ext in (".md", ".json")]
                + list(OTHER_FILES))
        return results
    finally:
        if stage is not None and stage.exists():
            shutil.rmtree(stage, ignore_errors=True)


def _device_name(dev: torch.device) -> str:
    from simgen.learn.evaluate import _cpu_name

    return torch.cuda.get_device_name(dev) if dev.type == "cuda" else _cpu_name()


def _criterion(results: dict) -> str | None:
    """Thesis Fig. 5.6 on this data: is SNUG's mean-curvature error below the vertex-L2 GRU's?"""
    kinds = {c["key"]: c for c in results["contestants"]}
    curv = results["overall"]["curvature_error"]
    snug = [k for k, c in kinds.items() if c["kind"] == "snug" and not c["ablation"] and curv.get(k) is not None]
    l2 = [k for k, c in kinds.items() if c["kind"] == "gru_l2" and curv.get(k) is not None]
    if not snug or not l2:
        return None
    a, b = curv[snug[0]], curv[l2[0]]
    return f"{'met' if a < b else 'not met'} ({a:.3f} vs {b:.3f} 1/m)"


class _StageClock:
    """Wall seconds per stage of the per-sequence loop (synchronising the GPU at each lap)."""

    def __init__(self, dev: torch.device):
        import time

        self._now, self._sync = time.perf_counter, (torch.cuda.synchronize if dev.type == "cuda" else None)
        self._t, self._totals = 0.0, {}

    def start(self) -> None:
        self._t = self._now()

    def lap(self, stage: str) -> None:
        if self._sync is not None:
            self._sync()
        t = self._now()
        self._totals[stage] = self._totals.get(stage, 0.0) + t - self._t
        self._t = t

    def totals(self) -> dict:
        return {k: round(v, 2) for k, v in self._totals.items()}


@torch.no_grad()
def _measure(data, split, groups, contestants, body_model, dev, inside_stride: int, progress) -> dict:
    """Per-sequence and aggregated metrics (the results dict without timing and costs), plus "_clips"."""
    from simgen.body.torch_lbs import TorchBody
    from simgen.learn.evaluate import physics_terms

    tb = TorchBody(body_model, device=dev)
    solver = dict(data.attrs.get("solver") or {})
    warp_device = "cuda:0" if dev.type == "cuda" else "cpu"
    counter = M.InsideCounter(body_model, data.skin_weights, solver, warp_device)
    keys = [c.key for c in contestants]
    interior = ~M.boundary_vertices(data.faces, data.num_vertices)
    clip_ids = pick_clips(groups, data)
    total = sum(len(v) for v in groups.values())
    per_seq, clips, physics_info, done = {}, [], None, 0
    clock = _StageClock(dev)
    for group, ids in groups.items():
        for sid in ids:
            s = data.sequences[sid]
            clock.start()
            b, p, t = (torch.as_tensor(x, dtype=torch.float32, device=dev) for x in (s.betas, s.poses, s.trans))
            bv, _, a = tb(b, p, t)
            # On ``dev`` (the curvature of every method and frame is most of this loop's arithmetic).
            on_dev = {c.key: c.predict(b, p, t, s.fps, a) for c in contestants}
            preds = {k: x.cpu().numpy() for k, x in on_dev.items()}
            clock.lap("predict")
            gt = s.vertices
            gt_dev = torch.as_tensor(gt, device=dev)
            h_gt = M.mean_curvature(gt_dev, data.faces)
            row = {"group": group, "motion": s.motion, "shape_id": s.shape_id, "frames": s.num_frames, "fps": s.fps,
                   "betas": [float(x) for x in s.betas[0]],
                   "mean_abs_curvature": float(h_gt[:, torch.as_tensor(interior, device=dev)].abs().mean()),
                   "error_cm_per_frame": {}, "curvature_error_per_frame": {}}
            for k, x in preds.items():
                row["error_cm_per_frame"][k] = [round(float(e), 5) for e in
                                                np.linalg.norm(x - gt, axis=-1).mean(-1) * 100.0]
                row["curvature_error_per_frame"][k] = [round(float(e), 5) for e in M.curvature_error(
                    on_dev[k], gt_dev, data.faces, interior, reference_curvature=h_gt)]
            row["error_cm"] = {k: float(np.mean(v)) for k, v in row["error_cm_per_frame"].items()}
            row["curvature_error"] = {k: float(np.mean(v)) for k, v in row["curvature_error_per_frame"].items()}
            clock.lap("errors_and_curvature")
            bv_np = bv.cpu().numpy()
            inside: dict[str, list] = {}
            for f in range(0, s.num_frames, inside_stride):
                for k, frac in counter.fractions({SIMULATION: gt[f], **{k: x[f] for k, x in preds.items()}},
                                                 bv_np[f]).items():
                    inside.setdefault(k, []).append(frac)
            row["_inside"] = inside
            row["inside_percent"] = {k: 100.0 * float(np.mean(v)) for k, v in inside.items()}
            clock.lap("inside")
            phys = physics_terms(data, [{"fps": s.fps, "body_vertices": bv_np,
                                          "sets": {SIMULATION: gt, **preds}}], body_model, dev)
            clock.lap("physics")
            if "skipped" not in phys:
                physics_info = phys.pop("terms_info")
                row["physics"] = phys
            per_seq[sid] = row
            if sid in clip_ids:
                clips.append({"id": sid, "fps": s.fps, "body": bv_np, "ground_truth": gt, "predictions": preds,
                              "betas": s.betas, "poses": s.poses, "trans": s.trans})
            done += 1
            if progress is not None:
                progress(done, total)
    all_ids = [i for g in groups.values() for i in g]
    results = {
        "dataset": str(data.source), "garment": data.garment_name, "body": data.identity.get("body"),
        "device": str(dev),
        "split": {"by": split.by, "test_shapes": list(split.test_shapes), "groups": groups},
        "contestants": [c.to_dict() for c in contestants],
        "groups": {g: _aggregate(per_seq, v, keys) for g, v in groups.items()},
        "overall": _aggregate(per_seq, all_ids, keys),
        "physics_info": physics_info,
        "stage_seconds": clock.totals(),
        "_clips": sorted(clips, key=lambda c: clip_ids.index(c["id"])),
    }
    for row in per_seq.values():
        row.pop("_inside")
    results["sequences"] = per_seq
    return results
