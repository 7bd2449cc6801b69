"""Garment templates: the bundled assets meet the quality contract, generation is reproducible and
works on another body shape, and every contract item catches the defect it is about.

The contract is checked against things nobody here chose: mesh topology (manifoldness, Euler
characteristic of the openings, orientation), the body's skin (signed distance by winding number)
and anthropometric landmarks of the body (joints, natural waist, crotch, knees, ankles).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from simgen.assets import bundled_dir
from simgen.errors import InputError
from simgen.garment.check import CheckReport, check_garment
from simgen.garment.garment import Garment
from simgen.garment.mesh import boundary_loops, connected_components, non_manifold_edges
from simgen.garment.templates import (DEFAULT_MATERIALS, DEFAULT_SKINNING, DEFAULT_TRIANGLES, EXPECTED_OPENINGS,
                                      TEMPLATE_NAMES, generate_template)

GENERIC_ITEMS = ("body", "manifold_edges", "manifold_vertices", "single_component", "consistent_orientation",
                 "outward_orientation", "openings", "min_angle", "edge_spread", "not_inside", "clearance", "ease")
TEMPLATE_ITEMS = {
    "tshirt": ("coverage_neck", "coverage_sleeves", "coverage_hem"),
    "tank_top": ("coverage_neck", "coverage_no_sleeves", "coverage_hem"),
    "dress": ("coverage_neck", "coverage_no_sleeves", "coverage_hem", "hem_clear_of_legs"),
    "skirt": ("coverage_waist", "coverage_hem", "hem_clear_of_legs"),
    "pants": ("coverage_waist", "coverage_hems"),
    "shorts": ("coverage_waist", "coverage_hems"),
}
OPENING_NAMES = {
    "tshirt": {"neck", "hem", "left_sleeve", "right_sleeve"},
    "tank_top": {"neck", "hem", "left_armhole", "right_armhole"},
    "dress": {"neck", "hem", "left_armhole", "right_armhole"},
    "skirt": {"waist", "hem"},
    "pants": {"waist", "left_hem", "right_hem"},
    "shorts": {"waist", "left_hem", "right_hem"},
}
BUNDLED = [(name, suffix) for name in TEMPLATE_NAMES for suffix in ("", "_1k")]


@pytest.fixture(scope="module")
def body():
    from simgen.body import load

    return load("open")


_garments: dict[str, Garment] = {}
_reports: dict[str, CheckReport] = {}


def bundled(name: str) -> Garment:
    if name not in _garments:
        _garments[name] = Garment.load(bundled_dir("garments") / name)
    return _garments[name]


def report_of(name: str, body) -> CheckReport:
    if name not in _reports:
        _reports[name] = check_garment(bundled(name), body)
    return _reports[name]


def moved(garment: Garment, vertices: np.ndarray | None = None, faces: np.ndarray | None = None,
          template: str | None = None) -> Garment:
    """A copy of a garment with other vertices and/or faces (weights kept when the count allows)."""
    v = garment.vertices if vertices is None else vertices
    f = garment.faces if faces is None else faces
    w = garment.skin_weights if len(v) == garment.num_vertices else np.tile(np.eye(24)[0], (len(v), 1))
    meta = dict(garment.metadata)
    if template is not None:
        meta["template"] = template
    return Garment(garment.name, v, f, w, meta)


def interior_vertex(garment: Garment) -> int:
    """An interior vertex far from every opening (the one farthest from the boundary)."""
    loops = np.concatenate(boundary_loops(garment.faces))
    d = np.linalg.norm(garment.vertices[:, None] - garment.vertices[loops][None], axis=2).min(axis=1)
    return int(np.argmax(d))


# ------------------------------------------------------------------------------------ bundled assets
@pytest.mark.parametrize("name,suffix", BUNDLED)
def test_bundled_template_loads_with_its_metadata(name, suffix, body):
    g = bundled(name + suffix)
    meta = g.metadata
    assert meta["template"] == name
    assert meta["body"]["hash"] == body.hash, "rebuild the garments: python scripts/build_garments.py"
    assert meta["default_material"] == DEFAULT_MATERIALS[name]
    assert meta["skinning"]["method"] == DEFAULT_SKINNING[name]
    assert {o["name"] for o in meta["openings"]} == OPENING_NAMES[name]
    assert meta["made_by"]["how"] == "generated" and meta["quality"]["passed"]
    assert np.all(g.skin_weights >= 0.0) and np.allclose(g.skin_weights.sum(axis=1), 1.0, atol=1e-5)
    # Topology read straight off the mesh (independent of the check module): Euler characteristic
    # of a sphere with k holes is 2 - k.
    e = np.unique(np.sort(np.concatenate([g.faces[:, [0, 1]], g.faces[:, [1, 2]], g.faces[:, [2, 0]]]), axis=1), axis=0)
    assert g.num_vertices - len(e) + g.num_triangles == 2 - EXPECTED_OPENINGS[name]


@pytest.mark.parametrize("name", TEMPLATE_NAMES)
def test_bundled_sizes(name):
    full, coarse = bundled(name), bundled(name + "_1k")
    if name == "tshirt":  # the thesis T-shirt: 4,424 vertices, 8,710 triangles
        assert abs(full.num_triangles - 8710) <= 0.03 * 8710 and abs(full.num_vertices - 4424) <= 0.03 * 4424
    elif name == "dress":
        assert 12_000 <= full.num_triangles <= 24_000
    else:
        assert 4_000 <= full.num_triangles <= 12_000
    assert abs(full.num_triangles - DEFAULT_TRIANGLES[name]) <= 0.03 * DEFAULT_TRIANGLES[name]
    assert 900 <= coarse.num_triangles <= 1100


@pytest.mark.parametrize("item", GENERIC_ITEMS)
@pytest.mark.parametrize("name,suffix", BUNDLED)
def test_bundled_template_meets_generic_contract(name, suffix, item, body):
    it = report_of(name + suffix, body).item(item)
    assert it.passed, f"{name}{suffix}: {item}: {it.message}"


@pytest.mark.parametrize("name,suffix,item", [(n, s, i) for n, s in BUNDLED for i in TEMPLATE_ITEMS[n]])
def test_bundled_template_meets_coverage_contract(name, suffix, item, body):
    it = report_of(name + suffix, body).item(item)
    assert it.passed, f"{name}{suffix}: {item}: {it.message}"


def test_report_is_complete_and_serialisable(body):
    r = report_of("skirt_1k", body)
    assert r.passed and r.template == "skirt"
    assert r.names() == list(GENERIC_ITEMS) + list(TEMPLATE_ITEMS["skirt"])
    d = json.loads(json.dumps(r.to_dict()))
    assert d["passed"] and len(d["items"]) == len(r.items)
    text = r.format()
    assert "PASSED" in text and all(name in text for name in r.names())
    ease = r.item("ease").values["regions"]
    # The waistband is tight, the flared hem loose (ease grows downwards).
    assert ease["spine1"]["fit"] == "tight" and ease["left_hip"]["mean_m"] > 2 * ease["spine1"]["mean_m"]


def test_imported_garment_gets_generic_checks_only(body):
    g = bundled("tshirt_1k")
    anon = Garment("my_top", g.vertices, g.faces, g.skin_weights, {})
    r = check_garment(anon, body)
    assert r.template is None and r.names() == list(GENERIC_ITEMS) and r.passed


# ------------------------------------------------------------------------------------ generation
def test_generate_is_deterministic_and_seed_changes_the_triangulation(body):
    v1, f1, info1 = generate_template("shorts", body, target_triangles=1000)
    v2, f2, _ = generate_template("shorts", body, target_triangles=1000)
    assert np.array_equal(v1, v2) and np.array_equal(f1, f2)
    assert {o["name"] for o in info1["openings"]} == OPENING_NAMES["shorts"]
    v3, f3, _ = generate_template("shorts", body, target_triangles=1000, seed=1)
    assert len(v3) != len(v1) or not np.array_equal(v1, v3)
    g3 = Garment("shorts_seed1", v3, f3, np.tile(np.eye(24)[0], (len(v3), 1)), {"template": "shorts"})
    r = check_garment(g3, body)
    assert r.passed, r.format()


def test_generate_rejects_bad_arguments(body):
    with pytest.raises(InputError, match="unknown garment template"):
        generate_template("poncho", body)
    with pytest.raises(InputError, match="at least 300"):
        generate_template("skirt", body, target_triangles=50)


@pytest.fixture(scope="module")
def tall_body(body):
    """The open body with betas [2, 0, ...] (taller) baked into a rest template of its own."""
    shaped = body.shaped_vertices(np.array([2.0]))[0]
    return dataclasses.replace(body, v_template=shaped, name="open_beta0_plus2")


@pytest.mark.parametrize("name", TEMPLATE_NAMES)
def test_templates_fit_another_body_shape(name, tall_body, body):
    assert np.ptp(tall_body.v_template[:, 1]) > np.ptp(body.v_template[:, 1]) + 0.1
    v, f, info = generate_template(name, tall_body, target_triangles=1000)
    g = Garment(name, v, f, np.tile(np.eye(24)[0], (len(v), 1)), {"template": name})
    r = check_garment(g, tall_body)
    assert r.passed, r.format()
    assert {o["name"] for o in info["openings"]} == OPENING_NAMES[name]
    # The garment follows the body: the landmarks it was cut at moved up with the taller body.
    assert info["landmarks"]["waist_y"] > 1.1


def test_build_writes_a_loadable_variant(tmp_path, body):
    from simgen.garment.build import build_garment, variant_name

    assert [variant_name("tshirt"), variant_name("tshirt", 1000), variant_name("skirt", 2500)] == \
        ["tshirt", "tshirt_1k", "skirt_2500"]
    g = build_garment("skirt", body, target_triangles=700, out_dir=tmp_path)
    loaded = Garment.load(tmp_path / "skirt_700")
    assert loaded.num_triangles == g.num_triangles and loaded.metadata["skinning"]["method"] == "diffused"
    assert loaded.metadata["body"]["hash"] == body.hash and loaded.metadata["quality"]["passed"]
    assert check_garment(loaded, body).passed


# ------------------------------------------------------------------------------------ negative tests
@pytest.fixture(scope="module")
def shirt():
    return bundled("tshirt_1k")


def failed(garment: Garment, body, item: str, **kw) -> CheckReport:
    r = check_garment(garment, body, **kw)
    assert not r.item(item).passed, f"{item} should fail: {r.item(item).message}"
    assert not r.passed
    return r


def test_removed_face_adds_an_opening(shirt, body):
    v = interior_vertex(shirt)
    face = np.flatnonzero((shirt.faces == v).any(axis=1))[0]
    r = failed(moved(shirt, faces=np.delete(shirt.faces, face, axis=0)), body, "openings")
    assert r.item("openings").values["openings"] == 5
    assert r.item("manifold_edges").passed


def test_flipped_face_fails_orientation(shirt, body):
    f = shirt.faces.copy()
    f[10] = f[10, ::-1]
    failed(moved(shirt, faces=f), body, "consistent_orientation")


def test_inward_normals_fail_outward_orientation(shirt, body):
    r = failed(moved(shirt, faces=shirt.faces[:, ::-1].copy()), body, "outward_orientation")
    assert r.item("consistent_orientation").passed
    assert r.item("outward_orientation").values["closed_volume_m3"] < 0


def test_third_triangle_on_an_edge_is_non_manifold(shirt, body):
    a, b = shirt.faces[0, :2]
    tip = shirt.vertices[[a, b]].mean(axis=0) + np.array([0.0, 0.0, 0.05])
    v = np.vstack([shirt.vertices, tip])
    f = np.vstack([shirt.faces, [[a, b, len(v) - 1]]])
    r = failed(moved(shirt, v, f), body, "manifold_edges")
    assert len(non_manifold_edges(f)) == 1 and r.item("manifold_edges").values["non_manifold_edges"] == 1


def test_bow_tie_vertex_is_non_manifold(shirt, body):
    v = interior_vertex(shirt)
    fan = np.flatnonzero((shirt.faces == v).any(axis=1))
    # Order the fan around v and drop two opposite triangles: two fans meet at v only.
    f = shirt.faces
    ring = [fan[0]]
    while len(ring) < len(fan):
        last = set(f[ring[-1]].tolist())
        nxt = [t for t in fan if t not in ring and len(last & set(f[t].tolist())) == 2]
        ring.append(nxt[0])
    drop = [ring[0], ring[len(ring) // 2]]
    failed(moved(shirt, faces=np.delete(f, drop, axis=0)), body, "manifold_vertices")


def test_extra_piece_fails_single_component(shirt, body):
    far = np.array([[0.0, 2.2, 0.5], [0.05, 2.2, 0.5], [0.0, 2.25, 0.5]])
    v = np.vstack([shirt.vertices, far])
    n = shirt.num_vertices
    f = np.vstack([shirt.faces, [[n, n + 1, n + 2]]])
    r = failed(moved(shirt, v, f), body, "single_component")
    assert r.item("single_component").values["components"] == 2
    assert connected_components(f, len(v))[0] == 2


def test_thin_triangle_fails_min_angle_and_edge_spread(shirt, body):
    v = shirt.vertices.copy()
    i = interior_vertex(shirt)
    j = [x for x in shirt.faces[(shirt.faces == i).any(axis=1)].ravel() if x != i][0]
    v[i] = v[i] + 0.9 * (v[j] - v[i])
    failed(moved(shirt, v), body, "min_angle")
    failed(moved(shirt, v), body, "edge_spread")


def test_vertex_inside_the_body_fails_clearance(shirt, body):
    from simgen.body.surface import project_to_surface

    v = shirt.vertices.copy()
    i = interior_vertex(shirt)
    p = project_to_surface(v[i:i + 1], body.v_template, body.faces)
    v[i] = p.closest[0] - 0.01 * (v[i] - p.closest[0]) / np.linalg.norm(v[i] - p.closest[0])
    r = failed(moved(shirt, v), body, "not_inside")
    assert r.item("not_inside").values["vertices_inside"] == 1
    assert not r.item("clearance").passed


def test_vertex_one_millimetre_out_fails_clearance_only(shirt, body):
    from simgen.body.surface import project_to_surface

    v = shirt.vertices.copy()
    i = interior_vertex(shirt)
    p = project_to_surface(v[i:i + 1], body.v_template, body.faces)
    v[i] = p.closest[0] + 0.001 * (v[i] - p.closest[0]) / np.linalg.norm(v[i] - p.closest[0])
    r = failed(moved(shirt, v), body, "clearance")
    assert r.item("not_inside").passed
    assert 0.0 < r.item("clearance").values["min_signed_distance_m"] < 0.002


def test_cloth_far_from_the_body_fails_ease(shirt, body):
    from simgen.body.surface import project_to_surface

    v = shirt.vertices.copy()
    i = interior_vertex(shirt)
    p = project_to_surface(v[i:i + 1], body.v_template, body.faces)
    v[i] = p.closest[0] + 0.5 * (v[i] - p.closest[0]) / np.linalg.norm(v[i] - p.closest[0])
    r = failed(moved(shirt, v), body, "ease")
    assert r.item("ease").values["max_m"] > 0.45


def test_garment_of_another_body_fails_body(shirt, tall_body):
    failed(shirt, tall_body, "body")


@pytest.mark.parametrize("garment,template,shift,item", [
    ("tshirt_1k", "tshirt", (0.0, 0.25, 0.0), "coverage_hem"),  # hem above the natural waist
    ("tshirt_1k", "tshirt", (0.15, 0.0, 0.0), "coverage_neck"),  # neck loop beside the neck
    ("tank_top_1k", "tshirt", (0.0, 0.0, 0.0), "coverage_sleeves"),  # a tank top has no sleeves
    ("tshirt_1k", "tank_top", (0.0, 0.0, 0.0), "coverage_no_sleeves"),  # a T-shirt has sleeves
    ("dress_1k", "dress", (0.0, 0.15, 0.0), "coverage_hem"),  # hem above the knees
    ("skirt_1k", "skirt", (0.0, -0.15, 0.0), "coverage_hem"),  # hem below the knees
    ("skirt_1k", "skirt", (0.0, 0.2, 0.0), "coverage_waist"),  # waistband up on the ribs
    ("pants_1k", "pants", (0.0, 0.2, 0.0), "coverage_hems"),  # hems far above the ankles
    ("shorts_1k", "shorts", (0.0, -0.2, 0.0), "coverage_hems"),  # hems below the knees
])
def test_coverage_rules_catch_misplaced_garments(garment, template, shift, item, body):
    g = bundled(garment)
    failed(moved(g, g.vertices + np.asarray(shift), template=template), body, item)


def test_hem_between_or_on_the_legs_fails(body):
    g = bundled("skirt_1k")
    v = g.vertices.copy()
    # Pull the skirt in round the body's vertical axis: the hem now runs on (and into) the thighs.
    v[:, [0, 2]] *= 0.6
    failed(moved(g, v), body, "hem_clear_of_legs")


# ------------------------------------------------------------------------------------ building blocks
def test_split_along_level_set_inserts_the_curve_as_closed_edge_chains():
    import gpytoolbox

    from simgen.garment.mesh import is_consistently_oriented, non_manifold_vertices
    from simgen.garment.remesh import split_along_level_set

    from simgen.garment.mesh import edge_lengths, triangle_areas, unique_edges

    v, f = gpytoolbox.icosphere(3)
    f = f.astype(np.int64)
    plane = lambda p: p[:, 2] - 0.3 + 0.2 * p[:, 0]  # noqa: E731 - linear: interpolation is exact
    edge = edge_lengths(v, unique_edges(f))
    for snap in (0.0, 0.15):
        sv, sf, curve = split_along_level_set(v, f, plane(v), snap=snap)
        on = np.unique(curve)
        # On the plane exactly without snapping; nudged by at most snap x the longest edge with it.
        assert np.abs(plane(sv[on])).max() <= 1e-12 + snap * edge.max()
        assert len(boundary_loops(sf)) == 0 and len(non_manifold_vertices(sf)) == 0
        assert is_consistently_oriented(sf)
        assert np.all(np.bincount(curve.ravel())[on] == 2)  # each curve vertex joins two curve edges
        assert triangle_areas(sv, sf).sum() == pytest.approx(triangle_areas(v, f).sum(), rel=1e-9)
    # Snapping keeps every new edge longer than a fraction of the original ones.
    assert edge_lengths(sv, unique_edges(sf)).min() > 0.1 * edge.min()


def test_convex_polygon_distance_is_exact_off_the_corners():
    from simgen.garment.envelope import _convex_polygon_distance

    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])  # counter-clockwise
    pts = np.array([[0.5, 0.5], [0.5, -0.3], [1.2, 0.4], [0.5, 0.9]])
    assert np.allclose(_convex_polygon_distance(pts, square), [-0.5, 0.3, 0.2, -0.1])


def test_delaunay_flip_fixes_a_bad_diagonal():
    from simgen.garment.remesh import delaunay_flips

    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.1, 0.0], [1.0, 0.2, 0.0]])
    f = np.array([[0, 1, 3], [1, 2, 3]])  # diagonal 1-3 is short: both opposite angles are wide
    f2, flips = delaunay_flips(v, np.array([[0, 1, 2], [0, 2, 3]]))
    assert flips == 1 and {tuple(sorted(t)) for t in f2.tolist()} == {tuple(sorted(t)) for t in f.tolist()}


def test_landmarks_are_anthropometric(body):
    from simgen.garment.envelope import body_landmarks

    lm = body_landmarks(body)
    j = {n: lm.joint(n) for n in ("pelvis", "spine3", "left_knee", "left_shoulder", "neck")}
    assert 1.5 < lm.height < 1.9
    assert j["pelvis"][1] < lm.waist_y < j["spine3"][1]  # the natural waist is above the hip bones
    assert 0.55 < lm.waist_y / lm.height < 0.70  # ~0.63 of stature in anthropometric tables
    assert j["left_knee"][1] < lm.crotch_y < j["pelvis"][1]
    assert np.all(lm.armpit_y < j["left_shoulder"][1]) and np.all(lm.armpit_y > lm.waist_y)
    assert 0.04 < lm.neck_extent[0] < 0.12  # half the neck's width at the neck joint
