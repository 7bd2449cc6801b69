"""simulate_batch() (simgen.sim.driver): N jobs in one batched system give what N separate
simulate() runs give, clips of unequal length are cut to their own frames, and an instance that
diverges fails alone (its slot reports it) while the others finish.

Tiny on purpose: the 1k-triangle T-shirt, 2 + 2 + 1 protocol frames, 3 output frames, 3 substeps.
"""

import os

import numpy as np
import pytest
import warp as wp

from simgen import body as body_pkg
from simgen.errors import InputError
from simgen.garment.library import load_garment
from simgen.motion.library import load_motion
from simgen.motion.ops import trim
from simgen.sim import (SimulationConfig, SimulationFailure, SimulationJob, SimulationResult, SolverDivergedError,
                        simulate, simulate_batch)
from simgen.sim import batch as batch_module

wp.config.quiet = True
DEVICE = os.environ.get("SIMGEN_TEST_DEVICE", "cpu")
CFG = SimulationConfig(substeps=3, relax_frames=2, ramp_frames=2, rest_frames=1, device=DEVICE)


@pytest.fixture(scope="module")
def inputs():
    body = body_pkg.load("open")
    garment = load_garment("tshirt_1k", body=body)
    walk = trim(load_motion("walk"), 2.0, 2.2)       # 7 frames at 30 fps
    squat = trim(load_motion("squat"), 0.5, 0.6)     # 4 frames
    return body, garment, walk, squat


@pytest.fixture(scope="module")
def batch(inputs):
    body, garment, walk, squat = inputs
    jobs = [SimulationJob(walk, betas=[1.0, -0.5], frames=3, key="walk"),
            SimulationJob(squat, betas=[-1.0], key="squat", material="denim")]
    return simulate_batch(garment, body, jobs, CFG)


def test_batch_equals_separate_runs(inputs, batch):
    body, garment, walk, squat = inputs
    single = [simulate(garment, body, walk, [1.0, -0.5], CFG, frames=3),
              simulate(garment, body, squat, [-1.0], SimulationConfig(**{**CFG.__dict__, "material": "denim"}))]
    for r, s in zip(batch, single):
        assert isinstance(r, SimulationResult)
        assert r.positions.shape == s.positions.shape
        # Per-instance CG, contact and friction: the instances do not interact; only float
        # summation order differs.
        assert np.abs(r.positions - s.positions).max() < 1e-4
        assert np.abs(r.protocol_positions - s.protocol_positions).max() < 1e-4
        assert r.metadata["betas"] == s.metadata["betas"] and r.metadata["material"] == s.metadata["material"]
    assert batch[0].metadata["key"] == "walk" and batch[1].metadata["batch_size"] == 2


def test_unequal_clips_cut_to_their_own_frames(inputs, batch):
    body, garment, walk, squat = inputs
    assert batch[0].num_frames == 3
    assert batch[1].num_frames == squat.num_frames == 4
    for r in batch:
        assert np.all(np.isfinite(r.positions))
        assert all(v.shape == (r.num_frames,) for v in r.stats.values())


def test_mixed_frame_rates_are_refused(inputs):
    body, garment, walk, squat = inputs
    from simgen.motion.ops import resample

    with pytest.raises(InputError, match="frame rates"):
        simulate_batch(garment, body, [SimulationJob(walk), SimulationJob(resample(squat, 60.0))], CFG)


class _Poison(batch_module.ImplicitSolver):
    """Puts NaN into the last instance's positions at its 8th step (``persistent``: at every step from
    the 8th on, so that instance diverges on every retry; else once, which a retry from the frame's
    start recovers)."""

    armed = True
    persistent = False

    def step(self, state_in, state_out, body, dt, **kw):
        self._calls = getattr(self, "_calls", 0) + 1
        if _Poison.armed and self._calls >= 8:
            _Poison.armed = _Poison.persistent
            x = state_in.positions.numpy()
            a = self.model.vertex_start[-2]  # the last instance
            x[a + 5] = np.nan
            state_in.positions.assign(x)
        return super().step(state_in, state_out, body, dt, **kw)


@pytest.fixture(scope="module")
def walk_alone(inputs):
    body, garment, walk, squat = inputs
    return simulate(garment, body, walk, None, CFG, frames=3)


def test_failed_instance_is_redone_alone(inputs, walk_alone, monkeypatch):
    """A step that fails in one instance is redone for it alone at finer steps: it recovers, and its
    batch mate's result is what it would be on its own (held, not retried)."""
    body, garment, walk, squat = inputs
    monkeypatch.setattr(batch_module, "ImplicitSolver", _Poison)
    monkeypatch.setattr(_Poison, "armed", True)
    monkeypatch.setattr(_Poison, "persistent", False)
    ok, bad = simulate_batch(garment, body, [SimulationJob(walk, frames=3, key="ok"),
                                             SimulationJob(walk, frames=3, key="bad")], CFG)
    assert isinstance(bad, SimulationResult) and np.all(np.isfinite(bad.positions))
    assert bad.protocol_stats["retries"].sum() == 1 and ok.protocol_stats["retries"].sum() == 0
    assert np.abs(ok.positions - walk_alone.positions).max() < 1e-6
    assert np.abs(ok.protocol_positions - walk_alone.protocol_positions).max() < 1e-6
    # The retried instance took half steps (5.6 ms here) through that one ramp frame: another
    # backward-Euler path, centimetres apart at these coarse test settings (5.1 cm with the T-shirt's
    # interlock, under 5 with SNUG's cotton), not a blow-up.
    assert 0 < np.abs(bad.positions - walk_alone.positions).max() < 0.08


def test_failing_instance_is_isolated(inputs, walk_alone, monkeypatch):
    body, garment, walk, squat = inputs
    monkeypatch.setattr(batch_module, "ImplicitSolver", _Poison)
    monkeypatch.setattr(_Poison, "armed", True)
    monkeypatch.setattr(_Poison, "persistent", True)
    jobs = [SimulationJob(walk, frames=3, key="ok"), SimulationJob(walk, frames=3, key="bad")]
    ok, bad = simulate_batch(garment, body, jobs, CFG)
    assert isinstance(bad, SimulationFailure) and bad.key == "bad"
    assert bad.phase == "ramp" and bad.frame == 0 and "non-finite" in bad.message   # step 8 = 3 substeps x 2 + 2
    assert isinstance(ok, SimulationResult) and np.all(np.isfinite(ok.positions))
    assert ok.positions.shape == (3, garment.num_vertices, 3)
    assert np.abs(ok.positions - walk_alone.positions).max() < 1e-6
    # simulate() turns the failure of its one instance into SolverDivergedError.
    monkeypatch.setattr(_Poison, "armed", True)
    with pytest.raises(SolverDivergedError):
        simulate(garment, body, walk, None, CFG, frames=3)
