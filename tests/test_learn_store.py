"""End to end on real simulations: the `tiny` dataset preset (tshirt_1k, 2 shapes x 2 motions x 5
frames, simulated here on the CPU in ~10 s), read into simgen.learn, trained and evaluated through the
CLI, compared in USD, and refused for another garment."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from simgen.cli import main
from simgen.garment import load_garment
from simgen.learn.solver_post import DEFAULT_SUBSTEPS, NEWTON_ITERATIONS


def run(argv, capsys):
    try:
        main(argv)
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    from simgen.dataset import generate_dataset

    out = tmp_path_factory.mktemp("learn_store") / "tiny"
    generate_dataset("tiny", out=str(out))
    return out


@pytest.fixture(scope="module")
def data(store):
    from simgen.learn import load_garment_data

    return load_garment_data(store)


def test_store_ground_truth_matches_the_torch_path_and_reconstructs(data):
    from simgen.body import load
    from simgen.learn import GarmentData, SequenceData, attach_ground_truth, lbs_torch

    assert data.garment_name == "tshirt_1k" and len(data.sequences) == 4 and set(data.shapes) == {"zero", "b1p2"}
    copy = GarmentData(identity=data.identity, template=data.template, template_smoothed=data.template_smoothed,
                       faces=data.faces, skin_weights=data.skin_weights, shapes=data.shapes,
                       sequences={k: SequenceData(**{**s.__dict__, "transforms": None, "wrinkle": None})
                                  for k, s in data.sequences.items()})
    attach_ground_truth(copy, load("open"))
    for sid, s in data.sequences.items():
        assert s.wrinkle is not None and s.split in ("train", "test")
        assert np.abs(copy.sequences[sid].transforms - s.transforms).max() < 1e-5
        assert np.abs(copy.sequences[sid].wrinkle - s.wrinkle).max() < 1e-5
        rest = data.template_smoothed + data.shape_fit(s.shape_id) + s.wrinkle
        posed = lbs_torch(torch.tensor(rest), torch.tensor(data.skin_weights), torch.tensor(s.transforms)).numpy()
        assert np.abs(posed - s.vertices).max() < 1e-5


def test_train_eval_compare_through_the_cli(store, tmp_path, capsys):
    model = tmp_path / "model"
    code, out, err = run(["train", "fit", "--dataset", str(store), "--out", str(model), "--epochs", "300"], capsys)
    assert code == 0, err
    assert "fit: 300 epochs" in out
    code, out, err = run(["train", "wrinkle", "--dataset", str(store), "--out", str(model), "--epochs", "60",
                          "--hidden", "32", "--window", "2", "--val-every", "20"], capsys)
    assert code == 0, err
    assert "wrinkle: 60 epochs" in out and "linear baselines" in out
    for sub in ("template", "fit", "wrinkle", "lr_pose", "lr_shape_pose"):
        assert (model / sub / "config.json").is_file() and (model / sub / "model.pt").is_file()
    # Rerunning the same command finds the run complete: nothing more to do.
    code, out, _ = run(["train", "wrinkle", "--dataset", str(store), "--out", str(model), "--epochs", "60",
                        "--hidden", "32", "--window", "2", "--val-every", "20", "--no-baselines"], capsys)
    assert code == 0 and "wrinkle: 60 epochs (epochs), 0 steps" in out

    ev = tmp_path / "eval"
    code, out, err = run(["eval", "garment", "--model", str(model), "--dataset", str(store), "--out", str(ev),
                          "--timing-frames", "5", "--inside-stride", "2", "--solver-pp", "on"], capsys)
    assert code == 0, err
    assert "mean vertex error [cm]" in out and "thesis (i7-6700 + Titan X)" in out
    metrics = json.loads((ev / "metrics.json").read_text())
    group = metrics["groups"]["held_out_motion"]
    assert group["sequences"] == 2 and group["frames"] == 10
    assert set(group["error_cm"]) >= {"model", "model_raw", "lbs", "lr_pose", "lr_shape_pose"}
    assert all(0 < v < 50 for v in group["error_cm"].values())
    assert group["inside_percent"]["model"] <= group["inside_percent"]["model_raw"]
    # The metric post-process: no vertex inside, and the prediction's triangle strain cut.
    assert group["inside_percent"]["model_relaxed"] <= group["inside_percent"]["model"]
    assert group["triangle_strain"]["model_relaxed"] < 0.5 * group["triangle_strain"]["model_raw"]
    # The solver post-process (the store's own material and settings): out of the body too, and the
    # cloth's metric kept closer than the metric post-process keeps it.
    assert group["inside_percent"]["model_solver"] <= group["inside_percent"]["model"]
    assert group["triangle_strain"]["model_solver"] < group["triangle_strain"]["model_relaxed"]
    assert metrics["solver_postprocess"]["frames"] > 0 and f"solver post-process: {DEFAULT_SUBSTEPS} substeps" in out
    # its own Newton iterations, not the store's (three since the solver's default changed)
    assert metrics["solver_postprocess"]["newton_per_substep"] == NEWTON_ITERATIONS
    # Strain and the per-clip rows: every method and the simulation; the clips' frame-weighted
    # errors average back to the group's.
    assert set(group["triangle_strain"]) == {"ground_truth", *group["error_cm"]}
    assert all(v >= 0 for v in group["triangle_strain"].values())
    clips = group["per_clip"]
    assert sum(c["sequences"] for c in clips.values()) == group["sequences"]
    frames = sum(c["frames"] for c in clips.values())
    assert sum(c["frames"] * c["mean_error_cm"]["model"] for c in clips.values()) / frames == pytest.approx(
        group["error_cm"]["model"], rel=1e-6)
    # the clips' inside shares, weighted by their tested frames, average back to the group's too
    tested = {c: sum(r["inside_frames"] for r in metrics["sequences"].values()
                     if r["motion"] == c and r["group"] == "held_out_motion") for c in clips}
    for m in ("ground_truth", "model_raw", "model"):
        assert sum(tested[c] * clips[c]["inside_percent"][m] for c in clips) / sum(tested.values()) == pytest.approx(
            group["inside_percent"][m], rel=1e-6, abs=1e-9)
    assert "mean triangle strain" in out and "held-out clips" in out and "inside raw" in out
    # On the (tiny) training set the model fits the simulations far better than LBS of the template.
    train = metrics["groups"]["train"]["error_cm"]
    assert train["model_raw"] < 0.5 * train["lbs"]
    assert metrics["timing"]["cpu"]["with_postprocess"]["mean_ms"] > 0
    assert metrics["timing"]["cpu"]["with_metric_postprocess"]["mean_ms"] > 0
    v = load_garment("tshirt_1k").num_vertices
    assert metrics["size_mb"]["fit"] == pytest.approx((3 * v * 21 + 10 * 20 + 20) * 4 / 1e6)
    assert len(metrics["shape_static"]["shapes"]) == 2 and metrics["shape_motion"]["motion"] == "walk_fast"
    for name in ("error_per_frame.png", "shape_generalization.png", "training.png"):
        assert (ev / name).stat().st_size > 10_000

    usd = tmp_path / "compare.usdc"
    code, out, err = run(["export", "usd", "--compare", "--model", str(model), "--dataset", str(store),
                          "--out", str(usd)], capsys)
    assert code == 0, err
    from simgen.io.usd import read_usd_meshes, validate_usd

    meshes = read_usd_meshes(usd)
    assert set(meshes) == {f"{k}_{w}" for k in ("body", "garment") for w in ("ground_truth", "ours", "lbs")}
    assert meshes["garment_ours"].colors is not None and meshes["garment_ours"].num_frames == 5
    gt, ours = meshes["garment_ground_truth"].points, meshes["garment_ours"].points
    assert ours[..., 0].min() > gt[..., 0].max()  # side by side, no overlap
    assert validate_usd(usd) == []


def test_a_model_for_another_garment_is_refused(store, data, tmp_path, capsys):
    from simgen.learn import FitConfig, make_split, train_fit

    model = tmp_path / "model"
    train_fit(data, model, make_split(data, "motion"), config=FitConfig(epochs=2))
    other = tmp_path / "other"
    shutil.copytree(model, other)
    for sub in ("template", "fit"):
        cfg_path = other / sub / "config.json"
        cfg = json.loads(cfg_path.read_text())
        cfg["garment"] = {"name": "dress_1k", "hash": "0" * 64}
        cfg_path.write_text(json.dumps(cfg))
    code, out, err = run(["eval", "garment", "--model", str(other), "--dataset", str(store), "--out",
                          str(tmp_path / "ev"), "--no-timing"], capsys)
    assert code == 2
    assert "trained for garment 'dress_1k'" in err and "not for 'tshirt_1k'" in err
    assert "Traceback" not in err


def test_a_snug_model_plays_beside_the_simulation(store, tmp_path, capsys):
    # A SNUG folder (snug/, no fit/) is read as SNUG by `export usd --compare`: its prediction sits
    # beside the ground truth and LBS like the supervised model's.
    from simgen.learn.snug import SnugConfig, train_snug

    config = SnugConfig(hidden=16, layers=1, batch_size=2, window_stride=90, val_windows=0, epochs=1)
    train_snug("tshirt_1k", tmp_path / "snug_model", motions=["walk"], config=config)
    usd = tmp_path / "snug.usdc"
    code, out, err = run(["export", "usd", "--compare", "--model", str(tmp_path / "snug_model"), "--dataset",
                          str(store), "--out", str(usd)], capsys)
    assert code == 0, err
    from simgen.io.usd import read_usd_meshes

    meshes = read_usd_meshes(usd)
    assert "garment_ours" in meshes and meshes["garment_ours"].num_frames == 5


def test_train_cli_validation_options_reach_the_split_and_the_run(store, tmp_path, capsys):
    # The store has one training motion: none can be kept for validation, and patience needs one.
    code, _, err = run(["train", "wrinkle", "--dataset", str(store), "--out", str(tmp_path / "a"),
                        "--val-motions", "1"], capsys)
    assert code != 0 and "1 validation motions asked for, but the split has 1 training motions" in err
    code, _, err = run(["train", "wrinkle", "--dataset", str(store), "--out", str(tmp_path / "b"), "--epochs", "2",
                        "--hidden", "8", "--patience", "3"], capsys)
    assert code != 0 and "patience needs a split with validation motions" in err


def test_per_clip_weights_errors_by_frames_and_inside_shares_by_tested_frames():
    from simgen.learn.evaluate import _per_clip

    def row(group, frames, tested, err, inside):
        return {"group": group, "motion": "hop", "frames": frames, "inside_frames": tested,
                "mean_error_cm": {"model": err}, "triangle_strain": {"model": 0.0}, "inside_percent": {"model": inside}}

    # tested frames not in proportion to frames (2 and 2 of 10 and 30), and a train row left out
    seqs = {"a": row("held_out_motion", 10, 2, 1.0, 10.0), "b": row("held_out_motion", 30, 2, 3.0, 2.0),
            "c": row("train", 100, 50, 9.0, 90.0)}
    (clip,) = _per_clip(seqs, "held_out_motion").values()
    assert clip["sequences"] == 2 and clip["frames"] == 40
    assert clip["mean_error_cm"]["model"] == pytest.approx((10 * 1.0 + 30 * 3.0) / 40)
    assert clip["inside_percent"]["model"] == pytest.approx((2 * 10.0 + 2 * 2.0) / 4)


def test_summary_columns_stay_apart_for_a_diverged_clip():
    """A per-clip strain of a diverged post-process (1.7e20) must not run into its neighbour's column."""
    from simgen.learn.evaluate import format_summary

    strain = {"ground_truth": 3.7e-4, "model": 0.0236, "model_relaxed": 0.00227, "model_solver": 1.6951e20}
    inside = {"ground_truth": 0.155, "model_raw": 11.704, "model": 0.001}
    metrics = {"groups": {"held_out_motion": {"error_cm": {}, "per_clip": {
        "lunge": {"mean_error_cm": {"model": 1.286, "lbs": 3.233}, "triangle_strain": strain,
                  "inside_percent": inside}}}}}
    row = next(line for line in format_summary(metrics).splitlines() if line.startswith("lunge"))
    assert [float(v) for v in row.split()[1:]] == pytest.approx(
        [1.286, 3.233, 3.7e-4, 0.0236, 0.00227, 1.6951e20, 0.155, 11.704, 0.001], rel=1e-3)
