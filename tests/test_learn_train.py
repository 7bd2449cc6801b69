"""Training on data with a known answer (test_learn_helpers.synthetic_data): the fit MLP and the
wrinkle GRU learn it and beat LBS and the pose-only linear regression on held-out motions; splits;
checkpoints resume to exactly the weights of an uninterrupted run; time budgets stop cleanly."""

from __future__ import annotations


import numpy as np
import pytest
import torch
from test_learn_helpers import synthetic_data

from simgen.errors import InputError
from simgen.learn import (FitConfig, WrinkleConfig, fit_linear_baselines, lbs_baseline, linear_baseline,
                          load_garment_model, load_linear_baselines, make_split, motion_features, train_fit,
                          train_wrinkle)


@pytest.fixture(scope="module")
def data():
    return synthetic_data(frames=40)


def test_splits(data):
    by_motion = make_split(data, "motion")
    assert set(by_motion.test) == {"held_out_motion"}
    assert all(data.sequences[i].split == "train" for i in by_motion.train_sequences)
    assert {data.sequences[i].motion for i in by_motion.test["held_out_motion"]} == {"dance", "lunge"}
    assert by_motion.train_shapes == sorted(data.shapes) and by_motion.test_shapes == []
    by_shape = make_split(data, "shape")
    assert by_shape.test_shapes == ["b0p2"]  # the one shape reaching |beta| = 2, beyond the others
    assert all(data.sequences[i].shape_id != "b0p2" for i in by_shape.train_sequences)
    assert {data.sequences[i].motion for i in by_shape.test["held_out_both"]} == {"dance", "lunge"}
    assert all(data.sequences[i].split == "train" for i in by_shape.test["held_out_shape"])
    chosen = make_split(data, "shape", test_shapes=["b1m1", "b1p1"])
    assert chosen.test_shapes == ["b1m1", "b1p1"] and "b1p1" not in chosen.train_shapes
    with pytest.raises(InputError, match="not in the dataset"):
        make_split(data, "shape", test_shapes=["nope"])
    with pytest.raises(InputError, match="split 'pose'"):
        make_split(data, "pose")


@torch.no_grad()
def _errors(folder, data, ids):
    model = load_garment_model(folder, identity=data.identity)
    lrs = load_linear_baselines(folder)
    err = {"model": [], "fit_only": [], "lbs": [], "lr_pose": [], "lr_shape_pose": []}
    for sid in ids:
        s = data.sequences[sid]
        b, p, t = (torch.tensor(x) for x in (s.betas, s.poses, s.trans))
        pred = model.predict(b, p, t, s.fps, postprocess=False)
        gt = torch.tensor(s.vertices)
        f = motion_features(p, t, s.fps, lrs["pose"].feature_mode)
        from simgen.learn.evaluate import lbs_baseline_fit

        outs = {"model": pred.vertices, "fit_only": lbs_baseline_fit(model, b, pred.transforms),
                "lbs": lbs_baseline(model.template, b, pred.transforms),
                "lr_pose": linear_baseline(lrs["pose"], model.template, b, f, pred.transforms),
                "lr_shape_pose": linear_baseline(lrs["shape_pose"], model.template, b, f, pred.transforms)}
        for k, v in outs.items():
            err[k].append(float((v - gt).norm(dim=-1).mean()) * 100)
    return {k: float(np.mean(v)) for k, v in err.items()}


def test_models_learn_the_known_answer_and_beat_the_baselines(data, tmp_path):
    torch.manual_seed(0)
    split = make_split(data, "motion")
    out = tmp_path / "model"
    r = train_fit(data, out, split, config=FitConfig(epochs=2000, dropout=0.0))
    assert r.epochs == 2000 and r.stopped == "epochs"
    r = train_wrinkle(data, out, split, config=WrinkleConfig(hidden=96, epochs=40, window=16, batch_size=8,
                                                               dropout=0.0, val_every=20))
    assert r.epochs == 40 and r.val_error_cm is not None
    fit_linear_baselines(data, out, split)
    # The fit MLP alone recovers the constructed rest-pose fit: rest-pose error far below LBS's.
    model = load_garment_model(out)
    for sid, row in data.shapes.items():
        pred = model.fit(torch.tensor(row["betas"])[None])[0].detach().numpy()
        assert np.linalg.norm(pred - row["fit"], axis=1).mean() < 0.003, sid
    test = _errors(out, data, split.test["held_out_motion"])
    train = _errors(out, data, split.train_sequences[::4])
    # On training data and on held-out motions the full model is better than LBS and pose-only LR.
    assert train["model"] < 0.5 * train["lbs"]
    assert test["model"] < 0.5 * test["lbs"]
    assert test["model"] < test["lr_pose"]
    assert test["model"] < 0.5 * test["fit_only"]  # the wrinkle GRU carries the pose-dependent part
    log = (out / "wrinkle" / "log.csv").read_text().splitlines()
    assert len(log) == 41 and log[0].startswith("epoch,steps,train_loss")
    first, last = float(log[1].split(",")[2]), float(log[-1].split(",")[2])
    assert last < 0.2 * first


def _wrinkle_state(folder):
    return torch.load(folder / "wrinkle" / "model.pt", weights_only=True)


def test_resume_reproduces_an_uninterrupted_run(data, tmp_path):
    split = make_split(data, "motion")
    cfg = WrinkleConfig(hidden=16, epochs=4, window=8, batch_size=5, val_every=0)
    train_wrinkle(data, tmp_path / "a", split, config=cfg)
    first = train_wrinkle(data, tmp_path / "b", split, config=WrinkleConfig(**{**cfg.__dict__, "epochs": 2}))
    assert first.epochs == 2
    # The same settings with more epochs continue the saved run (model, optimiser, random state).
    resumed = train_wrinkle(data, tmp_path / "b", split, config=cfg)
    assert resumed.epochs == 4 and resumed.steps == first.steps
    a, b = _wrinkle_state(tmp_path / "a"), _wrinkle_state(tmp_path / "b")
    for k in a:
        assert torch.equal(a[k], b[k]), k
    rows = (tmp_path / "b" / "wrinkle" / "log.csv").read_text().splitlines()
    assert [r.split(",")[0] for r in rows[1:]] == ["1", "2", "3", "4"]
    with pytest.raises(InputError, match="other settings.*--restart"):
        train_wrinkle(data, tmp_path / "b", split, config=WrinkleConfig(**{**cfg.__dict__, "hidden": 17}))
    fresh = train_wrinkle(data, tmp_path / "b", split, config=WrinkleConfig(**{**cfg.__dict__, "hidden": 17}),
                          resume=False)
    assert fresh.epochs == 4


def test_time_budget_stops_cleanly(data, tmp_path):
    split = make_split(data, "motion")
    r = train_wrinkle(data, tmp_path, split, config=WrinkleConfig(hidden=16, epochs=10_000, window=8, batch_size=4),
                      time_budget=0.5)
    assert r.stopped == "time budget" and r.epochs < 10_000 and r.steps >= 1
    model = load_garment_model(tmp_path) if (tmp_path / "fit").is_dir() else None
    assert model is None  # no fit model trained here; the wrinkle model alone still loads:
    from simgen.learn import load_model

    gru = load_model(tmp_path / "wrinkle", identity=data.identity)
    assert gru.saved_config["training"]["epochs"] == r.epochs
    r2 = train_fit(data, tmp_path, split, config=FitConfig(epochs=10_000_000), time_budget=0.3)
    assert r2.stopped == "time budget" and 1 <= r2.epochs < 10_000_000


def test_models_of_one_folder_share_a_split(data, tmp_path):
    train_fit(data, tmp_path, make_split(data, "motion"), config=FitConfig(epochs=2))
    with pytest.raises(InputError, match="another split"):
        train_fit(data, tmp_path, make_split(data, "shape"), config=FitConfig(epochs=2))


def test_validation_motions_leave_training_and_nothing_else(data):
    import zlib

    from simgen.learn import Split

    base = make_split(data, "motion")
    train_motions = sorted({data.sequences[i].motion for i in base.train_sequences})
    split = make_split(data, "motion", validation_motions=1)
    (first,) = sorted(train_motions, key=lambda m: zlib.crc32(m.encode()))[:1]
    assert {data.sequences[i].motion for i in split.validation} == {first}
    # Every shape of that motion, taken from training and from nowhere else.
    assert sorted(split.validation) == sorted(i for i in base.train_sequences if data.sequences[i].motion == first)
    assert sorted(split.train_sequences + split.validation) == sorted(base.train_sequences)
    assert split.test == base.test and split.train_shapes == base.train_shapes
    named = make_split(data, "shape", validation_motions=["walk", "squat"])
    assert {data.sequences[i].motion for i in named.validation} == {"walk", "squat"}
    assert all(data.sequences[i].shape_id not in named.test_shapes for i in named.validation)
    assert Split.from_dict(named.to_dict()) == named and "validation" not in base.to_dict()
    for bad, match in ((["dance"], "'dance' is not a training motion"), (train_motions, "every training motion"),
                       (len(train_motions), "needs at least one left")):
        with pytest.raises(InputError, match=match):
            make_split(data, "motion", validation_motions=bad)


def test_patience_stops_a_run_whose_validation_error_stays(data, tmp_path):
    split = make_split(data, "motion", validation_motions=1)
    # lr = 0: the weights never move, so the first validation is the best and no later one gains 1%.
    cfg = WrinkleConfig(hidden=16, epochs=50, window=8, batch_size=5, lr=0.0, val_every=1, patience=2)
    r = train_wrinkle(data, tmp_path, split, config=cfg)
    assert (r.stopped, r.epochs, r.best_epoch) == ("converged", 3, 1)
    with pytest.raises(InputError, match="patience needs a split with validation motions"):
        train_wrinkle(data, tmp_path / "b", make_split(data, "motion"), config=cfg)
    with pytest.raises(InputError, match="patience needs validations"):
        train_wrinkle(data, tmp_path / "c", split, config=WrinkleConfig(**{**cfg.__dict__, "val_every": 0}))


def test_the_saved_wrinkle_model_is_the_best_validations(data, tmp_path):
    from simgen.learn import load_model, stack_sequences
    from simgen.learn.train import _wrinkle_val_error

    split = make_split(data, "motion", validation_motions=1)
    cfg = WrinkleConfig(hidden=32, epochs=8, window=8, batch_size=3, lr=0.03, dropout=0.0, val_every=1)
    r = train_wrinkle(data, tmp_path, split, config=cfg)
    rows = [line.split(",") for line in (tmp_path / "wrinkle" / "log.csv").read_text().splitlines()[1:]]
    logged = {int(row[0]): float(row[3]) for row in rows}
    assert r.stopped == "epochs" and r.best_epoch == min(logged, key=logged.get)
    assert r.val_error_cm == pytest.approx(min(logged.values()), rel=1e-6)
    gru = load_model(tmp_path / "wrinkle", identity=data.identity)
    batch = stack_sequences(data, split.validation, feature_mode=cfg.feature_mode, target="wrinkle")
    assert _wrinkle_val_error(gru, batch) == pytest.approx(logged[r.best_epoch], rel=1e-5)
    assert gru.saved_config["training"]["validation"]["best_epoch"] == r.best_epoch
    # Resumed with more epochs, the run keeps its best so far: epoch 9 replaces it only if lower.
    more = train_wrinkle(data, tmp_path, split, config=WrinkleConfig(**{**cfg.__dict__, "epochs": 9}))
    assert more.epochs == 9
    assert ((more.best_epoch, more.val_error_cm) == (r.best_epoch, r.val_error_cm)
            or (more.best_epoch == 9 and more.val_error_cm < r.val_error_cm))
    # Saving the best weights mid-run (a checkpoint every epoch) leaves the training where it was.
    again = train_wrinkle(data, tmp_path / "every", split, config=cfg, checkpoint_every=0.0)
    assert _log_rows(tmp_path / "every") == [row[:4] for row in rows]
    assert (again.best_epoch, again.val_error_cm) == (r.best_epoch, r.val_error_cm)


def _log_rows(folder) -> list:
    """log.csv's rows without the seconds column."""
    return [line.split(",")[:4] for line in (folder / "wrinkle" / "log.csv").read_text().splitlines()[1:]]


def test_the_cli_fills_what_is_not_given_from_the_folders_split(data, tmp_path):
    from simgen.learn._cli import _split
    from simgen.learn.train import write_split

    existing = make_split(data, "shape", test_shapes=["b1m1", "b1p1"], validation_motions=1)
    write_split(existing, tmp_path)
    assert _split(data, tmp_path, "shape", None) == existing
    more = _split(data, tmp_path, None, None, 2)
    assert (more.by, more.test_shapes) == ("shape", ["b1m1", "b1p1"]) and len(more.validation) > len(existing.validation)


def test_triangle_strain_of_a_stretch_and_a_rotation(data):
    """Table 6.2's strain as simgen defines it: the mean over triangles of ||G||_F^2. A rigid motion
    of the rest template has none; a uniform stretch by s has (s^2 - 1)^2 / 2 on every triangle."""
    from simgen.learn.evaluate import cloth_rest, triangle_strain

    rest = cloth_rest(data)
    x = np.asarray(data.rest_template if data.rest_template is not None else data.template, dtype=np.float64)
    c, s = np.cos(0.7), np.sin(0.7)
    turned = x @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T + [0.3, -0.2, 1.0]
    out = triangle_strain(np.stack([x, turned, 1.1 * x]), rest)
    assert out[0] == pytest.approx(0.0, abs=1e-20) and out[1] == pytest.approx(0.0, abs=1e-24)
    assert out[2] == pytest.approx((1.1 ** 2 - 1) ** 2 / 2, rel=1e-9)
