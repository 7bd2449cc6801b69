"""USD export: validity under pxr.UsdValidation, stage metadata, exact round trips, bad input."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from simgen.errors import InputError
from simgen.io import usd as usd_module
from simgen.io.usd import MeshTrack, read_usd_info, read_usd_meshes, validate_usd, write_usd

pxr = pytest.importorskip("pxr")

FPS = 30.0
T = 10


def sphere_sequence(n_frames: int = T, fps: float = FPS) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere (r = 0.2 m) resting on the floor, moving along +X and pulsing in size."""
    ico = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    verts, faces = np.asarray(ico.vertices), np.asarray(ico.faces)
    t = np.arange(n_frames) / fps
    scale = 1.0 + 0.25 * np.sin(2 * np.pi * t)  # one pulse per second
    offset = np.stack([0.8 * t, 0.2 * scale, np.zeros_like(t)], axis=1)  # the bottom stays at y = 0
    points = verts[None] * scale[:, None, None] + offset[:, None, :]
    return points, faces


@pytest.fixture
def scene() -> list[MeshTrack]:
    points, faces = sphere_sequence()
    colors = (points[0] - points[0].min(0)) / np.ptp(points[0], axis=0)  # per-vertex, static
    return [
        MeshTrack("body", points, faces, colors=colors, role="body"),
        MeshTrack("shirt", points * [1.05, 1.0, 1.05], faces, role="garment"),
        MeshTrack("ground", points[0], faces, role="other"),  # static
    ]


@pytest.mark.parametrize("suffix", [".usdc", ".usda"])
def test_written_file_is_valid_and_round_trips(tmp_path, scene, suffix):
    path = write_usd(tmp_path / f"seq{suffix}", scene, fps=FPS, metadata={"motion": "walk"})
    assert path.is_file()
    assert validate_usd(path) == []
    assert validate_usd(path, strict=True) == []  # no warnings either

    back = read_usd_meshes(path)
    assert list(back) == ["body", "shirt", "ground"]
    for track in scene:
        got = back[track.name]
        assert got.points.dtype == np.float32
        assert got.points.shape == track.points.shape
        np.testing.assert_array_equal(got.points, track.points.astype(np.float32))
        np.testing.assert_array_equal(got.faces, track.faces)
        assert got.role == track.role
    np.testing.assert_array_equal(back["body"].colors, scene[0].colors.astype(np.float32))
    assert back["shirt"].colors is None  # constant role colour is not per-vertex data


def test_encoding_follows_the_file_name(tmp_path, scene):
    assert (write_usd(tmp_path / "a.usda", scene, fps=FPS).read_bytes()[:5]) == b"#usda"
    assert (write_usd(tmp_path / "a.usdc", scene, fps=FPS).read_bytes()[:8]) == b"PXR-USDC"
    assert (write_usd(tmp_path / "a.usd", scene, fps=FPS).read_bytes()[:8]) == b"PXR-USDC"
    text = write_usd(tmp_path / "b.usd", scene, fps=FPS, format="usda")
    assert text.read_bytes()[:5] == b"#usda"
    assert validate_usd(text) == []


@pytest.mark.parametrize(("fps", "start"), [(30.0, 0), (24.0, 5), (59.94, -3)])
def test_stage_metadata(tmp_path, scene, fps, start):
    path = write_usd(
        tmp_path / "seq.usdc",
        scene,
        fps=fps,
        start_frame=start,
        root_name="sequence",
        metadata={"body": "open", "motion": "walk", "betas": np.arange(3) * 0.5, "frames": np.int64(T),
                  "solver": {"substeps": 10, "tags": ["a", "b"]}},
    )
    info = read_usd_info(path)
    assert info["up_axis"] == "Y"
    assert info["meters_per_unit"] == 1.0
    assert info["time_codes_per_second"] == pytest.approx(fps)
    assert info["frames_per_second"] == pytest.approx(fps)
    assert info["start_time_code"] == start
    assert info["end_time_code"] == start + T - 1
    assert info["default_prim"] == "sequence"
    meta = info["metadata"]
    assert meta["body"] == "open" and meta["motion"] == "walk" and meta["frames"] == T
    assert meta["betas"] == [0.0, 0.5, 1.0]
    assert meta["solver"] == {"substeps": 10, "tags": ["a", "b"]}
    assert meta["simgen_version"]

    stage = pxr.Usd.Stage.Open(str(path))
    root = stage.GetDefaultPrim()
    assert root.IsA(pxr.UsdGeom.Xform)
    assert pxr.Usd.ModelAPI(root).GetKind() == pxr.Kind.Tokens.component
    # read_usd_meshes samples the time codes start..end of the stage.
    assert read_usd_meshes(path)["body"].points.shape == (T, scene[0].num_vertices, 3)


def test_mesh_attributes_and_per_frame_extent(tmp_path, scene):
    path = write_usd(tmp_path / "seq.usdc", scene, fps=FPS, start_frame=1)
    stage = pxr.Usd.Stage.Open(str(path))
    UsdGeom = pxr.UsdGeom
    body = UsdGeom.Mesh(stage.GetPrimAtPath("/simgen/body"))
    shirt = UsdGeom.Mesh(stage.GetPrimAtPath("/simgen/shirt"))
    ground = UsdGeom.Mesh(stage.GetPrimAtPath("/simgen/ground"))

    assert body.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    assert body.GetOrientationAttr().Get() == UsdGeom.Tokens.rightHanded
    assert body.GetDoubleSidedAttr().Get() is False
    assert shirt.GetDoubleSidedAttr().Get() is True
    assert body.GetPointsAttr().GetTypeName() == pxr.Sdf.ValueTypeNames.Point3fArray
    # Topology once, geometry once per frame.
    assert body.GetFaceVertexIndicesAttr().GetNumTimeSamples() == 0
    assert body.GetFaceVertexCountsAttr().GetNumTimeSamples() == 0
    assert body.GetPointsAttr().GetTimeSamples() == list(range(1, T + 1))
    assert body.GetExtentAttr().GetTimeSamples() == list(range(1, T + 1))
    assert ground.GetPointsAttr().GetNumTimeSamples() == 0

    points = scene[0].points
    for i in range(T):
        extent = np.asarray(body.GetExtentAttr().Get(1 + i))
        bounds = np.stack([points[i].min(0), points[i].max(0)]).astype(np.float32)
        np.testing.assert_array_equal(extent, bounds)
        # The stored extent is what USD itself computes from the stored points.
        computed = UsdGeom.Boundable.ComputeExtentFromPlugins(body, pxr.Usd.TimeCode(1 + i))
        np.testing.assert_allclose(np.asarray(computed), extent, atol=1e-6)
    assert np.asarray(body.GetExtentAttr().Get(1))[1, 0] < np.asarray(body.GetExtentAttr().Get(T))[1, 0]

    color = body.GetDisplayColorPrimvar()
    assert color.GetInterpolation() == UsdGeom.Tokens.vertex
    assert shirt.GetDisplayColorPrimvar().GetInterpolation() == UsdGeom.Tokens.constant


def test_time_varying_colors_round_trip(tmp_path):
    points, faces = sphere_sequence()
    rng = np.random.default_rng(0)
    colors = rng.random((T, points.shape[1], 3))
    path = write_usd(tmp_path / "c.usda", [MeshTrack("body", points, faces, colors=colors)], fps=FPS)
    assert validate_usd(path) == []
    np.testing.assert_array_equal(read_usd_meshes(path)["body"].colors, colors.astype(np.float32))


def test_static_only_stage(tmp_path):
    points, faces = sphere_sequence(1)
    path = write_usd(tmp_path / "s.usdc", [MeshTrack("body", points[0], faces)], fps=FPS)
    assert validate_usd(path) == []
    info = read_usd_info(path)
    assert info["start_time_code"] == info["end_time_code"] == 0
    back = read_usd_meshes(path)["body"]
    assert back.static and back.points.shape == points[0].shape


def test_rewrite_is_read_fresh(tmp_path, scene):
    path = tmp_path / "seq.usdc"
    write_usd(path, scene, fps=FPS)
    first = read_usd_meshes(path)
    moved = [MeshTrack(t.name, t.points + 1.0, t.faces, colors=t.colors, role=t.role) for t in scene]
    write_usd(path, moved, fps=FPS)
    again = read_usd_meshes(path)
    np.testing.assert_array_equal(again["body"].points, first["body"].points + np.float32(1.0))


def test_failed_write_leaves_old_file_and_no_debris(tmp_path, scene, monkeypatch):
    path = write_usd(tmp_path / "seq.usdc", scene, fps=FPS)
    before = path.read_bytes()

    def crash(src, dst):
        raise OSError("disk full")

    moved = [MeshTrack(t.name, t.points + 1.0, t.faces, role=t.role) for t in scene]
    with monkeypatch.context() as patch, pytest.raises(OSError):
        patch.setattr(usd_module.os, "replace", crash)  # dies between writing and renaming
        write_usd(path, moved, fps=FPS)
    assert os.listdir(tmp_path) == ["seq.usdc"]
    assert path.read_bytes() == before


def test_validator_reports_problems(tmp_path):
    """validate_usd is not vacuous: a stage without upAxis, metersPerUnit and defaultPrim fails."""
    path = tmp_path / "bare.usda"
    stage = pxr.Usd.Stage.CreateNew(str(path))
    pxr.UsdGeom.Mesh.Define(stage, "/m")
    stage.Save()
    messages = validate_usd(path)
    assert any("upAxis" in m for m in messages)
    assert any("metersPerUnit" in m for m in messages)
    assert any("defaultPrim" in m for m in messages)


def test_read_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        read_usd_meshes(tmp_path / "missing.usdc")
    junk = tmp_path / "junk.usdc"
    junk.write_bytes(b"\x00not a usd file" * 10)
    with pytest.raises(InputError, match="junk.usdc"):
        validate_usd(junk)


def _points_faces():
    return sphere_sequence()


BAD_TRACKS = {
    "nan points": (lambda p, f: MeshTrack("body", np.where(np.arange(p.size).reshape(p.shape) == 7, np.nan, p),
                                          f),
                   r"'body'.*points.*not finite at frame 0, vertex 2"),
    "overflowing points": (lambda p, f: MeshTrack("body", p * 1e300, f), r"'body'.*points"),
    "points shape": (lambda p, f: MeshTrack("body", p[..., :2], f), r"'body'.*points.*shape"),
    "faces out of range": (lambda p, f: MeshTrack("body", p, f + 1), r"'body'.*faces.*162 vertices"),
    "negative faces": (lambda p, f: MeshTrack("body", p, f - 1), r"'body'.*faces"),
    "float faces": (lambda p, f: MeshTrack("body", p, f.astype(float)), r"'body'.*faces.*integer"),
    "quad faces": (lambda p, f: MeshTrack("body", p, np.hstack([f, f[:, :1]])), r"'body'.*faces.*shape"),
    "colors shape": (lambda p, f: MeshTrack("body", p, f, colors=np.zeros((5, 3))), r"'body'.*colors.*shape"),
    "colors range": (lambda p, f: MeshTrack("body", p, f, colors=np.full((p.shape[1], 3), 2.0)),
                     r"'body'.*colors.*\[0, 1\]"),
    "bad name": (lambda p, f: MeshTrack("2 bodies", p, f), r"'2 bodies'.*name"),
    "bad role": (lambda p, f: MeshTrack("body", p, f, role="hat"), r"'body'.*role"),
}


@pytest.mark.parametrize("case", sorted(BAD_TRACKS))
def test_bad_tracks_are_rejected(case):
    make, message = BAD_TRACKS[case]
    points, faces = _points_faces()
    with pytest.raises(InputError, match=message):
        make(points, faces)


def test_bad_write_arguments_write_nothing(tmp_path, scene):
    points, faces = _points_faces()
    short = MeshTrack("cape", points[:5], faces, role="garment")
    cases = [
        (dict(tracks=scene, fps=0), "fps"),
        (dict(tracks=scene, fps=-30), "fps"),
        (dict(tracks=scene, fps=float("nan")), "fps"),
        (dict(tracks=scene, fps="30"), "fps"),
        (dict(tracks=[], fps=FPS), "no mesh tracks"),
        (dict(tracks=[*scene, short], fps=FPS), r"different frame counts.*cape: 5"),
        (dict(tracks=[scene[0], scene[0]], fps=FPS), "'body' is used twice"),
        (dict(tracks=scene, fps=FPS, start_frame=0.5), "start_frame"),
        (dict(tracks=scene, fps=FPS, root_name="my root"), "root_name"),
        (dict(tracks=scene, fps=FPS, metadata={"note": None}), r"metadata\['note'\]"),
        (dict(tracks=scene, fps=FPS, metadata={"mixed": [1, "a"]}), r"metadata\['mixed'\]"),
        (dict(tracks=scene, fps=FPS, metadata={"x": float("inf")}), r"metadata\['x'\]"),
        (dict(tracks=scene, fps=FPS, format="usdz"), "format"),
    ]
    for kwargs, message in cases:
        with pytest.raises(InputError, match=message):
            write_usd(tmp_path / "out" / "seq.usdc", **kwargs)
    with pytest.raises(InputError, match=r"\.usdc, \.usda or \.usd"):
        write_usd(tmp_path / "seq.obj", scene, fps=FPS)
    with pytest.raises(InputError, match="contradicts"):
        write_usd(tmp_path / "seq.usdc", scene, fps=FPS, format="usda")
    assert not any(tmp_path.rglob("*.*"))


def test_reads_foreign_files_without_time_range(tmp_path):
    """A file from another tool: no time code range, so the points' own samples are used."""
    Usd, UsdGeom, Vt = pxr.Usd, pxr.UsdGeom, pxr.Vt
    points, faces = sphere_sequence(3)
    path = tmp_path / "foreign.usda"
    stage = Usd.Stage.CreateNew(str(path))
    mesh = UsdGeom.Mesh.Define(stage, "/thing")
    mesh.CreateFaceVertexCountsAttr([3] * len(faces))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1).astype(np.int32)))
    for i in range(3):
        mesh.CreatePointsAttr().Set(Vt.Vec3fArray.FromNumpy(points[i].astype(np.float32)), 10 + i)
    quad = UsdGeom.Mesh.Define(stage, "/quad")
    quad.CreateFaceVertexCountsAttr([4])
    quad.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    quad.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    stage.Save()
    with pytest.raises(InputError, match="not a triangle mesh"):
        read_usd_meshes(path)
    stage.RemovePrim("/quad")
    stage.Save()
    back = read_usd_meshes(path)["thing"]
    assert back.role == "other"
    np.testing.assert_array_equal(back.points, points.astype(np.float32))
