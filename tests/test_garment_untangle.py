"""Untangling (simgen.garment.untangle, simgen.sim.tangle_repair) on known tangles: a bump of one
sheet pushed through another, a sleeve pushed through itself, with pins; every result is checked
with the independent brute-force crossing count of the counter's tests."""

import numpy as np
import pytest
import warp as wp

from simgen.garment.crossings import CrossingCounter
from simgen.garment.untangle import untangle
from test_garment_crossings import brute_force, grid, sleeves, two_sheets


def bumped_sheets(depth=0.03, n=20):
    """Two parallel 1 m sheets 1 cm apart (y = 0 and y = 0.01); a Gaussian bump of the upper one
    pushed ``depth`` [m] down, through the lower one. Returns positions, faces and the upper
    sheet's first vertex index."""
    v1, f1 = grid(n, n, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    v2, f2 = grid(n, n, (0.013, 0.01, 0.007), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    x, f = np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)])
    r2 = np.sum((x[len(v1):, [0, 2]] - 0.5) ** 2, axis=1)
    x[len(v1):, 1] -= depth * np.exp(-r2 / 0.02)
    return x, f, len(v1)


def test_pairs_name_every_crossing_edge_and_only_those():
    x, f = two_sheets((0.2013, -0.3071, 0.5029), (0.6, 0.0, 0.0017), (0.0, 0.6, 0.0))
    counter = CrossingCounter(f, len(x))
    pairs = counter.pairs(x)
    assert len(np.unique(pairs[:, 0])) == brute_force(x, f)
    assert set(pairs[:, 0]) == set(np.flatnonzero(counter.crossing(x)))
    # Each pair is an edge through a triangle that shares no vertex with it.
    edges, faces = counter.edges[pairs[:, 0]], f[pairs[:, 1]]
    assert not (edges[:, :, None] == faces[:, None, :]).any()
    assert len(counter.pairs(x * [1.0, 0.0, 1.0])) == 0  # both sheets flattened onto one plane: touching only


def test_a_bump_through_a_sheet_is_pushed_back_locally():
    x, f, upper = bumped_sheets()
    assert brute_force(x, f) > 0
    result = untangle(x, f)
    assert result.untangled and brute_force(result.positions, f) == 0
    assert result.crossings_before == brute_force(x, f) and result.rounds <= 20
    # Only vertices near the bump moved, by no more than the bump's depth and the margin.
    moved = np.linalg.norm(result.positions - x, axis=1) > 0
    centre = np.linalg.norm(x[:, [0, 2]] - 0.5, axis=1)
    assert moved.any() and centre[moved].max() < 0.35
    assert result.max_displacement < 0.03 + 0.005


def test_a_pinned_sheet_stays_and_the_other_one_moves():
    x, f, upper = bumped_sheets()
    pinned = np.zeros(len(x), dtype=bool)
    pinned[:upper] = True
    result = untangle(x, f, pinned=pinned)
    assert result.untangled and brute_force(result.positions, f) == 0
    assert np.array_equal(result.positions[:upper], x[:upper])
    # The bump came back above the pinned sheet where it lies over it.
    over = (np.abs(x[upper:, 0] - 0.5) < 0.3) & (np.abs(x[upper:, 2] - 0.5) < 0.3)
    assert result.positions[upper:][over, 1].min() > 0.0


def test_a_sleeve_pushed_through_itself_is_untangled_without_exploding():
    _, flat, tangled, f = sleeves()
    assert brute_force(tangled, f) > 0
    result = untangle(tangled, f)
    assert result.untangled and brute_force(result.positions, f) == 0
    assert np.all(np.isfinite(result.positions)) and result.max_displacement < 0.03  # the sleeve's radius is 5 cm


def test_with_a_reference_the_vertex_that_left_its_side_goes_back():
    """Two sheets 1 cm apart; one vertex of the upper sheet dragged 2 cm down through the lower
    one (a single-frame slip): with the clean state as reference, one round moves that vertex back
    above the lower sheet (and at most a neighbour of the lower sheet that its spike's tilted
    triangles now put on their other side)."""
    x, f, upper = bumped_sheets(depth=0.0)
    clean = x.copy()
    k = upper + int(np.argmin(np.linalg.norm(x[upper:, [0, 2]] - 0.5, axis=1)))
    x[k, 1] -= 0.02
    assert brute_force(x, f) > 0 and brute_force(clean, f) == 0
    result = untangle(x, f, reference=clean)
    assert result.untangled and result.rounds == 1 and result.moved <= 2
    assert 0.0 < result.positions[k, 1] < 0.01 and brute_force(result.positions, f) == 0
    with pytest.raises(Exception, match="reference"):
        untangle(x, f, reference=clean[:-1])


def test_a_boundary_fold_the_pushes_cannot_close_is_rolled_back_to_the_reference():
    """A real tangle (tests/data/untangle_collar_fold.npz, float32): the coarse T-shirt of before
    2026-11-29 in kick at beta 1 = +2, frame 23 of scripts/untangle_replay.py, one collar edge
    through its neighbour triangle at the neckline, and frame 22 (clean) as reference. Pushing the
    edge's vertex through the triangle's plane makes its other edges cross and the next round
    pushes it back, so global intersection analysis alone swings it for all its rounds (200); with
    the reference, untangle's roll-back (after ROLLBACK_AFTER rounds) clears it, moving the crossing's
    vertices and their neighbours toward the reference by a couple of centimetres at most."""
    from pathlib import Path

    from simgen.garment.untangle import ROLLBACK_AFTER

    with np.load(Path(__file__).parent / "data" / "untangle_collar_fold.npz") as d:
        x, reference, f = d["positions"].astype(np.float64), d["reference"].astype(np.float64), d["faces"]
    assert brute_force(x, f) > 0 and brute_force(reference, f) == 0
    alone = untangle(x, f)
    assert alone.rounds > ROLLBACK_AFTER  # the pushes alone do not close it before the roll-back would start
    result = untangle(x, f, reference=reference)
    assert result.untangled and result.rounds > ROLLBACK_AFTER and brute_force(result.positions, f) == 0
    moved = np.linalg.norm(result.positions - x, axis=1) > 0
    assert 0 < moved.sum() <= 30 and result.max_displacement < 0.03
    # Every moved vertex ended closer to the reference than it started.
    before = np.linalg.norm(x[moved] - reference[moved], axis=1)
    after = np.linalg.norm(result.positions[moved] - reference[moved], axis=1)
    assert np.all(after < before + 1e-9)


def test_clean_cloth_is_left_exactly_as_it_is_and_bad_input_is_refused():
    _, flat, _, f = sleeves()
    result = untangle(flat, f)
    assert result.rounds == 0 and result.moved == 0 and np.array_equal(result.positions, flat)
    with pytest.raises(Exception, match="positions"):
        untangle(flat[:, :2], f)
    with pytest.raises(Exception, match="pinned"):
        untangle(flat, f, pinned=np.zeros(3, dtype=bool))


def test_frame_end_repair_untangles_busy_instances_only():
    """TangleRepair on a two-instance cloth state: the busy tangled copy is untangled and loses the
    velocity that pointed back through; the idle tangled copy is left as it is."""
    from simgen.sim.tangle_repair import TangleRepair

    x, f, upper = bumped_sheets(n=12)
    model = _two_copies(x, f)
    state = model.state()
    both = np.vstack([x, x])
    state.positions.assign(both.astype(np.float32))
    velocity = np.zeros_like(both)
    velocity[:, 1] = -1.0   # everything moving down, the way the bump went through
    state.velocities.assign(velocity.astype(np.float32))
    repair = TangleRepair(f, len(x), 2, "cpu")
    moved = repair(state, model.vertex_pinned, np.array([True, False]), reference=None)
    assert moved == [0] and repair.repaired.tolist() == [1, 0] and repair.left.tolist() == [0, 0]
    out, v = state.positions.numpy().astype(np.float64), state.velocities.numpy()
    assert brute_force(out[:len(x)], f) == 0 and brute_force(out[len(x):], f) == brute_force(x, f)
    shift = out[:len(x)] - x
    moved = np.linalg.norm(shift, axis=1) > 1e-6
    back = np.einsum("ij,ij->i", v[:len(x)][moved], shift[moved]) / np.linalg.norm(shift[moved], axis=1)
    assert moved.any() and back.min() > -1e-6                     # nothing moves back the way it was pushed
    still = ~moved
    assert np.allclose(v[:len(x)][still, 1], -1.0) and np.allclose(v[len(x):, 1], -1.0)


def _two_copies(x, f):
    from simgen.sim.model import ClothModelBuilder

    b = ClothModelBuilder()
    for _ in range(2):
        b.add_instance(x, f, "interlock")
    return b.finalize("cpu", dtype=wp.float32)


def test_frame_end_repair_on_the_device_takes_the_frame_start_as_reference():
    """With the frame's start (two clean sheets 1 cm apart) as reference, the device rounds put the
    bump that went through back above the lower sheet; nothing is left for the host."""
    from simgen.sim.tangle_repair import TangleRepair

    x, f, upper = bumped_sheets(n=12)
    clean, _, _ = bumped_sheets(depth=0.0, n=12)
    model = _two_copies(x, f)
    state = model.state()
    state.positions.assign(np.vstack([x, x]).astype(np.float32))
    state.velocities.zero_()
    reference = wp.array(np.vstack([clean, clean]).astype(np.float32), dtype=wp.vec3, device="cpu")
    repair = TangleRepair(f, len(x), 2, "cpu")
    assert repair(state, model.vertex_pinned, np.array([True, True]), reference=reference) == [0, 1]
    out = state.positions.numpy().astype(np.float64)
    for k in range(2):
        assert brute_force(out[k * len(x):(k + 1) * len(x)], f) == 0
    assert repair.left.tolist() == [0, 0] and out[:upper, 1].max() == 0.0  # the lower sheet stayed
