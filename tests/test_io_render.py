"""Offscreen rendering: PNG and MP4 of the requested size that show the meshes, a fixed camera."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from simgen.errors import InputError
from simgen.io.render import Camera, default_camera, render_frame, render_sequence, sequence_bounds
from simgen.io.usd import ROLE_COLORS, MeshTrack

pytest.importorskip("pyvista")
iio = pytest.importorskip("imageio.v3")

FPS = 30.0


def figure(n_frames: int, *, speed: float = 0.6) -> list[MeshTrack]:
    """A 1.7 m 'body' (a stretched icosphere standing on the floor) walking along +X with a
    'garment' tube around its middle."""
    ico = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    body = np.asarray(ico.vertices) * [0.25, 0.85, 0.18] + [0.0, 0.85, 0.0]
    tube = trimesh.creation.cylinder(radius=1.0, height=1.0, sections=32)
    tube.update_faces(np.abs(tube.face_normals[:, 2]) < 0.5)  # drop the caps: an open sleeve
    tube.remove_unreferenced_vertices()
    cloth = np.asarray(tube.vertices)[:, [0, 2, 1]] * [0.27, 0.4, 0.2] + [0.0, 1.05, 0.0]
    shift = np.zeros((n_frames, 1, 3))
    shift[:, 0, 0] = speed * np.arange(n_frames) / FPS
    return [
        MeshTrack("body", body[None] + shift, ico.faces, role="body"),
        MeshTrack("shirt", cloth[None] + shift, tube.faces, role="garment"),
    ]


def hue_is(pixel: np.ndarray, rgb: tuple[float, float, float]) -> bool:
    """True when the pixel's channel order matches the colour's (shading scales all channels)."""
    return list(np.argsort(pixel.astype(float))) == list(np.argsort(rgb))


def test_frame_png_shows_the_meshes(tmp_path):
    tracks = figure(1)
    path = render_frame(tmp_path / "f.png", tracks, size=(320, 240), title="frame 0")
    image = iio.imread(path)
    assert image.shape == (240, 320, 3) and image.dtype == np.uint8
    assert image.std() > 20  # not blank

    # The camera looks at the middle of the figure: the garment covers the image centre; the
    # body shows above it (upper torso) in skin colour, the floor and sky fill the corners.
    assert hue_is(image[120, 160], ROLE_COLORS["garment"])
    column = image[40:110, 160]
    assert sum(hue_is(p, ROLE_COLORS["body"]) and p[0] > 120 for p in column) > 20
    top, bottom = image[2, 2].astype(int), image[-3, 2].astype(int)
    assert top[2] > top[0]  # sky: bluish
    assert abs(bottom[0] - bottom[2]) < 30 and bottom.mean() > 120  # floor: light grey

    # Without meshes' colours the same place looks different: the figure is really drawn.
    plain = iio.imread(render_frame(tmp_path / "g.png", [tracks[1]], size=(320, 240), floor=False))
    assert np.abs(plain.astype(int) - image.astype(int)).mean() > 5


def test_frame_png_tuples_and_colors(tmp_path):
    tracks = figure(1)
    pts, faces = tracks[0].points[0], tracks[0].faces
    vertex_colors = np.tile([0.2, 0.9, 0.4], (len(pts), 1))  # green per vertex
    path = render_frame(tmp_path / "t.png", [(pts, faces, vertex_colors)], size=(161, 121), floor=False)
    image = iio.imread(path)
    assert image.shape == (121, 161, 3)  # PNG keeps odd sizes
    assert hue_is(image[60, 80], (0.2, 0.9, 0.4))
    red = iio.imread(render_frame(tmp_path / "r.png", [(pts, faces, (0.9, 0.3, 0.1))], size=(160, 120)))
    assert hue_is(red[60, 80], (0.9, 0.3, 0.1))
    # A lone MeshTrack is accepted as a one-mesh scene.
    assert iio.imread(render_frame(tmp_path / "one.png", tracks[0], size=(64, 48))).shape == (48, 64, 3)


def test_sequence_mp4_decodes_and_moves(tmp_path):
    n = 6
    tracks = figure(n, speed=3.0)
    calls = []
    path = render_sequence(tmp_path / "s.mp4", tracks, fps=FPS, size=(161, 120),
                           progress=lambda done, total: calls.append((done, total)))
    assert calls == [(i + 1, n) for i in range(n)]
    import imageio.v2 as iio2

    with iio2.get_reader(path, format="FFMPEG") as reader:
        meta = reader.get_meta_data()
        frames = [np.asarray(f) for f in reader]
    assert len(frames) == n
    assert all(f.shape == (120, 162, 3) for f in frames)  # odd width rounded up to even
    assert meta["fps"] == pytest.approx(FPS)
    assert "h264" in meta["codec"]
    diffs = [np.abs(a.astype(int) - b.astype(int)).mean() for a, b in zip(frames, frames[1:])]
    assert min(diffs) > 0.5  # the figure moves 10 cm per frame

    # The camera is fixed: sky pixels (top rows) do not change while the figure walks below.
    sky = [f[:8].astype(int) for f in frames]
    assert max(np.abs(a - sky[0]).max() for a in sky) <= 8  # codec noise only


def test_static_sequence_gives_identical_frames(tmp_path):
    body = figure(1)[0]
    still = MeshTrack("body", np.repeat(body.points, 4, axis=0), body.faces)
    import imageio.v2 as iio2

    path = render_sequence(tmp_path / "still.mp4", [still], fps=24, size=(96, 64))
    frames = [np.asarray(f).astype(int) for f in iio2.get_reader(path, format="FFMPEG")]
    assert len(frames) == 4
    assert max(np.abs(f - frames[0]).mean() for f in frames) < 1.0


def test_default_camera_frames_the_box():
    box = np.array([[-0.4, 0.0, -0.2], [2.5, 1.8, 0.3]])
    aspect = 4 / 3
    cam = default_camera(box, aspect=aspect)
    assert isinstance(cam, Camera)
    pos, focal = np.array(cam.position), np.array(cam.focal_point)
    np.testing.assert_allclose(focal, box.mean(0))
    view = focal - pos
    assert view[2] < 0 and view[1] < 0 and view[0] < 0  # from the front (+Z), above, from +X side
    # Every corner lies inside the frustum, and the tightest one nearly touches its border.
    forward = view / np.linalg.norm(view)
    up = np.array(cam.view_up)
    right = np.cross(forward, up)
    tan_v = math.tan(math.radians(cam.view_angle / 2))
    extremes = []
    for corner in np.array(np.meshgrid(*box.T)).reshape(3, -1).T:
        rel = corner - pos
        depth = rel @ forward
        assert depth > 0
        extremes.append(max(abs(rel @ right) / (depth * tan_v * aspect), abs(rel @ up) / (depth * tan_v)))
    assert 0.85 < max(extremes) <= 1.0
    # pyvista-style bounds give the same camera.
    same = default_camera(box.T.reshape(-1), aspect=aspect)
    np.testing.assert_allclose(same.position, cam.position)


def test_sequence_bounds_is_the_union_over_frames():
    tracks = figure(5, speed=3.0)
    bounds = sequence_bounds(tracks)
    all_points = np.concatenate([t.points.reshape(-1, 3) for t in tracks])
    np.testing.assert_allclose(bounds, [all_points.min(0), all_points.max(0)], rtol=0, atol=1e-6)


def test_bad_render_input_writes_nothing(tmp_path):
    tracks = figure(3)
    one = figure(1)
    cases = [
        (lambda: render_frame(tmp_path / "a.jpg", one), r"\.png"),
        (lambda: render_frame(tmp_path / "a.png", []), "non-empty"),
        (lambda: render_frame(tmp_path / "a.png", one, size=(8, 8)), "size"),
        (lambda: render_frame(tmp_path / "a.png", one, size=(100.5, 80)), "size"),
        (lambda: render_frame(tmp_path / "a.png", [(one[0].points[0], one[0].faces, "hat")]), "role"),
        (lambda: render_frame(tmp_path / "a.png", [(one[0].points[0], one[0].faces, (2, 0, 0))]), "RGB"),
        (lambda: render_frame(tmp_path / "a.png", [(one[0].points, one[0].faces)]), "points"),
        (lambda: render_frame(tmp_path / "a.png", (one[0].points[0], one[0].faces)), "wrap"),
        (lambda: render_frame(tmp_path / "a.png", tracks, frame=3), "frame 3"),
        (lambda: render_frame(tmp_path / "a.png", one, camera=(0, 0, 1)), "camera"),
        (lambda: render_sequence(tmp_path / "a.avi", tracks, fps=FPS), r"\.mp4"),
        (lambda: render_sequence(tmp_path / "a.mp4", tracks, fps=0), "fps"),
        (lambda: render_sequence(tmp_path / "a.mp4", [tracks[0], figure(2)[1]], fps=FPS), "frame counts"),
        (lambda: render_sequence(tmp_path / "a.mp4", [(1, 2)], fps=FPS), "MeshTrack"),
        (lambda: default_camera([[0, 0, 0], [1, np.nan, 1]]), "bounds"),
    ]
    for call, message in cases:
        with pytest.raises(InputError, match=message):
            call()
    assert not any(tmp_path.iterdir())


def test_modules_import_without_usd_or_vtk():
    """The GPU machine has neither usd-core nor pyvista: importing simgen.io must not need them."""
    import subprocess
    import sys

    code = (
        "import sys, simgen.io.usd, simgen.io.render\n"
        "heavy = {'pxr', 'pyvista', 'vtk', 'vtkmodules', 'imageio', 'imageio_ffmpeg'}\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def skin_tight(offset: float) -> list[MeshTrack]:
    """A body ellipsoid and a 'garment' on the same ellipsoid, tessellated differently (the sphere
    turned by 7 degrees before scaling) and moved ``offset`` [m] out along its normals: cloth
    resting on the skin as the solver leaves it (0.2 mm outside)."""
    ico = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    scale, centre = np.array([0.25, 0.85, 0.18]), np.array([0.0, 0.85, 0.0])
    body = np.asarray(ico.vertices) * scale + centre
    c, s = np.cos(np.radians(7.0)), np.sin(np.radians(7.0))
    turned = np.asarray(ico.vertices) @ np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    cloth = trimesh.Trimesh(turned * scale + centre, ico.faces)
    cloth = cloth.vertices + offset * cloth.vertex_normals
    return [MeshTrack("body", body[None], ico.faces, role="body"),
            MeshTrack("shirt", cloth[None], ico.faces, role="garment")]


def test_cloth_on_the_skin_is_drawn_without_the_body_showing_through(tmp_path, monkeypatch):
    """Cloth that the solver leaves within a fraction of a millimetre of the skin, on either side
    (0.2 mm outside after projection; its triangles sag up to ~0.2 mm in), is drawn over the body:
    garments are drawn GARMENT_DISPLAY_OFFSET out along their normals. The test switches it off to
    show it matters."""
    import simgen.io.render as render

    def body_share(path):
        image = iio.imread(path)[40:190, 145:175]  # inside the figure's silhouette
        return np.mean([hue_is(p, ROLE_COLORS["body"]) and p[0] > 100 for p in image.reshape(-1, 3)])

    tracks = skin_tight(-2.0e-4)
    assert body_share(render_frame(tmp_path / "a.png", tracks, size=(320, 240))) < 0.01
    monkeypatch.setattr(render, "GARMENT_DISPLAY_OFFSET", 0.0)
    assert body_share(render_frame(tmp_path / "b.png", tracks, size=(320, 240))) > 0.05
