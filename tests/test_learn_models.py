"""simgen.learn building blocks: skinning and body transforms against the numpy references, motion
features against invariants, the regressors' save/load round trip and identity checks, the closed-form
linear regressor against numpy's least squares, and TBPTT's hidden-state hand-over."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from simgen.body import TorchBody, load
from simgen.errors import InputError
from simgen.learn import (GarmentFitMLP, GarmentTemplate, LinearRegressor, WrinkleGRU, feature_size, inverse_lbs_torch,
                          joint_transforms, lbs_torch, load_model, motion_features, save_model)
from simgen.learn.train import tbptt_batch

IDENTITY = {"garment": {"name": "tshirt_1k", "hash": "a" * 64}, "body": {"id": "open-x", "hash": "b" * 64}}


@pytest.fixture(scope="module")
def body():
    return load("open")


def _random_pose(rng, n, scale=0.4):
    return rng.normal(scale=scale, size=(n, 24, 3))


# ------------------------------------------------------------------------------------ skinning
def test_joint_transforms_match_numpy_and_torch_body(body):
    from simgen.dataset.groundtruth import skinning_transforms

    rng = np.random.default_rng(0)
    betas = rng.normal(size=(3, body.num_betas))
    pose, trans = _random_pose(rng, 3), rng.normal(size=(3, 3))
    ref = skinning_transforms(body, betas, pose, trans)
    tb = TorchBody(body, dtype=torch.float64)
    ours = joint_transforms(tb, torch.tensor(betas), torch.tensor(pose), torch.tensor(trans)).numpy()
    assert np.abs(ours - ref).max() < 1e-12
    assert np.abs(tb(betas, pose, trans)[2].numpy() - ref).max() < 1e-12


def test_lbs_torch_matches_numpy_and_inverts(body):
    from simgen.garment.library import load_garment
    from simgen.garment.skinning import lbs

    g = load_garment("tshirt_1k", body=body)
    rng = np.random.default_rng(1)
    a = body.forward(rng.normal(size=(2, body.num_betas)), _random_pose(rng, 2), rng.normal(size=(2, 3))).transforms
    rest = g.vertices[None] + rng.normal(scale=0.01, size=(2, g.num_vertices, 3))
    posed = lbs_torch(torch.tensor(rest), torch.tensor(g.skin_weights), torch.tensor(a))
    assert np.abs(posed.numpy() - lbs(rest, g.skin_weights, a)).max() < 1e-12
    back = inverse_lbs_torch(posed, torch.tensor(g.skin_weights), torch.tensor(a))
    assert np.abs(back.numpy() - rest).max() < 1e-10


# ------------------------------------------------------------------------------------ features
def _rot_y(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def test_pose_velocity_features_ignore_heading_and_measure_velocity():
    """Turning a whole motion about the vertical and moving it changes nothing; the root velocity in
    the heading frame is the finite difference of trans, rotated; frame 0 is at rest."""
    from simgen.motion import load_motion
    from simgen.rotations import axis_angle_to_matrix, matrix_to_axis_angle

    clip = load_motion("walk_curve")
    poses, trans = clip.poses[:40].copy(), clip.trans[:40].copy()
    base = motion_features(torch.tensor(poses), torch.tensor(trans), clip.fps).numpy()
    assert base.shape == (40, feature_size("pose_velocity"))
    rw = _rot_y(1.1)
    turned = poses.copy()
    turned[:, 0] = matrix_to_axis_angle(rw @ axis_angle_to_matrix(poses[:, 0]))
    moved = trans @ rw.T + np.array([3.0, 0.2, -5.0])
    other = motion_features(torch.tensor(turned), torch.tensor(moved), clip.fps).numpy()
    assert np.abs(other - base).max() < 1e-9
    # Velocity block (features 75:78) against the finite difference in the heading frame.
    r0 = axis_angle_to_matrix(poses[:, 0])
    heading = np.arctan2(r0[:, 0, 2], r0[:, 2, 2])
    v = np.diff(trans, axis=0) * clip.fps
    local = np.einsum("tij,tj->ti", np.stack([_rot_y(h).T for h in heading[1:]]), v)
    assert np.abs(base[1:, 75:78] - local).max() < 1e-9
    assert np.all(base[0, 75:] == 0.0)
    # Streaming one frame at a time gives the same features.
    prev = None
    for t in range(5):
        f = motion_features(torch.tensor(poses[t:t + 1]), torch.tensor(trans[t:t + 1]), clip.fps, previous=prev)
        prev = (torch.tensor(poses[t]), torch.tensor(trans[t]))
        assert np.abs(f.numpy()[0] - base[t]).max() < 1e-12
    assert motion_features(torch.tensor(poses), torch.tensor(trans), 30.0, "pose").shape == (40, 72)


# ------------------------------------------------------------------------------------ save / load
def _models():
    torch.manual_seed(0)
    fit = GarmentFitMLP(10, 50, hidden=7)
    gru = WrinkleGRU(10, 79, 50, hidden=16)
    lr = LinearRegressor(10, 79, 50, inputs="shape_pose")
    tpl = GarmentTemplate.from_arrays(np.random.rand(50, 3), np.random.rand(50, 3), np.arange(30).reshape(10, 3),
                                      np.full((50, 24), 1 / 24), np.random.rand(50, 3, 10))
    for m in (fit, gru, lr):
        m.set_normalization(torch.randn(20, m.input_mean.numel()), torch.randn(20, 50, 3) * 0.01)
    return {"fit": fit, "gru": gru, "lr": lr, "tpl": tpl}


def test_save_load_round_trip_is_exact(tmp_path):
    models = _models()
    betas, feats = torch.randn(2, 5, 10), torch.randn(2, 5, 79)
    for name, m in models.items():
        save_model(m, tmp_path / name, identity=IDENTITY, training={"note": name})
        back = load_model(tmp_path / name, identity=IDENTITY)
        assert type(back) is type(m)
        for k, v in m.state_dict().items():
            assert torch.equal(back.state_dict()[k], v), (name, k)
        # The weights file holds plain tensors: the safe loader reads it.
        state = torch.load(tmp_path / name / "model.pt", weights_only=True)
        assert set(state) == set(m.state_dict())
        cfg = json.loads((tmp_path / name / "config.json").read_text())
        assert cfg["garment"] == IDENTITY["garment"] and cfg["training"] == {"note": name}
    m, back = models["gru"].eval(), load_model(tmp_path / "gru")
    assert torch.equal(m(betas, feats)[0], back(betas, feats)[0])
    assert torch.equal(models["fit"].eval()(betas), load_model(tmp_path / "fit")(betas))
    assert torch.equal(models["lr"](betas, feats), load_model(tmp_path / "lr")(betas, feats))


def test_checkpoint_for_another_garment_or_body_is_refused(tmp_path):
    save_model(_models()["fit"], tmp_path / "fit", identity=IDENTITY)
    other_garment = {"garment": {"name": "dress_1k", "hash": "c" * 64}, "body": IDENTITY["body"]}
    with pytest.raises(InputError, match=r"trained for garment 'tshirt_1k'.*not for 'dress_1k'"):
        load_model(tmp_path / "fit", identity=other_garment)
    same_name = {"garment": {"name": "tshirt_1k", "hash": "d" * 64}, "body": IDENTITY["body"]}
    with pytest.raises(InputError, match="hash aaaaaaaaaaaa"):
        load_model(tmp_path / "fit", identity=same_name)
    other_body = {"garment": IDENTITY["garment"], "body": {"id": "smpl_female-123", "hash": "e" * 64}}
    with pytest.raises(InputError, match="trained for body 'open-x'"):
        load_model(tmp_path / "fit", identity=other_body)
    with pytest.raises(InputError, match="'garment_fit' model, expected 'garment_wrinkle'"):
        load_model(tmp_path / "fit", kind="garment_wrinkle")
    with pytest.raises(InputError, match="not a simgen model folder"):
        load_model(tmp_path / "nothing")


# ------------------------------------------------------------------------------------ linear regressor
def test_linear_regressor_equals_least_squares():
    """With no ridge the closed-form fit (streamed in blocks) is numpy's least squares."""
    rng = np.random.default_rng(3)
    n, v = 300, 4
    betas, feats = rng.normal(size=(n, 3)), rng.normal(size=(n, 5))
    x = np.concatenate([betas, feats], 1)
    w = rng.normal(size=(8, v * 3))
    y = (x @ w + 0.5 + 0.01 * rng.normal(size=(n, v * 3))).reshape(n, v, 3)
    lr = LinearRegressor(3, 5, v, inputs="shape_pose").double()

    def chunks():
        for s in range(0, n, 64):
            yield (torch.tensor(betas[s:s + 64]), torch.tensor(feats[s:s + 64]), torch.tensor(y[s:s + 64]))

    lr.fit(chunks, ridge=0.0)
    design = np.concatenate([x, np.ones((n, 1))], 1)
    coef, *_ = np.linalg.lstsq(design, y.reshape(n, -1), rcond=None)
    ref = (design @ coef).reshape(n, v, 3)
    ours = lr(torch.tensor(betas), torch.tensor(feats)).detach().numpy()
    assert np.abs(ours - ref).max() < 1e-5
    pose_only = LinearRegressor(3, 5, v, inputs="pose")
    assert pose_only.linear.in_features == 5


# ------------------------------------------------------------------------------------ TBPTT
def test_tbptt_carries_the_hidden_state_across_windows():
    """Each window starts from the previous window's final state (values equal, graph cut), and the
    windows together compute what one pass over the whole sequence computes."""
    torch.manual_seed(0)
    model = WrinkleGRU(2, 3, 4, hidden=8, dropout=0.0)
    x = torch.randn(3, 10, 5)
    y = torch.randn(3, 10, 12)
    mask = torch.ones(3, 10, dtype=torch.bool)
    mask[2, 7:] = False
    calls = []
    original = model.forward_normalized

    def recording(inputs, h0=None):
        z, h = original(inputs, h0)
        calls.append((None if h0 is None else h0.clone(), None if h0 is None else h0.requires_grad, h.clone(),
                      inputs.shape[1]))
        return z, h

    model.forward_normalized = recording
    # A zero learning rate keeps the weights fixed, so the chunks can be compared with one full pass.
    opt = torch.optim.SGD(model.parameters(), lr=0.0)
    total, count, steps, stopped = tbptt_batch(model, x, y, mask, opt, window=4)
    assert steps == 3 and [c[3] for c in calls] == [4, 4, 2] and not stopped
    assert count == int(mask.sum())
    assert calls[0][0] is None
    for prev, cur in zip(calls, calls[1:]):
        assert torch.equal(cur[0], prev[2]) and cur[1] is False
    model.forward_normalized = original
    full, h_full = model.forward_normalized(x)
    assert torch.allclose(calls[-1][2], h_full, atol=1e-6)
    expected = ((full - y).pow(2).mean(-1)[mask]).sum()
    assert total == pytest.approx(float(expected.detach()), rel=1e-5)


def test_tbptt_gradient_stops_at_the_window_start():
    """The loss of window 2 depends on window 1's inputs through the carried state, but its gradient
    does not reach them (truncation)."""
    torch.manual_seed(1)
    model = WrinkleGRU(1, 2, 2, hidden=6, dropout=0.0)
    x = torch.randn(1, 8, 3, requires_grad=True)
    _, h = model.forward_normalized(x[:, :4])
    z2, _ = model.forward_normalized(x[:, 4:], h.detach())
    z2.sum().backward()
    assert torch.all(x.grad[:, :4] == 0) and torch.any(x.grad[:, 4:] != 0)
    z2_fresh, _ = model.forward_normalized(x[:, 4:].detach())
    assert not torch.allclose(z2, z2_fresh)  # the carried state matters
