"""SNUG (thesis ch. 5, simgen.learn.snug) at tiny sizes on the CPU: the loss of a window is the
simgen.physics energy of the same positions with the dataset preset's parameters; training lowers
it; ablation switches remove their term; models save and load in one call and predict the same;
an interrupted run resumes to exactly the weights of an uninterrupted one."""

from __future__ import annotations

import csv
import tomllib
from dataclasses import replace

import numpy as np
import pytest
import torch

from simgen.errors import InputError
from simgen.learn.checkpoint import save_model
from simgen.learn.snug import (LOSS_TERMS, SnugConfig, SnugModel, SnugNet, _Run, load_snug_model, sample_shapes,
                               shape_range, train_snug, window_loss)

GARMENT = "tshirt_1k"
# 2 windows per epoch (walk frames 0-2 and 90-92), 2 validation windows, a small GRU stack.
TINY = SnugConfig(hidden=16, layers=2, batch_size=1, window_stride=90, val_windows=2, epochs=2, lr_epochs=1)


def _rows(folder):
    with open(folder / "log.csv", newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """One torch thread: these tiny sizes gain nothing from more, and a busy 2-core machine loses ~20x."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def run():
    return _Run(GARMENT, ["walk"], replace(TINY, val_windows=0), torch.device("cpu"), None)


def test_defaults_follow_the_preset_and_the_thesis(run):
    import simgen.dataset.spec as spec

    with open(spec.PRESETS_DIR / "thesis-tshirt.toml", "rb") as fh:
        preset = tomllib.load(fh)
    p = run.physics
    assert p.material.name == preset["garment"]["material"] == "interlock"
    assert p.contact.stiffness == preset["solver"]["contact"]["stiffness"] == 1e5
    assert (p.contact.margin, p.contact.power, p.fps, p.bending_rest) == (2e-3, 3.0, 30.0, "template")
    c = SnugConfig()
    assert (c.hidden, c.layers, c.window, c.batch_size, c.lr, c.lr_epochs, c.lr_final, c.hidden_init_std) == \
        (256, 4, 3, 16, 1e-3, 10, 1e-4, 0.1)
    assert (run.range, run.components) == (2.0, 5)  # open body: U(-2, 2) on its 5 live components
    b = sample_shapes(500, 10, *shape_range(run.body, SnugConfig(shape_range=3.0)), torch.Generator().manual_seed(0))
    assert float(b[:, :5].abs().max()) <= 3.0 and float(b[:, :5].abs().max()) > 2.9 and not b[:, 5:].any()
    assert run.windows.starts == [0, 90] and run.windows.poses.shape == (2, 3, 24, 3)


def test_window_loss_is_the_physics_of_the_predicted_positions(run):
    """batch_loss of window 0 (walk frames 0-2) = simgen.physics terms of SnugModel.predict's positions,
    posed with the numpy body, with the preset's material and contact written out here."""
    from simgen.garment import load_garment
    from simgen.motion import load_motion
    from simgen.params import ContactParams, GravityParams
    from simgen.physics import BodySurface, ClothRest, bending, contact, gravity, inertia, membrane, predict

    torch.manual_seed(1)
    with torch.no_grad():  # a non-zero regressor output
        run.net.output_layer.bias.normal_(0.0, 1.0)  # ~1 cm per vertex
    betas = torch.tensor([[1.5, -1.0, 0.5, 0.0, 1.0, 0, 0, 0, 0, 0]])
    got = run.batch_loss(run.windows, torch.tensor([0]), betas, torch.zeros(1, TINY.layers, TINY.hidden), TINY)
    got = {k: v.detach() for k, v in got.items()}

    clip = load_motion("walk")
    x = SnugModel(run.net, run.body).predict(betas[0], clip.poses[:3], clip.trans[:3], 30.0).vertices.double()
    bodies = torch.from_numpy(run.body.forward(betas.numpy().repeat(3, 0), clip.poses[:3], clip.trans[:3]).vertices)
    rest = ClothRest.from_garment(load_garment(GARMENT), "interlock", dtype=torch.float64)
    surface = BodySurface.from_body(run.body)
    want = {"strain": membrane(x, rest), "bending": bending(x, rest), "gravity": gravity(x, rest, GravityParams()),
            "inertia": inertia(x[2], predict(x[1], x[0]), rest, 1 / 30.0),
            "collision": contact(x, bodies, surface, ContactParams(stiffness=1e5, margin=2e-3, power=3.0))}
    assert float(want["collision"]) > 0 and float(want["inertia"]) > 0  # every term is exercised
    for k, v in want.items():
        assert float(got[k]) == pytest.approx(float(v), rel=2e-4, abs=1e-9), k
    assert float(got["total"]) == pytest.approx(sum(float(v) for v in want.values()), rel=2e-4)
    with torch.no_grad():
        run.net.output_layer.bias.zero_()


@pytest.mark.parametrize("off", ["strain", "bending", "gravity", "inertia", "collision"])
def test_ablation_switch_removes_its_term(run, off):
    transforms = run.torch_body(torch.zeros(6, 10), run.windows.poses.reshape(6, 24, 3),
                                run.windows.trans.reshape(6, 3))[2].reshape(2, 3, 24, 4, 4)
    x = run.net.posed(run.net.rest_garment(torch.zeros(2, 3, 10)), transforms)
    x = (x + 0.004 * torch.randn(x.shape, generator=torch.Generator().manual_seed(0))).requires_grad_(True)
    bv = run.torch_body(torch.zeros(6, 10), run.windows.poses.reshape(6, 24, 3),
                        run.windows.trans.reshape(6, 3))[0].reshape(2, 3, -1, 3)
    full = window_loss(x, bv, run.rest, run.surface, run.physics, TINY)
    value = float(full[off].detach())
    g_term = torch.autograd.grad(full[off], x, retain_graph=True)[0]
    assert float(g_term.abs().max()) > 0
    ablated = window_loss(x, bv, run.rest, run.surface, run.physics, replace(TINY, **{off: False}))
    assert value > 0 and float(ablated[off]) == pytest.approx(value)  # still logged
    assert float(ablated["total"].detach()) == pytest.approx(float(full["total"].detach()) - value, rel=1e-6)
    g_ablated = torch.autograd.grad(ablated["total"], x)[0]
    g_others = torch.autograd.grad(sum(full[k] for k in LOSS_TERMS if k != off), x, retain_graph=True)[0]
    g_full = torch.autograd.grad(full["total"], x, retain_graph=True)[0]
    assert torch.allclose(g_ablated, g_others, rtol=1e-5, atol=1e-9 * float(g_others.abs().max()))
    assert not torch.allclose(g_ablated, g_full)  # the term did pull on the positions


def test_validation_motions_are_training_motions_kept_out():
    """By default two of the library's training motions validate (CRC-32 order, as the supervised
    models': the two the thesis-tshirt run kept out, BENCHMARKS.md), are not trained on, and no
    test motion is among them; a single motion trains alone."""
    from simgen.motion import list_motions

    listed = list_motions("open")
    train = {m["name"] for m in listed if m["split"] != "test"}
    test = {m["name"] for m in listed if m["split"] == "test"}
    run = _Run(GARMENT, None, replace(TINY, window_stride=600), torch.device("cpu"), None)
    kept = set(run.validation_motions)
    assert kept == {"bend_and_reach", "cmu_131_01_walk_start_stop"}
    assert not kept & test and not kept & set(run.motions) and set(run.motions) | kept == train
    assert set(run.val.names) <= kept and not set(run.windows.names) & kept
    assert run.training_facts() == {"validation_motions": sorted(kept)}
    alone = _Run(GARMENT, ["walk"], TINY, torch.device("cpu"), None)
    assert alone.motions == ["walk"] and alone.val is None and alone.validation_motions == []


def test_training_lowers_the_loss(tmp_path):
    config = replace(TINY, batch_size=2, epochs=8, lr_epochs=8, val_windows=2, val_motions=1)
    result = train_snug(GARMENT, tmp_path, motions=["walk", "jumping_jacks"], config=config)
    rows = _rows(result.folder)
    assert result.epochs == 8 and result.steps == 8 and len(rows) == 8 and result.stopped == "epochs"
    first, last = float(rows[0]["val_loss"]), float(rows[-1]["val_loss"])
    assert last < first - 0.01, (first, last)
    assert set(LOSS_TERMS) <= set(rows[0]) and rows[0]["lr"] == "0.001"


def test_save_load_predict_and_export(tmp_path):
    from simgen.body import load
    from simgen.io.usd import write_usd
    from simgen.learn.snug import snug_tracks
    from simgen.motion import load_motion

    body = load("open")
    torch.manual_seed(0)
    net = SnugNet(10, 79, 521, 973, hidden=8, layers=2)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0.0, 0.05)
        net.template.template.normal_(0.0, 0.3)
        net.template.skin_weights.copy_(torch.softmax(torch.randn(521, 24), dim=1))
    identity = {"garment": {"name": GARMENT, "hash": "abc"}, "body": {"id": body.model_id, "hash": body.hash}}
    save_model(net, tmp_path / "snug", identity=identity, training={"physics": {"fps": 30.0}})
    clip = load_motion("jump")
    betas = np.array([1.0, -0.5, 0.3])
    want = SnugModel(net, body).rollout(clip, betas).vertices
    for loaded in (load_snug_model(tmp_path), load_snug_model(tmp_path, identity=identity)):
        assert isinstance(loaded, SnugModel) and loaded.fps == 30.0
        assert torch.equal(loaded.rollout(clip, betas).vertices, want)
    with pytest.raises(InputError, match="trained for garment"):
        load_snug_model(tmp_path, identity={"garment": {"name": "dress_1k", "hash": "x"}})
    tracks, meta, fps = snug_tracks(load_snug_model(tmp_path), clip, betas)
    assert [t.points.shape for t in tracks][1] == (clip.num_frames, 521, 3)
    assert write_usd(tmp_path / "play.usda", tracks, fps=fps, metadata=meta).is_file()


def test_resume_continues_exactly(tmp_path):
    whole = train_snug(GARMENT, tmp_path / "a", motions=["walk"], config=TINY)
    part = train_snug(GARMENT, tmp_path / "b", motions=["walk"], config=TINY, time_budget=0.0)
    assert part.stopped == "time budget" and part.epochs == 0 and part.steps == 1  # in the middle of epoch 1
    train_snug(GARMENT, tmp_path / "b", motions=["walk"], config=replace(TINY, epochs=1))
    rest = train_snug(GARMENT, tmp_path / "b", motions=["walk"], config=TINY)
    assert (whole.epochs, rest.epochs, rest.steps) == (2, 2, 2)
    a = torch.load(tmp_path / "a" / "snug" / "model.pt", weights_only=True)
    b = torch.load(tmp_path / "b" / "snug" / "model.pt", weights_only=True)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert _rows(whole.folder) == [dict(r, seconds=s["seconds"]) for r, s in zip(_rows(rest.folder),
                                                                                _rows(whole.folder))]
    with pytest.raises(InputError, match="hidden differ.*--restart"):
        train_snug(GARMENT, tmp_path / "b", motions=["walk"], config=replace(TINY, hidden=8))
    again = train_snug(GARMENT, tmp_path / "b", motions=["walk"], config=replace(TINY, hidden=8, epochs=1),
                       resume=False)
    assert again.epochs == 1 and len(_rows(again.folder)) == 1


def test_train_snug_command_writes_a_model_it_can_resume(tmp_path):
    # The CLI end to end, tiny: one epoch of one short clip, then a rerun that resumes and stops at
    # once (its epochs are done); the folder loads in one call.
    from typer.testing import CliRunner

    from simgen.cli import app

    args = ["train", "snug", "--garment", GARMENT, "--out", str(tmp_path), "--motions", "walk", "--epochs", "1",
            "--hidden", "16", "--batch-size", "4"]
    first = CliRunner().invoke(app, args)
    assert first.exit_code == 0, first.output
    assert "stopped: " in first.output and len(_rows(tmp_path / "snug")) == 1
    second = CliRunner().invoke(app, args)
    assert second.exit_code == 0, second.output
    assert len(_rows(tmp_path / "snug")) == 1  # resumed: nothing left to train
    assert load_snug_model(tmp_path).net is not None


@pytest.mark.parametrize("kwargs", [{"garment": "no_such_garment"}, {"motions": ["no_such_clip"]},
                                    {"config": replace(TINY, physics="no_such_preset")}])
def test_bad_input_is_one_sentence_and_writes_nothing(tmp_path, kwargs):
    args = {"garment": GARMENT, **kwargs}
    with pytest.raises(InputError, match="no_such"):
        train_snug(args.pop("garment"), tmp_path / "out", **args)
    assert not (tmp_path / "out").exists()
