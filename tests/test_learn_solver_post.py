"""The solver post-process (simgen.learn.solver_post) on the CPU with small meshes: a sheet in free
fall against backward Euler's closed form, a noisy sheet sunk into a sphere (out of it, its metric
restored), the solver settings read back from a store's attributes, and bad input."""

from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np
import pytest
import torch
import trimesh

from simgen.errors import InputError
from simgen.learn.solver_post import SolverPostProcess, solver_config_from_attrs
from simgen.params import ContactParams, FrictionParams
from simgen.sim.config import SolverConfig

H = 1.0 / 300.0


def _sheet(n: int = 9, size: float = 0.16):
    """A flat square sheet [m] in the xz-plane at y = 0: vertices (n*n, 3), faces."""
    u = np.linspace(-size / 2, size / 2, n)
    x, z = np.meshgrid(u, u, indexing="ij")
    v = np.stack([x.ravel(), np.zeros(n * n), z.ravel()], 1)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [[a, b, d], [a, d, c]]
    return v, np.array(faces)


def _sphere(radius: float = 0.3):
    s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    return np.asarray(s.vertices), np.asarray(s.faces)


def _post(rest, faces, body_faces, substeps: int, config=None, device: str = "cpu") -> SolverPostProcess:
    return SolverPostProcess(rest, faces, np.zeros(len(rest), dtype=np.int32), "cotton",
                             config or SolverConfig(), H, body_faces, np.ones(len(body_faces), dtype=np.int32),
                             substeps=substeps, chunk=8, device=device)


def _mean_strain2(x: np.ndarray, rest: np.ndarray, faces: np.ndarray) -> float:
    """Mean over triangles of ||E||_F^2, E the Green strain of positions x [m] (V, 3) against rest."""
    def frame(p):
        e1, e2 = p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]]
        return np.stack([e1, e2], -1)                              # (F, 3, 2)
    dm, dx = frame(rest), frame(x)
    g_rest = np.einsum("fki,fkj->fij", dm, dm)
    g = np.einsum("fki,fkj->fij", dx, dx)
    inv = np.linalg.inv(g_rest)
    e = 0.5 * (np.einsum("fij,fjk->fik", inv, g) - np.eye(2))     # right Cauchy-Green - I, in the rest basis
    return float((e * e).sum((1, 2)).mean())


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device"))])
def test_a_sheet_at_rest_falls_as_backward_euler_says(device):
    """A sheet at its rest shape, rotated and far from the body and the floor, only falls: after K
    substeps of h from rest, backward Euler has moved every vertex by g h^2 K (K + 1) / 2 (its
    membrane and bending stay zero under a translation), on every frame of a call."""
    rest, faces = _sheet()
    bv, bf = _sphere()
    k = 6
    post = _post(rest, faces, bf, k, device=device)
    rot = trimesh.transformations.rotation_matrix(0.7, [1.0, 0.3, 0.2])[:3, :3]
    frames = np.stack([rest @ rot.T + [2.0, 1.0, 0.0], rest + [0.0, 2.0, 1.5], rest + [-2.0, 1.0, 0.0]])
    out = post(torch.tensor(frames), torch.tensor(np.stack([bv] * 3))).numpy()
    drop = 9.81 * H * H * k * (k + 1) / 2
    expected = frames + np.array([0.0, -drop, 0.0])
    assert np.abs(out - expected).max() < 1e-2 * drop     # the CG solves stop at a relative 1e-3
    assert post.frames == 3 and post.report()["substeps"] == k
    rep = post.report()
    assert rep["retried_frames"] == 0 and rep["diverged_frames"] == 0 and rep["guard_retries"] == 0
    # one chunk of k substeps, each of the default's three Newton iterations
    assert rep["newton_per_substep"] == SolverConfig().newton_iterations and rep["cg_per_substep"] >= 1.0


def test_a_noisy_sheet_sunk_into_the_body_ends_outside_with_its_metric_restored():
    """A prediction-like sheet: its rest shape bent over a sphere's top, sunk 4 mm into it and
    jittered by 1.5 mm per vertex. The solver's steps leave every vertex outside the sphere, strain
    its triangles 20x less and keep it within 2 cm of where it was (in 20 substeps of 1/300 s it
    slides down the sphere by about 1 cm under gravity)."""
    r = 0.3
    rest, faces = _sheet(11, 0.2)
    bv, bf = _sphere(r)
    rng = np.random.default_rng(3)
    d = rest[:, [0, 2]]
    # On the sphere (arc length preserved along each axis, to first order), 4 mm deep, then noise.
    theta = np.linalg.norm(d, axis=1) / r
    direction = np.c_[d[:, 0], np.zeros(len(d)), d[:, 1]] / np.maximum(np.linalg.norm(d, axis=1), 1e-12)[:, None]
    onto = (r - 0.004) * (np.sin(theta)[:, None] * direction + np.cos(theta)[:, None] * [0.0, 1.0, 0.0])
    pred = onto + rng.normal(scale=0.0015, size=onto.shape)
    post = _post(rest, faces, bf, 20, SolverConfig(newton_iterations=2, contact=ContactParams(stiffness=1.0e5)))
    out = post(torch.tensor(pred[None]), torch.tensor(bv[None])).numpy()[0]
    radius = np.linalg.norm(out, axis=1)
    assert radius.min() >= r - 1e-4
    assert np.linalg.norm(pred, axis=1).min() < r - 0.005
    assert _mean_strain2(out, rest, faces) < 0.05 * _mean_strain2(pred, rest, faces)
    assert np.linalg.norm(out - pred, axis=1).max() < 0.02


def test_frames_the_guard_cannot_resolve_are_stepped_again_then_left_raw():
    """With a speed limit no falling sheet keeps (1 mm/s), the guard fails every step at every
    half-step level and the solver keeps the frames as unresolved: each is stepped once more at
    half the substep, fails again and comes back as the prediction itself, all counted."""
    rest, faces = _sheet(5)
    bv, bf = _sphere()
    post = _post(rest, faces, bf, 2, SolverConfig(max_speed=1.0e-3, max_retries=1))
    frames = np.stack([rest + [0.0, 1.0, 0.0], rest + [0.5, 1.2, 0.0]])
    out = post(torch.tensor(frames), torch.tensor(np.stack([bv] * 2))).numpy()
    assert np.array_equal(out, frames.astype(np.float32).astype(np.float64))
    rep = post.report()
    assert rep["retried_frames"] == 2 and rep["diverged_frames"] == 2 and rep["frames"] == 2


def test_a_frame_that_diverges_or_is_not_finite_stays_raw_and_the_others_are_stepped(monkeypatch):
    """Five sheets, one with a NaN and one whose instance the solver reports diverged (a stand-in
    for a step that stays non-finite after the guard's retries; a real one is rare: the PCG leaves
    a non-finite system's step at 0): those two come back as predicted and counted, and the three
    others fall as backward Euler says, as they would alone, stepped again without the diverged one."""
    from simgen.sim import ImplicitSolver, SolverDivergedError

    step = ImplicitSolver.step

    def diverging_step(self, state_in, state_out, body, dt, **kw):
        x = state_in.positions.numpy().reshape(self.model.num_instances, -1, 3)
        marked = np.flatnonzero(x[:, :, 0].mean(axis=1) > 5.0)        # the sheet placed at x = 10 m
        if len(marked):
            raise SolverDivergedError("diverged (test)", instances=marked)
        return step(self, state_in, state_out, body, dt, **kw)

    monkeypatch.setattr(ImplicitSolver, "step", diverging_step)
    rest, faces = _sheet(5)
    bv, bf = _sphere()
    k = 2
    post = _post(rest, faces, bf, k)
    frames = np.stack([rest + [0.0, 1.0, 0.0], rest + [10.0, 1.0, 0.0], rest + [0.5, 1.2, 0.0],
                       rest + [0.0, 1.0, 0.7], rest + [0.0, 1.5, 0.0]]).astype(np.float32)
    frames[3, 4, 1] = np.nan
    out = post(torch.tensor(frames), torch.tensor(np.stack([bv] * len(frames)))).numpy()
    assert np.array_equal(out[1], frames[1]) and np.array_equal(out[3], frames[3], equal_nan=True)
    drop = 9.81 * H * H * k * (k + 1) / 2
    for i in (0, 2, 4):
        assert np.abs(out[i] - frames[i] - [0.0, -drop, 0.0]).max() < 1e-2 * drop
    rep = post.report()
    assert rep["retried_frames"] == 1 and rep["diverged_frames"] == 2 and rep["frames"] == 5


def test_the_solver_settings_come_back_from_a_stores_attributes():
    """As a store writes them: JSON, an unbounded friction load as null."""
    from simgen.dataset.storage import _jsonable

    cfg = SolverConfig(newton_iterations=2, contact=ContactParams(stiffness=1.0e5), strain_limit=0.5,
                       guard_energy=False, friction=FrictionParams(max_normal_load=float("inf")))
    attrs = {"solver": {"fps": 30.0, "substeps": 10, "dt": 1.0 / 300.0,
                        "config": json.loads(json.dumps(_jsonable(asdict(cfg))))}}
    assert attrs["solver"]["config"]["friction"]["max_normal_load"] is None
    assert solver_config_from_attrs(attrs) == cfg
    with pytest.raises(InputError, match="no solver settings"):
        solver_config_from_attrs({"material": "cotton"})


def test_bad_input_is_refused():
    rest, faces = _sheet(4)
    bv, bf = _sphere()
    post = _post(rest, faces, bf, 2)
    with pytest.raises(InputError, match="points must have shape"):
        post(torch.zeros(2, 5, 3), torch.tensor(np.stack([bv] * 2)))
    with pytest.raises(InputError, match="body_vertices must have shape"):
        post(torch.tensor(rest[None]), torch.tensor(np.stack([bv] * 2)))
    with pytest.raises(InputError, match="power of two"):
        SolverPostProcess(rest, faces, np.zeros(len(rest), dtype=np.int32), "cotton", SolverConfig(), H, bf,
                          np.ones(len(bf), dtype=np.int32), chunk=12)
