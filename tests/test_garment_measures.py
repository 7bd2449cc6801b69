"""The size-chart measuring helpers of scripts/garment_measures.py on shapes of known size (a
cylinder, a box, an open tube, a half tube), and one pass over two 1k templates on the open body
(CPU, a few seconds)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import garment_measures as gm  # noqa: E402

sys.path.pop(0)


def tube(radius: float, y0: float, y1: float, n: int = 64, rows: int = 8, caps: bool = False,
         arc: float = 2.0 * math.pi):
    """A vertical tube round the y axis [m]: vertices (V, 3), faces (F, 3); ``caps`` closes it
    with a centre vertex at each end; ``arc`` < 2 pi makes an open half tube (a sheet)."""
    closed = arc >= 2.0 * math.pi
    cols = n if closed else n + 1
    a = np.arange(cols) * arc / n
    y = np.linspace(y0, y1, rows + 1)
    v = np.stack([np.tile(radius * np.cos(a), rows + 1), np.repeat(y, cols), np.tile(radius * np.sin(a), rows + 1)], 1)
    faces = []
    for r in range(rows):
        for c in range(n):
            p, q = r * cols + c, r * cols + (c + 1) % cols
            faces += [[p, p + cols, q], [q, p + cols, q + cols]]
    if caps:
        v = np.vstack([v, [[0.0, y0, 0.0], [0.0, y1, 0.0]]])
        bottom, top = len(v) - 2, len(v) - 1
        for c in range(n):
            faces += [[bottom, c, (c + 1) % n], [top, rows * cols + (c + 1) % n, rows * cols + c]]
    return v, np.array(faces)


def box(size):
    """An axis-aligned box [m] with one corner at the origin, 12 triangles."""
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float) * np.asarray(size)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return corners, np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def test_cylinder_section_is_a_circle():
    r = 0.15
    v, f = tube(r, 0.0, 0.6, caps=True)
    v[:, 1] = np.round(v[:, 1], 6)  # rows at exact heights: y = 0.3 goes through one of them
    (loop, closed), = gm.plane_section(v, f, 0.3)
    assert closed and len(loop) >= 64
    for y in (0.3, 0.31):
        assert gm.section_girth(v, f, y, (0.0, 0.0)) == pytest.approx(2 * math.pi * r, rel=0.01)
    assert np.isnan(gm.section_girth(v, f, 0.3, (1.0, 0.0)))  # no loop goes round a point outside
    assert np.isnan(gm.section_girth(v, f, 0.9, (0.0, 0.0)))  # above the mesh


def test_box_sections_along_two_axes():
    v, f = box((0.3, 0.5, 0.2))
    assert gm.section_girth(v, f, 0.1, (0.15, 0.1)) == pytest.approx(2 * (0.3 + 0.2), abs=1e-9)
    (loop, closed), = gm.plane_section(v, f, 0.1, axis=0)
    assert closed and gm.polyline_length(loop) == pytest.approx(2 * (0.5 + 0.2), abs=1e-9)


def test_open_tube_length_and_open_section():
    v, f = tube(0.05, 0.1, 0.5, rows=20)
    outer = lambda p: p[np.argmax(p[:, 0])]  # noqa: E731
    assert gm.silhouette_length(v, f, 0.1, 0.5, outer, step=0.01) == pytest.approx(0.4, rel=0.01)
    assert len(gm.plane_section(v, f, 0.3)) == 1
    half_v, half_f = tube(0.05, 0.1, 0.5, arc=math.pi)
    (chain, closed), = gm.plane_section(half_v, half_f, 0.3)
    assert not closed and gm.polyline_length(chain, closed=False) == pytest.approx(math.pi * 0.05, rel=0.01)


def test_slanted_silhouette_and_small_helpers():
    v, f = tube(0.05, 0.0, 0.4, rows=20)
    v[:, 0] += 0.3 * v[:, 1]  # sheared: every generator has length 0.4 * sqrt(1 + 0.3^2)
    outer = lambda p: p[np.argmax(p[:, 0])]  # noqa: E731
    assert gm.silhouette_length(v, f, 0.0, 0.4, outer) == pytest.approx(0.4 * math.hypot(1, 0.3), rel=0.01)
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], dtype=float)
    assert gm.encloses(square, (0.5, 0.5)) and not gm.encloses(square, (1.5, 0.5))
    assert gm.hull_perimeter(square[:, [0, 2]]) == pytest.approx(4.0)
    assert gm.polyline_length(square) == pytest.approx(4.0) and gm.polyline_length(square, closed=False) == 3.0


def test_two_1k_templates_on_the_open_body():
    """Invariants, not values: the cloth is outside the body, so every girth has positive ease."""
    from simgen import body as body_pkg

    body = body_pkg.load("open")
    bodies = {"beta 0 = 0": gm.shaped_body(body, 0.0)}
    shapes = {k: gm.body_measures(b) for k, b in bodies.items()}
    m = shapes["beta 0 = 0"]
    assert m["hip_y"] < m["waist_y"] < m["chest_y"] < m["hps_y"] < m["height"]
    assert m["waist"] < min(m["chest"], m["hip"])
    for name in ("tshirt_1k", "shorts_1k"):
        rows = {r["measure"]: r for r in gm.measure_garment(name, body, bodies, shapes)}
        for key in ("chest", "waist", "sleeve opening", "hip", "thigh (2.5 cm below crotch)", "leg opening"):
            if key in rows and rows[key]["garment_cm"] is not None:
                assert rows[key]["diff_cm"]["beta 0 = 0"] > 0, (name, key)
    assert rows["inseam"]["garment_cm"] > 0 and rows["outseam"]["garment_cm"] > rows["inseam"]["garment_cm"]
