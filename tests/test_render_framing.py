"""Renders framed on the body: the camera follows the root (smoothed), the body spans ~80 % of the
height (measured on the rendered pixels), 1280x720 by default, a legend of what is shown; and the
simulation's video shows the body in motion (the start only with --with-start)."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from simgen.errors import InputError
from simgen.io.render import (BODY_FILL, DEFAULT_SIZE, Camera, describe_betas, follow_cameras, render_frame,
                              render_sequence, scene_legend)
from simgen.io.usd import MeshTrack

pytest.importorskip("pyvista")
iio = pytest.importorskip("imageio.v3")

REPO = Path(__file__).resolve().parents[1]


def body_rows(image: np.ndarray) -> tuple[int, int]:
    """First and last image row holding body-coloured pixels (skin: red well above blue; the floor's
    greys and the sky's blues are not)."""
    img = image.astype(int)
    skin = (img[..., 0] - img[..., 2] > 35) & (img[..., 0] > 90)
    rows = np.flatnonzero(skin.sum(axis=1) >= 2)
    assert rows.size, "no body pixels in the image"
    return int(rows[0]), int(rows[-1])


def body_columns(image: np.ndarray) -> float:
    img = image.astype(int)
    skin = (img[..., 0] - img[..., 2] > 35) & (img[..., 0] > 90)
    return float(np.flatnonzero(skin.sum(axis=0)).mean())


@pytest.fixture(scope="module")
def walk():
    """The open body walking: 24 frames from 1.5 s of the library walk (in stride), and the clip."""
    from simgen.body import load
    from simgen.motion import load_motion

    body, clip = load("open"), load_motion("walk")
    out = body.forward_sequence(np.zeros(body.num_betas), clip.poses[45:69], clip.trans[45:69])
    return body, clip, MeshTrack("body", out.vertices.astype(np.float32), body.faces, role="body")


def test_the_body_fills_80_percent_of_a_1280x720_frame_and_the_legend_reads(tmp_path, walk):
    body, clip, track = walk
    legend = scene_legend(garment=None, betas=[1.5, -0.5], motion="walk")
    path = render_frame(tmp_path / "walk.png", [track], frame=12, legend=legend, fps=clip.fps)
    image = iio.imread(path)
    assert image.shape == (DEFAULT_SIZE[1], DEFAULT_SIZE[0], 3) == (720, 1280, 3)
    top, bottom = body_rows(image)
    fill = (bottom - top + 1) / image.shape[0]
    # The tallest frame of the sequence spans BODY_FILL exactly; a walking frame a little less.
    assert 0.72 <= fill <= BODY_FILL + 0.02, fill
    assert top > 0.05 * 720 and bottom < 0.95 * 720  # head and feet inside, with a margin
    assert abs(body_columns(image) - 640) < 0.1 * 1280  # horizontally centred on the body
    # The legend: dark text on a light box in the upper-left corner, absent without a legend.
    plain = iio.imread(render_frame(tmp_path / "plain.png", [track], frame=12, fps=clip.fps))
    corner, plain_corner = image[:100, :400].astype(int), plain[:100, :400].astype(int)
    assert (corner.sum(axis=2) < 150).sum() > 300  # text strokes
    assert (plain_corner.sum(axis=2) < 150).sum() == 0
    assert np.array_equal(image[200:, 500:], plain[200:, 500:])  # same camera: only the corner differs


def test_the_camera_follows_the_root_smoothly_at_one_distance():
    """A box 'body' walking 2 m along +X with a 2 Hz, 3 cm lateral wobble: the focal point follows
    the walk, not the wobble; distance, height and direction stay the same."""
    fps, n = 30.0, 60
    t = np.arange(n) / fps
    box = np.array([[x, y, z] for x in (-0.2, 0.2) for y in (0.0, 1.7) for z in (-0.1, 0.1)])
    faces = np.array([[0, 1, 2], [1, 3, 2], [4, 6, 5], [5, 6, 7]])
    shift = np.stack([2.0 * t / t[-1], 0 * t, 0.03 * np.sin(2 * np.pi * 2.0 * t)], axis=1)
    track = MeshTrack("body", box[None] + shift[:, None], faces, role="body")
    cams = follow_cameras([track], fps=fps)
    assert len(cams) == n
    focal = np.array([c.focal_point for c in cams])
    offsets = np.array([c.position for c in cams]) - focal
    # One distance and direction, one height.
    np.testing.assert_allclose(offsets, np.broadcast_to(offsets[0], offsets.shape), atol=1e-6)
    np.testing.assert_allclose(focal[:, 1], focal[0, 1], atol=1e-6)
    # The look-at point sits a fixed step from the root (along the camera's up, which leans back).
    step = focal - shift
    np.testing.assert_allclose(step[:, 0], step[0, 0], atol=0.01)  # follows the walk, ends included
    middle = slice(15, 45)
    assert np.abs(focal[middle, 2] - focal[middle, 2].mean()).max() < 0.1 * 0.03  # not the wobble
    # Unsmoothed, it would follow the wobble.
    raw = np.array([c.focal_point for c in follow_cameras([track], fps=fps, smoothing=0.0)]) - shift
    np.testing.assert_allclose(raw[:, 2], raw[0, 2], atol=1e-6)


def test_the_tallest_frame_spans_exactly_the_fill():
    """Projected through its camera, the highest and lowest points of a standing box span BODY_FILL
    of the image height, centred."""
    box = np.array([[x, y, z] for x in (-0.2, 0.2) for y in (0.0, 1.7) for z in (-0.1, 0.1)], float)
    track = MeshTrack("body", box, np.array([[0, 1, 2]]), role="body")
    cam = follow_cameras([track])[0]
    pos, focal, up = (np.array(v) for v in (cam.position, cam.focal_point, cam.view_up))
    back = (pos - focal) / np.linalg.norm(pos - focal)
    rel = box - pos
    depth = -(rel @ back)
    tan = (rel @ up) / depth  # vertical image coordinate, as a tangent
    half = np.tan(np.radians(cam.view_angle) / 2)
    assert (tan.max() - tan.min()) / (2 * half) == pytest.approx(BODY_FILL, abs=1e-6)
    assert tan.max() + tan.min() == pytest.approx(0.0, abs=1e-6)


def test_sequence_png_and_video_share_the_framing(tmp_path, walk):
    """render_frame of frame k is frame k of render_sequence (the same follow camera, the same
    legend), and videos are 1280x720 by default."""
    import imageio.v2 as iio2

    body, clip, track = walk
    short = MeshTrack("body", track.points[:3], track.faces, role="body")
    legend = scene_legend(motion="walk")
    mp4 = render_sequence(tmp_path / "s.mp4", [short], fps=clip.fps, legend=legend)
    png = iio.imread(render_frame(tmp_path / "s.png", [short], frame=1, legend=legend, fps=clip.fps))
    with iio2.get_reader(mp4, format="FFMPEG") as reader:
        frames = [np.asarray(f) for f in reader]
    assert len(frames) == 3 and frames[1].shape == (720, 1280, 3)
    assert np.abs(frames[1].astype(int) - png.astype(int)).mean() < 3.0  # equal up to H.264


def test_render_sequence_checks_cameras_and_labels(tmp_path, walk):
    _, _, track = walk
    cam = Camera((0.0, 1.0, 4.0), (0.0, 1.0, 0.0))
    with pytest.raises(InputError, match="one per frame"):
        render_sequence(tmp_path / "a.mp4", [track], fps=30, camera=[cam, cam])
    with pytest.raises(InputError, match="frame_labels"):
        render_sequence(tmp_path / "a.mp4", [track], fps=30, frame_labels=["x"])
    with pytest.raises(InputError, match="frame counts"):
        follow_cameras([track, MeshTrack("g", track.points[:2], track.faces, role="garment")])
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("betas, text", [
    (None, "mean shape (betas 0)"),
    ([0.0, 0.0], "mean shape (betas 0)"),
    ([1.5, -0.5, 0.0], "betas 1.5, -0.5"),
    ([-0.001, 2.0], "betas 0, 2"),
    ([0, 0, 0, 0, 0, 0, 0.25], "betas b6 0.25"),
    (list(range(1, 11)), "betas b0 1, b1 2, b2 3, b3 4 +6"),
])
def test_describe_betas(betas, text):
    assert describe_betas(betas) == text


def test_scene_legend_order():
    assert list(scene_legend(garment="tshirt", betas=[1.0], motion="walk", sequence="x")) == \
        ["garment", "shape", "motion", "sequence"]


def test_every_render_caller_takes_the_one_framing():
    """Nothing in the package frames a camera itself: simgen.io.render.follow_cameras is the
    framing of every render (default_camera is for the docs' composed pictures in scripts/)."""
    offenders = []
    for path in (REPO / "simgen").rglob("*.py"):
        if path.name == "render.py" and path.parent.name == "io":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module == "simgen.io.render":
                names = {a.name for a in node.names}
                if names & {"default_camera", "Camera", "sequence_bounds"}:
                    offenders.append(f"{path.relative_to(REPO)}: {sorted(names)}")
    assert not offenders, offenders
    from simgen.dataset.export import export_sequence
    from simgen.garment.preview import preview_garment, render_skin_weights

    for fn in (preview_garment, render_skin_weights, export_sequence, render_frame, render_sequence):
        assert inspect.signature(fn).parameters["size"].default == (1280, 720), fn.__name__


# --------------------------------------------------------------------------- the simulation's video
def fake_result(body, clip, *, frames: int, relax=2, ramp=3, rest=2, betas=(1.0,)):
    """A SimulationResult-like object: the body posed over the clip's first frames (as the solver
    records it), the 'cloth' a copy of the body, the protocol's frame counts and betas in
    the metadata as the JobRecorder writes them."""
    b = body.check_betas(np.asarray(betas))[0]
    posed = body.forward_sequence(b, clip.poses[:frames], clip.trans[:frames]).vertices.astype(np.float32)
    P = relax + ramp + rest
    phases = np.array(["relax"] * relax + ["ramp"] * ramp + ["rest"] * rest)
    return SimpleNamespace(
        positions=posed, faces=body.faces, fps=30.0, num_frames=frames,
        protocol_positions=np.repeat(posed[:1], P, axis=0), protocol_phases=phases,
        body_vertices=posed, body_faces=body.faces,
        metadata={"betas": [float(x) for x in b],
                  "config": {"relax_frames": relax, "ramp_frames": ramp, "rest_frames": rest}})


def test_the_video_starts_in_motion_and_with_start_shows_the_protocol(walk):
    from simgen._sim_video import LEAD_IN_S, lead_in_frames, protocol_body_vertices, simulation_pictures
    from simgen.motion import procedural

    body, clip, _ = walk
    assert LEAD_IN_S == procedural._ARMS_DOWN_TIME  # the library clips' arms-down lead-in
    result = fake_result(body, clip, frames=61)
    lead = lead_in_frames(clip, 61, 30.0)
    assert lead == 27

    plain = simulation_pictures(result, body, clip, garment="tshirt")
    assert [t.num_frames for t in plain.tracks] == [61 - lead] * 2
    assert plain.labels[0].startswith("27 / 60") and plain.labels[-1].startswith("60 / 60")
    assert plain.labels[plain.still].startswith(f"{27 + (61 - 27) // 2} / 60")  # the middle of the motion shown
    np.testing.assert_array_equal(plain.tracks[0].points[0], result.body_vertices[lead])
    assert plain.legend == {"garment": "tshirt", "shape": "betas 1", "motion": "walk"}

    full = simulation_pictures(result, body, clip, garment="tshirt", with_start=True)
    assert [t.num_frames for t in full.tracks] == [7 + 61] * 2
    assert full.labels[:7] == ["start: relax 1/2", "start: relax 2/2", "start: ramp 1/3", "start: ramp 2/3",
                               "start: ramp 3/3", "start: rest 1/2", "start: rest 2/2"]
    assert full.labels[7].startswith("0 / 60")
    assert full.labels[full.still] == plain.labels[plain.still]  # the same still either way

    # The protocol's body, re-posed from the solver's schedule: the template body in rest pose at
    # the clip's first translation (relax), then the target shape in the clip's first pose (rest),
    # which is where the recorded clip starts.
    start = protocol_body_vertices(result, body, clip)
    assert start.shape == (7, body.num_vertices, 3)
    np.testing.assert_allclose(start[0], body.forward(pose=np.zeros((24, 3)), trans=clip.trans[0]).vertices[0],
                               atol=1e-5)
    np.testing.assert_allclose(start[-1], result.body_vertices[0], atol=1e-4)


def test_short_or_mocap_clips_keep_every_frame(walk):
    from simgen._sim_video import lead_in_frames
    from simgen.motion import load_motion

    _, clip, _ = walk
    assert lead_in_frames(clip, 4, 30.0) == 0  # 0.1 s of a walk: nothing would be left
    assert lead_in_frames(load_motion("cmu_131_02_walk"), 61, 30.0) == 0  # mocap starts in motion


def test_describe_betas_takes_one_shape_vector():
    with pytest.raises(InputError, match="one shape vector"):
        describe_betas(np.zeros((3, 10)))  # per-frame betas: the caller picks the frame
