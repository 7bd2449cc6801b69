"""OBJ garment import: a good file imports with its safe repairs reported; each broken file is refused
with an InputError that names the problem, and nothing is written; garbled text never crashes.
Also the garment library lookup (user folder first, body check)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from garment_bodies import skirt, two_leg_body
from simgen.errors import InputError
from simgen.garment import (
    Garment,
    GarmentImportError,
    import_garment_obj,
    list_garments,
    load_garment,
    validate_obj,
)
from simgen.garment.obj_import import MAX_TRIANGLES


@pytest.fixture(scope="module")
def body():
    return two_leg_body()


@pytest.fixture(scope="module")
def skirt_mesh():
    return skirt(n_around=24, n_rings=6)


def obj_text(v, f, *, quads: bool = False) -> str:
    """OBJ text of a mesh; with quads=True the (tube) triangle pairs [a, c, b], [b, c, d] are
    written as one quad a c d b."""
    lines = [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in v]
    if quads:
        lines += [f"f {a + 1} {c + 1} {d + 1} {b + 1}" for (a, c, b), (_, _, d) in zip(f[0::2], f[1::2])]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    return "\n".join(lines) + "\n"


def write(tmp_path: Path, content, name="garment.obj") -> Path:
    p = tmp_path / name
    if isinstance(content, bytes):
        p.write_bytes(content)
    else:
        p.write_text(content)
    return p


def _codes(report, kind="problem"):
    return {i.code for i in report.items if i.kind == kind}


# ----------------------------------------------------------------------------- a good file
def test_good_obj_imports_with_repairs(tmp_path, body, skirt_mesh):
    v, f = skirt_mesh
    n = len(v)
    # Quads, negative (relative) indices, vt/vn/groups/comments, a continued line, CRLF line
    # endings, three duplicated vertices (one exact, two 5e-8 m off) and one unused vertex.
    lines = ["# a skirt", "mtllib skirt.mtl", "o skirt", "g panel"]
    lines += [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in v]
    lines += ["vt 0.5 0.5", "vn 0 0 1"]
    dup_of = [0, 30, 61]
    for k, d in enumerate(dup_of):
        x, y, z = v[d] + (0.0 if k == 0 else 5e-8)
        lines.append(f"v {x:.9f} {y:.9f} {z:.9f}")  # vertices n + 1 .. n + 3 (1-based)
    lines.append("v 5 5 5")  # unused
    total = n + len(dup_of) + 1
    remap = {d: n + k for k, d in enumerate(dup_of)}
    for (a, c, b), (_, _, d) in zip(f[0::2], f[1::2]):
        idx = [remap.get(i, i) for i in (a, c, d, b)]
        # Negative indices count back from the last vertex read (the file's last one here).
        lines.append("f " + " ".join(f"{i - total}/1/1" for i in idx))
    lines[-1] = lines[-1].replace(" ", " \\\r\n", 1)  # a statement continued on the next line
    path = write(tmp_path, "\r\n".join(lines) + "\r\n")

    report = validate_obj(path, body)
    assert report.passed, report.format()
    out = tmp_path / "lib"
    garment, report = import_garment_obj(path, "my_skirt", body, out_dir=out)
    assert report.passed
    repairs = {i.code: i.count for i in report.repairs}
    assert repairs == {"merged_vertices": 3, "unreferenced_vertices": 1}
    notes = {i.code: i for i in report.notes}
    assert notes["triangulated"].count == len(f) // 2
    assert "fan" in notes["triangulated"].message
    assert garment.num_vertices == n and garment.num_triangles == len(f)
    assert report.stats["openings"] == 2
    # The garment is the skirt, vertex for vertex (float precision of the file: 1e-9 m).
    np.testing.assert_allclose(np.sort(garment.vertices, axis=0), np.sort(v, axis=0), atol=1e-8)
    assert np.all(garment.skin_weights >= 0)
    np.testing.assert_allclose(garment.skin_weights.sum(axis=1), 1.0, atol=1e-12)
    # A loose skirt (90 % of its vertices more than 3 cm from the legs) gets diffused weights.
    assert garment.metadata["skinning"]["method"] == "diffused"
    assert garment.metadata["body"]["hash"] == body.hash
    assert garment.metadata["openings"] == 2
    assert sorted(os.listdir(out / "my_skirt")) == ["my_skirt.json", "my_skirt.npz", "my_skirt.obj"]
    loaded = Garment.load(out / "my_skirt")
    np.testing.assert_allclose(loaded.vertices, garment.vertices, atol=1e-6)
    np.testing.assert_array_equal(loaded.faces, garment.faces)
    np.testing.assert_allclose(loaded.skin_weights, garment.skin_weights, atol=1e-6)
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no staging folder left


def test_orientation_is_repaired_outward(tmp_path, body, skirt_mesh):
    v, f = skirt_mesh
    mixed = f.copy()
    mixed[::3] = mixed[::3, ::-1]  # a third of the triangles flipped: inconsistent
    report = validate_obj(write(tmp_path, obj_text(v, mixed), "mixed.obj"), body)
    assert report.passed and "reoriented" in _codes(report, "repair")
    inward = f[:, ::-1]  # consistent, but every normal faces the body
    garment, report = import_garment_obj(write(tmp_path, obj_text(v, inward), "inward.obj"), "inward", body,
                                         out_dir=tmp_path / "lib", skinning="closest")
    assert "flipped_outward" in _codes(report, "repair")
    assert {tuple(t) for t in garment.faces} == {tuple(t) for t in f}
    assert garment.metadata["skinning"]["method"] == "closest"


def test_existing_name_and_bad_name(tmp_path, body, skirt_mesh):
    path = write(tmp_path, obj_text(*skirt_mesh))
    out = tmp_path / "lib"
    import_garment_obj(path, "a-1", body, out_dir=out, skinning="closest")
    with pytest.raises(InputError, match="already exists"):
        import_garment_obj(path, "a-1", body, out_dir=out)
    g, _ = import_garment_obj(path, "a-1", body, out_dir=out, overwrite=True, skinning="closest")
    assert Garment.load(out / "a-1").num_vertices == g.num_vertices
    for bad in ("", "a b", "../x", "x/y", "é"):
        with pytest.raises(InputError, match="name"):
            import_garment_obj(path, bad, body, out_dir=out)
    pkg = Path(__import__("simgen").__file__).parent
    with pytest.raises(InputError, match="package"):
        import_garment_obj(path, "x", body, out_dir=pkg / "garments_test")
    assert not (pkg / "garments_test").exists()


# ----------------------------------------------------------------------------- broken files
def _grid_obj(n: int) -> str:
    """An n x n quad grid (2 n^2 triangles), written cheaply with numpy."""
    ij = np.stack(np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij"), -1).reshape(-1, 2)
    vs = np.char.add("v ", np.char.add(np.char.add(ij[:, 0].astype(str), " "), ij[:, 1].astype(str)))
    vs = np.char.add(vs, " 0")
    a = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None]).reshape(-1) + 1
    quads = np.stack([a, a + n + 1, a + n + 2, a + 1], 1).astype(str)
    fs = np.char.add("f ", np.char.add(np.char.add(np.char.add(quads[:, 0], " "), np.char.add(quads[:, 1], " ")),
                                        np.char.add(np.char.add(quads[:, 2], " "), quads[:, 3])))
    return "\n".join(vs.tolist() + fs.tolist()) + "\n"


def _broken_cases(v, f):
    """(case id, file content, problem code, a phrase of the refusal sentence)."""
    good = obj_text(v, f)
    lines = good.splitlines()
    n = len(v)
    cases = []
    nan_lines = list(lines)
    nan_lines[5] = "v nan 0.5 0.1"
    cases.append(("nan", "\n".join(nan_lines), "non_finite", "NaN"))
    # A fin: a third triangle on an edge in the middle of the skirt, its tip well outside.
    a, b = f[40][0], f[40][1]
    tip = (v[a] + v[b]) / 2 * np.array([1.3, 1.0, 1.3])
    cases.append(("non_manifold", good + f"v {tip[0]} {tip[1]} {tip[2]}\nf {a + 1} {b + 1} {n + 1}\n",
                  "non_manifold_edges", "more than two triangles"))
    p = np.array([0.5, 1.0, 0.5])
    cases.append(("zero_area", good + "".join(f"v {x} {y} {z}\n" for x, y, z in (p, p + 0.1, p + 0.2))
                  + f"f {n + 1} {n + 2} {n + 3}\n", "degenerate_triangles", "degenerate"))
    inside = list(lines)
    inside[7] = "v 0.09 0.55 0.0"  # in the left leg
    cases.append(("inside", "\n".join(inside), "inside_body", "inside the body"))
    cases.append(("centimetres", obj_text(v * 100, f), "scale", "scale=0.01"))
    cases.append(("millimetres", obj_text(v * 1000, f), "scale", "scale=0.001"))
    cases.append(("inches", obj_text(v / 0.0254, f), "scale", "scale=0.0254"))
    zup = np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)  # (x, y, z) -> (x, -z, y): Y-up to Z-up
    cases.append(("z_up", obj_text(zup, f), "placement", "Z-up"))
    cases.append(("too_many", _grid_obj(317), "too_many_triangles", str(MAX_TRIANGLES)))
    cases.append(("empty", "", "empty", "empty"))
    cases.append(("comments_only", "# nothing here\n\n   \n", "empty", "no statements"))
    cases.append(("binary", bytes(range(256)) * 8, "not_obj", "binary"))
    cases.append(("text", "hello world\nthis is not a mesh\n", "not_obj", "not a Wavefront OBJ"))
    cases.append(("syntax", "v 1 2\nv 0 1 0\nv 0 0 1\nf 1 2 3\n", "syntax", "line 1"))
    cases.append(("index", good + f"f 1 2 {n + 7}\n", "syntax", f"vertex {n + 7}"))
    cases.append(("points", "".join(f"v {x} {y} {z}\n" for x, y, z in v), "no_faces", "no faces"))
    # Two triangles touching at one vertex only (outside the body, beside the skirt).
    bow = np.array([[0.5, 1.0, 0.0], [0.6, 1.1, 0.0], [0.6, 0.9, 0.0], [0.4, 1.1, 0.0], [0.4, 0.9, 0.0]])
    cases.append(("bow_tie", good + "".join(f"v {x} {y} {z}\n" for x, y, z in bow)
                  + f"f {n + 1} {n + 2} {n + 3}\nf {n + 1} {n + 4} {n + 5}\n", "non_manifold_vertices", "bow-tie"))
    # A Moebius band around the chest: manifold, but no consistent side.
    k, m = 48, 3
    t = 2 * np.pi * np.arange(k) / k
    s = np.linspace(-0.05, 0.05, m)
    r = 0.3 + s[None, :] * np.cos(t / 2)[:, None]
    band = np.stack([r * np.cos(t)[:, None], 1.2 + s[None, :] * np.sin(t / 2)[:, None] + 0 * r,
                     r * np.sin(t)[:, None]], axis=-1).reshape(-1, 3)
    tris = []
    for i in range(k):
        for j in range(m - 1):
            a, b = i * m + j, i * m + j + 1
            if i < k - 1:
                c, d = a + m, b + m
            else:  # the half twist: the last strip joins the first one upside down
                c, d = m - 1 - j, m - 2 - j
            tris += [[a, c, b], [b, c, d]]
    cases.append(("moebius", obj_text(band, np.asarray(tris)), "non_orientable", "not orientable"))
    # An L-shaped hexagon written as one polygon: its fan around the first corner folds over.
    ell = np.array([[0.5, 1.0, 0.0], [0.7, 1.0, 0.0], [0.7, 1.1, 0.0], [0.6, 1.1, 0.0], [0.6, 1.3, 0.0],
                    [0.5, 1.3, 0.0]])[[2, 3, 4, 5, 0, 1]]
    cases.append(("non_convex", good + "".join(f"v {x} {y} {z}\n" for x, y, z in ell)
                  + "f " + " ".join(str(n + 1 + i) for i in range(6)) + "\n", "non_convex_polygons", "not convex"))
    cases.append(("duplicate_triangle", good + "f {} {} {}\n".format(*(f[3] + 1)), "duplicate_triangles", "repeat"))
    return cases


_CASE_IDS = ["nan", "non_manifold", "zero_area", "inside", "centimetres", "millimetres", "inches", "z_up", "too_many",
             "empty", "comments_only", "binary", "text", "syntax", "index", "points", "bow_tie", "moebius",
             "non_convex", "duplicate_triangle"]


@pytest.mark.parametrize("case", _CASE_IDS)
def test_broken_obj_is_refused_and_nothing_is_written(tmp_path, body, skirt_mesh, case):
    cases = {c[0]: c[1:] for c in _broken_cases(*skirt_mesh)}
    content, code, phrase = cases[case]
    path = write(tmp_path, content)
    out = tmp_path / "lib"
    with pytest.raises(GarmentImportError) as info:
        import_garment_obj(path, "broken", body, out_dir=out)
    err = info.value
    assert isinstance(err, InputError)
    message = str(err)
    assert str(path) in message and phrase in message, message
    assert code in _codes(err.report), err.report.format()
    assert err.report.problems[0].message in message
    assert not out.exists()
    assert validate_obj(path, body).to_dict()["passed"] is False


def test_missing_file_and_folder_are_refused(tmp_path, body):
    with pytest.raises(InputError, match="does not exist"):
        import_garment_obj(tmp_path / "nope.obj", "x", body, out_dir=tmp_path / "lib")
    with pytest.raises(InputError, match="not a file"):
        import_garment_obj(tmp_path, "x", body, out_dir=tmp_path / "lib")
    with pytest.raises(InputError, match="scale"):
        validate_obj(tmp_path / "nope.obj", body, scale=-1.0)
    assert not (tmp_path / "lib").exists()


def test_scale_parameter_imports_a_centimetre_file(tmp_path, body, skirt_mesh):
    v, f = skirt_mesh
    path = write(tmp_path, obj_text(v * 100, f))
    garment, report = import_garment_obj(path, "cm", body, out_dir=tmp_path / "lib", scale=0.01, skinning="closest")
    np.testing.assert_allclose(np.sort(garment.vertices, axis=0), np.sort(v, axis=0), atol=1e-8)
    assert garment.metadata["made_by"]["scale"] == 0.01


def test_report_lists_every_problem_with_counts(tmp_path, body, skirt_mesh):
    v, f = skirt_mesh
    lines = obj_text(v, f).splitlines()
    lines[7] = "v 0.09 0.55 0.0"
    lines[9] = "v -0.09 0.6 0.0"
    text = "\n".join(lines) + "\nf 1 2 1\n"
    report = validate_obj(write(tmp_path, text), body)
    problems = {i.code: i for i in report.problems}
    assert problems["inside_body"].count == 2 and len(problems["inside_body"].examples) == 2
    assert problems["degenerate_triangles"].count == 1
    assert "line" in problems["degenerate_triangles"].examples[0]
    text = report.format()
    assert "REFUSED" in text and "inside_body" in text and "degenerate_triangles" in text
    assert report.to_dict()["items"][0]["kind"] == "problem"


def test_warnings_do_not_refuse_and_size_hints(tmp_path, body, skirt_mesh):
    v, f = skirt_mesh
    n = len(v)
    # A separate sliver (an angle of 0.3 deg) beside the left leg, one corner 1 mm from its surface.
    sliver = "v 0.156 0.3 0.0\nv 0.25 0.3 0.0\nv 0.25 0.3005 0.0\n" + f"f {n + 1} {n + 2} {n + 3}\n"
    report = validate_obj(write(tmp_path, obj_text(v, f) + sliver), body)
    assert report.passed, report.format()
    assert _codes(report, "warning") == {"thin_triangles", "close_to_body", "several_pieces"}
    assert report.stats["connected_components"] == 2 and report.stats["min_angle_deg"] < 1.0
    # Too big in every known unit (and far off), and too small: the sentence says which.
    big = validate_obj(write(tmp_path, obj_text((v + [0.0, 0.0, 2.0]) * 8, f), "big.obj"), body)
    assert _codes(big) == {"scale"} and "other units than metres" in big.problems[0].message
    small = validate_obj(write(tmp_path, obj_text(v * 1e-3, f), "small.obj"), body)
    assert _codes(small) == {"scale"} and "too small" in small.problems[0].message
    with pytest.raises(InputError, match="BodyModel"):
        validate_obj(write(tmp_path, obj_text(v, f)), "body")


# ----------------------------------------------------------------------------- fuzz
_TOKENS = st.one_of(
    st.sampled_from(["v", "f", "vt", "vn", "g", "o", "s", "#", "usemtl", "l", "\\", "/", "//", "-", "nan", "inf",
                     "1e999", "0", "-1", "1/1/1", "2//2", "-3/1", "x", "f1", "\t", "v1"]),
    st.integers(-5, 12).map(str),
    st.floats(-2, 2).map(repr),
    st.text(alphabet=st.characters(codec="utf-8"), max_size=4),
)
# Well-formed statements too, so that some files get as far as the geometric checks.
_VERTEX = st.tuples(*[st.floats(-0.3, 1.6)] * 3).map(lambda p: "v {} {} {}".format(*p))
_FACE = st.lists(st.integers(-8, 10), min_size=3, max_size=5).map(lambda ix: "f " + " ".join(map(str, ix)))
_LINES = st.lists(st.one_of(_VERTEX, _FACE, st.lists(_TOKENS, max_size=6).map(" ".join)),
                  max_size=16).map("\n".join)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=_LINES)
def test_fuzz_garbled_obj_text_only_raises_input_error(tmp_path, body, text):
    path = tmp_path / "fuzz.obj"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    report = validate_obj(path, body)
    assert isinstance(report.format(), str) and isinstance(report.to_dict(), dict)
    try:
        import_garment_obj(path, "fuzz", body, out_dir=tmp_path / "lib", overwrite=True, skinning="closest")
    except InputError:
        assert not report.passed
    else:
        assert report.passed


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=300))
def test_fuzz_random_bytes_only_raise_input_error(tmp_path, body, data):
    path = tmp_path / "fuzz.obj"
    path.write_bytes(data)
    report = validate_obj(path, body)
    if not report.passed:
        with pytest.raises(InputError):
            import_garment_obj(path, "fuzz", body, out_dir=tmp_path / "lib", overwrite=True)


# ----------------------------------------------------------------------------- library
def test_library_finds_user_garments_and_checks_the_body(tmp_path, monkeypatch, body, skirt_mesh):
    monkeypatch.setenv("SIMGEN_HOME", str(tmp_path / "home"))
    path = write(tmp_path, obj_text(*skirt_mesh))
    garment, _ = import_garment_obj(path, "skirt_u", body, skinning="closest")
    folder = tmp_path / "home" / body.model_id / "garments" / "skirt_u"
    assert folder.is_dir()
    entries = {e["name"]: e for e in list_garments(body.model_id)}
    e = entries["skirt_u"]
    assert e["source"] == "user" and Path(e["path"]) == folder
    assert (e["vertices"], e["triangles"], e["openings"]) == (garment.num_vertices, garment.num_triangles, 2)
    assert e["body_hash"] == body.hash and e["body_id"] == body.model_id and e["skinning"] == "closest"
    assert e["default_material"]
    loaded = load_garment("skirt_u", body=body)
    np.testing.assert_allclose(loaded.vertices, garment.vertices, atol=1e-6)
    with pytest.raises(InputError, match="(?i)available: skirt_u"):
        load_garment("skirt_v", body=body)  # unknown: the message lists what there is


def test_library_refuses_a_garment_made_for_another_body(tmp_path, monkeypatch, skirt_mesh):
    # Two different bodies that share the asset id "open" (the bundled body re-baked, say).
    monkeypatch.setenv("SIMGEN_HOME", str(tmp_path / "home"))
    made_on = dataclasses.replace(two_leg_body(), name="open")
    other = dataclasses.replace(two_leg_body(n_around=20), name="open")
    import_garment_obj(write(tmp_path, obj_text(*skirt_mesh)), "skirt_o", made_on, skinning="closest")
    assert {e["name"]: e["source"] for e in list_garments("open")}["skirt_o"] == "user"
    assert load_garment("skirt_o", body=made_on).name == "skirt_o"
    with pytest.raises(InputError, match="made for body 'open'.*simgen garment"):
        load_garment("skirt_o", body=other)
