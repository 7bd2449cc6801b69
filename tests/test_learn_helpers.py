"""Shared builders for the simgen.learn tests (imported by the other test_learn_* files), and checks
that what they build has the structure the learning tests rely on.

`synthetic_data` dresses the open body in the 1k-triangle T-shirt and makes "simulations" whose
ground truth is known by construction: S_c = W(T_c + G(beta) + L(beta, history of theta)), with G the
body's shape blendshape carried to the garment plus a nonlinear (tanh) tightening, and L a
history-dependent displacement (an exponential moving average of shoulder and spine angles times
smooth spatial fields, scaled by the shape). LBS of the template misses both, so a model that
learns them must beat it. Real simulations are used by test_learn_store.py.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from simgen.learn.data import GarmentData, SequenceData, attach_ground_truth, garment_shape_directions

MOTIONS = {"walk": "train", "arm_swings": "train", "jumping_jacks": "train", "squat": "train",
           "dance": "test", "lunge": "test"}
SHAPES = {"zero": [0.0, 0.0], "b0m1": [-1.0, 0.0], "b0p1": [1.0, 0.0], "b1m1": [0.0, -1.0], "b1p1": [0.0, 1.0],
          "b0p2": [2.0, 0.0]}


@functools.lru_cache(maxsize=1)
def _assets():
    from simgen.body import load
    from simgen.dataset.groundtruth import smooth_garment
    from simgen.garment.library import load_garment

    body = load("open")
    garment = load_garment("tshirt_1k", body=body)
    tr = garment.vertices.astype(np.float64)
    tc = smooth_garment(tr, garment.faces)
    dirs = garment_shape_directions(tr, body)  # (V, 3, B)
    rng = np.random.default_rng(7)
    # Smooth spatial fields: random low-order polynomials of the rest position (cm-scale).
    centred = (tc - tc.mean(0)) / np.ptp(tc, axis=0).max()
    basis = np.stack([np.ones(len(tc)), centred[:, 0], centred[:, 1], centred[:, 2], centred[:, 0] * centred[:, 1],
                      centred[:, 1] ** 2], axis=1)  # (V, 6)
    fields = np.einsum("vk,mkc->mvc", basis, rng.normal(scale=0.02, size=(3, 6, 3)))  # (3, V, 3)
    return body, garment, tr, tc, dirs, fields


def _bind_betas(values, nb: int) -> np.ndarray:
    b = np.zeros(nb, dtype=np.float32)
    b[: len(values)] = values
    return b


def true_fit(betas: np.ndarray) -> np.ndarray:
    """G(beta) [m], (V, 3): the shape blendshape plus a tanh tightening along the first field."""
    _, _, _, tc, dirs, fields = _assets()
    lin = np.einsum("vcb,b->vc", dirs[:, :, : len(betas)], betas)
    return lin + 0.5 * np.tanh(betas[0]) * fields[0]


def true_wrinkle(betas: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """L(beta, theta history) [m], (T, V, 3): EMA (time constant ~5 frames) of joint angles on fields."""
    _, _, _, _, _, fields = _assets()
    drive = np.stack([np.sin(poses[:, 16, 2]) - np.sin(poses[:, 17, 2]), np.sin(poses[:, 3, 0] + poses[:, 6, 0])], 1)
    ema = np.zeros_like(drive)
    acc = np.zeros(2)
    for t in range(len(drive)):
        acc = 0.8 * acc + 0.2 * drive[t]
        ema[t] = acc
    scale = 1.0 + 0.3 * np.tanh(betas[1])
    return scale * (np.einsum("t,vc->tvc", ema[:, 0], fields[1]) + np.einsum("t,vc->tvc", ema[:, 1], fields[2]))


def synthetic_data(frames: int = 48, motions=None, shapes=None) -> GarmentData:
    """GarmentData with known ground truth (see the module docstring); ~0.3 s to build."""
    from simgen.body.torch_lbs import TorchBody
    from simgen.learn.skinning import lbs_torch
    from simgen.motion import load_motion

    body, garment, tr, tc, dirs, _ = _assets()
    nb = body.num_betas
    motions = motions or MOTIONS
    shapes = shapes or SHAPES
    shape_rows = {}
    for sid, vals in shapes.items():
        b = _bind_betas(vals, nb)
        shape_rows[sid] = {"betas": b, "fit": true_fit(b).astype(np.float32),
                           "vertices": (tc + true_fit(b)).astype(np.float32)}
    tb = TorchBody(body, dtype=torch.float64)
    w = torch.as_tensor(garment.skin_weights)
    seqs = {}
    for m, split in motions.items():
        clip = load_motion(m)
        poses = clip.poses[10:10 + frames].astype(np.float32)
        trans = clip.trans[10:10 + frames].astype(np.float32)
        for sid, row in shape_rows.items():
            betas = np.repeat(row["betas"][None], len(poses), 0)
            _, _, a = tb(betas, poses, trans)
            rest = tc[None] + row["fit"][None] + true_wrinkle(row["betas"], poses)
            verts = lbs_torch(torch.as_tensor(rest), w, a).numpy().astype(np.float32)
            seqs[f"{m}__{sid}"] = SequenceData(id=f"{m}__{sid}", motion=m, shape_id=sid, split=split, fps=clip.fps,
                                               betas=betas, poses=poses, trans=trans, vertices=verts)
    identity = {"garment": {"name": garment.name, "hash": "synthetic-" + garment.name},
                "body": {"id": body.model_id, "hash": body.hash}}
    data = GarmentData(identity=identity, template=tr.astype(np.float32), template_smoothed=tc.astype(np.float32),
                       faces=garment.faces, skin_weights=garment.skin_weights.astype(np.float32), shapes=shape_rows,
                       sequences=seqs, source="synthetic")
    return attach_ground_truth(data, body)


def test_synthetic_ground_truth_recovers_construction():
    """Unposing the synthetic frames (attach_ground_truth) returns the wrinkle field they were made with."""
    data = synthetic_data(frames=12, motions={"walk": "train"}, shapes={"b0p1": [1.0, 0.0]})
    s = data.sequences["walk__b0p1"]
    expected = true_wrinkle(data.shapes["b0p1"]["betas"], s.poses)
    assert np.abs(s.wrinkle - expected).max() < 2e-5  # float32 positions, metres
    assert np.abs(expected).max() > 5e-3  # the field is not negligible


def test_synthetic_lbs_error_is_substantial():
    """LBS of the template misses the constructed fit and wrinkles by centimetres (so the learning
    tests' 'beats LBS' has room)."""
    from simgen.learn.skinning import lbs_torch

    data = synthetic_data(frames=12, motions={"dance": "test"}, shapes={"b0p2": [2.0, 0.0]})
    _, _, _, _, dirs, _ = _assets()
    s = data.sequences["dance__b0p2"]
    rest = data.template + np.einsum("vcb,b->vc", dirs, s.betas[0])
    lbs = lbs_torch(torch.as_tensor(rest), torch.as_tensor(data.skin_weights), torch.as_tensor(s.transforms)).numpy()
    err_cm = np.linalg.norm(lbs - s.vertices, axis=-1).mean() * 100
    assert err_cm > 1.0
