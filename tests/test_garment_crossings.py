"""The crossing-edge counter (simgen.garment.crossings) on known tangles and known clean folds,
against an independent brute-force float64 count over every edge-triangle pair."""

import numpy as np
import pytest

from simgen.errors import InputError
from simgen.garment.crossings import CrossingCounter, count_crossing_edges, crossing_edges
from simgen.garment.mesh import unique_edges


def grid(nu: int, nv: int, origin, du, dv):
    """A sheet of (nu+1) x (nv+1) vertices spanned by du, dv [m] from origin, two triangles a cell."""
    o, du, dv = (np.asarray(a, dtype=np.float64) for a in (origin, du, dv))
    v = np.array([o + i / nu * du + j / nv * dv for i in range(nu + 1) for j in range(nv + 1)])
    f = []
    for i in range(nu):
        for j in range(nv):
            a, b, c, d = i * (nv + 1) + j, (i + 1) * (nv + 1) + j, (i + 1) * (nv + 1) + j + 1, i * (nv + 1) + j + 1
            f += [[a, b, c], [a, c, d]]
    return v, np.array(f)


def two_sheets(second_origin, second_du, second_dv, n=6):
    v1, f1 = grid(n, n, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    v2, f2 = grid(n, n, second_origin, second_du, second_dv)
    return np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)])


def brute_force(x, faces) -> int:
    """Crossing edges by the module's definition, all pairs, vectorised numpy float64."""
    edges = unique_edges(faces)
    p, q = x[edges[:, 0]][:, None], x[edges[:, 1]][:, None]
    a, b, c = (x[faces[:, k]][None] for k in range(3))

    def orient(u, v, w, z):
        return np.einsum("...i,...i->...", v - u, np.cross(w - u, z - u))

    sp, sq = orient(a, b, c, p), orient(a, b, c, q)
    t1, t2, t3 = orient(p, q, a, b), orient(p, q, b, c), orient(p, q, c, a)
    hit = (sp * sq < 0) & (((t1 > 0) & (t2 > 0) & (t3 > 0)) | ((t1 < 0) & (t2 < 0) & (t3 < 0)))
    shares = (edges[:, None, :, None] == faces[None, :, None, :]).any(axis=(2, 3))
    return int((hit & ~shares).any(axis=1).sum())


def test_a_sheet_pushed_through_another_counts_the_piercing_edges_of_both():
    # A vertical sheet through the middle of a horizontal one, at generic offsets.
    x, f = two_sheets((0.2013, -0.3071, 0.5029), (0.6, 0.0, 0.0017), (0.0, 0.6, 0.0))
    n = int(count_crossing_edges(x, f)[0])
    assert n == brute_force(x, f)
    # At least every column edge of the second sheet spanning y = 0 pierces the first sheet.
    assert n >= 7
    pairs = crossing_edges(x, f)
    assert len(pairs) == n and set(map(tuple, pairs)) <= set(map(tuple, unique_edges(f)))


def test_clean_layers_and_folds_count_zero_however_close():
    # A second sheet 0.1 mm above the first (a fold lying on itself), and one exactly on its plane.
    for gap in (1e-4, 1e-6, 0.0):
        x, f = two_sheets((0.0137, gap, 0.0211), (0.97, 0.0, 0.0), (0.0, 0.0, 0.95))
        assert int(count_crossing_edges(x, f)[0]) == 0 == brute_force(x, f)
    # A sheet folded flat onto itself along a hinge line (adjacent triangles share vertices).
    v, f = grid(6, 6, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    folded = v.copy()
    right = folded[:, 0] > 0.5
    folded[right, 0] = 1.0 - folded[right, 0]
    folded[right, 1] = 1e-4 * (v[right, 0] - 0.5)
    assert int(count_crossing_edges(folded, f)[0]) == 0 == brute_force(folded, f)


def test_touching_is_not_crossing():
    # One triangle and a separate edge-sharing-nothing triangle whose corner ends exactly on its plane.
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1], [0.25, 0.0, 0.25], [0.25, 0.5, 0.25], [0.3, 0.5, 0.2]], float)
    f = np.array([[0, 2, 1], [3, 4, 5]])
    assert int(count_crossing_edges(x, f)[0]) == 0 == brute_force(x, f)
    x[3, 1] = -1e-9   # now just through
    assert int(count_crossing_edges(x, f)[0]) == 2 == brute_force(x, f)


def tube(n_around=12, n_along=8, radius=0.05, length=0.4):
    """An open cylinder along x (a sleeve), vertices (n_along+1) rings of n_around."""
    v = np.array([[length * i / n_along, radius * np.cos(2 * np.pi * k / n_around),
                   radius * np.sin(2 * np.pi * k / n_around)] for i in range(n_along + 1) for k in range(n_around)])
    f = []
    for i in range(n_along):
        for k in range(n_around):
            a, b = i * n_around + k, i * n_around + (k + 1) % n_around
            c, d = a + n_around, b + n_around
            f += [[a, b, d], [a, d, c]]
    return v, np.array(f)


def sleeves():
    """A tube (a sleeve) as built, squashed flat to 1 mm (its two walls lie on each other: clean),
    and squashed with a patch of the upper wall pushed 2 mm through the lower one (tangled)."""
    v, f = tube()
    flat = v.copy()
    flat[:, 1] *= 0.01
    tangled = flat.copy()
    top = (tangled[:, 1] > 1e-6) & (np.abs(tangled[:, 0] - 0.2) < 0.06)
    tangled[top, 1] -= 0.002
    return v, flat, tangled, f


def test_a_sleeve_squashed_flat_is_clean_and_one_pushed_through_itself_is_not():
    v, flat, tangled, f = sleeves()
    assert int(count_crossing_edges(flat, f)[0]) == 0 == brute_force(flat, f)
    n = int(count_crossing_edges(tangled, f)[0])
    assert n > 0 and n == brute_force(tangled, f)


def test_counter_counts_every_frame_and_refuses_bad_input():
    v, flat, tangled, f = sleeves()
    counter = CrossingCounter(f, len(v))
    counts = counter.count(np.stack([v, flat, tangled, flat]))
    assert counts[0] == counts[1] == counts[3] == 0 and counts[2] > 0
    with pytest.raises(Exception, match="shape"):
        counter.count(np.zeros((2, 3, 3)))
    bad = v.copy()
    bad[0, 0] = np.nan
    with pytest.raises(Exception, match="NaN"):
        counter.crossing(bad)


def test_dataset_check_lists_crossings_and_warns_past_the_limits():
    """Per sequence: frames with crossings, the longest run, the most edges; past 0.5% of the frames
    or 3 frames in a row the check names the sequence (a warning until self-collision is on)."""
    from types import SimpleNamespace

    from simgen.dataset.check import CheckReport, _check_sequence_crossings

    v, flat, tangled, f = sleeves()
    ctx = SimpleNamespace(crossings=CrossingCounter(f, len(v)))
    clean, one = [flat] * 400, [flat] * 399 + [tangled]           # one frame of 400: 0.25%, no warning
    three = [flat] * 1000 + [tangled] * 3 + [flat] * 997           # 3 in a row, 0.15%
    four = [flat] * 1000 + [tangled] * 4 + [flat] * 996            # 4 in a row
    rep = CheckReport(path="mem")
    for sid, frames in (("clean", clean), ("one", one), ("three", three), ("four", four)):
        _check_sequence_crossings(rep, f"sequences/{sid}", sid, np.stack(frames), ctx)
    assert set(rep.crossings) == {"one", "three", "four"}
    assert rep.crossings["four"] == {"frames": 4, "longest_run": 4, "max_edges": rep.max_crossing_edges,
                                     "first_frame": 1000}
    assert [w["node"] for w in rep.warnings] == ["sequences/four"] and rep.passed
    assert rep.crossing_frames == 1 + 3 + 4
    assert rep.to_dict()["crossings"]["three"]["longest_run"] == 3


def test_copies_side_by_side_are_counted_each_against_itself():
    """A batched state: three overlapping copies of a sleeve (clean, tangled, clean) in one array;
    each copy counts only its own crossings (the copies pass through each other everywhere)."""
    import warp as wp

    v, flat, tangled, f = sleeves()
    shifted = flat + [0.1, 0.0, 0.0]                  # overlaps the others, crossing them, not itself
    counter = CrossingCounter(f, len(v), instances=3)
    points = wp.array(np.vstack([flat, tangled, shifted]).astype(np.float32), dtype=wp.vec3)
    counts = counter.count_points(points)
    assert counts[0] == counts[2] == 0
    assert counts[1] == count_crossing_edges(tangled.astype(np.float32), f)[0] > 0
    # Counting some copies only (a pool's busy slots): theirs as before, the others 0, then all again.
    assert counter.count_points(points, [1, 2]).tolist() == [0, counts[1], 0]
    assert counter.count_points(points, [0]).tolist() == [0, 0, 0]
    assert counter.count_points(points).tolist() == counts.tolist()
    with pytest.raises(InputError, match="instances \\[0, 3\\]"):
        counter.count_points(points, [3, 0])
