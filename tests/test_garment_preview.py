"""LBS preview: a USD that validates with zero errors, holding the body's forward pass and the garment
skinned by it (shape offsets applied), an MP4 with one frame per clip frame, and a PNG."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from garment_bodies import brute_force_closest, skirt, two_leg_body
from simgen.errors import InputError
from simgen.garment import Garment, compute_skin_weights, lbs, preview_garment, shape_offsets
from simgen.io.usd import read_usd_info, read_usd_meshes, validate_usd
from simgen.motion import MotionClip

pytest.importorskip("pyvista")
iio = pytest.importorskip("imageio.v3")


@pytest.fixture(scope="module")
def scene():
    body = two_leg_body()
    # An odd number of vertices around: none lies on the mirror plane x = 0, where the closest leg
    # (and so the shape offset) is a tie that two closest-point searches may break differently.
    v, f = skirt(n_around=25, n_rings=6)
    w = compute_skin_weights(v, body, method="diffused", faces=f, num_samples=16)
    garment = Garment("skirt-1", v, f, w, metadata={"body": {"id": body.model_id, "hash": body.hash},
                                                    "skinning": {"method": "diffused"}})
    T = 5
    poses = np.zeros((T, 24, 3))
    s = np.sin(np.linspace(0, np.pi, T))
    poses[:, 1, 0], poses[:, 2, 0] = 0.5 * s, -0.5 * s  # hips swing
    poses[:, 0, 1] = 0.3 * s  # and the body turns
    trans = np.stack([np.zeros(T), np.zeros(T), 0.1 * np.arange(T)], axis=1)
    return body, garment, MotionClip("swing", 10.0, poses, trans)


def test_preview_writes_valid_usd_video_and_picture(tmp_path, scene):
    body, garment, clip = scene
    betas = np.array([1.0, 2.0])
    done = []
    out = preview_garment(garment, body, clip, out_dir=tmp_path, betas=betas, size=(96, 72),
                          progress=lambda i, n: done.append((i, n)), shape_method="closest")
    assert set(out) == {"usd", "png", "video"}
    assert out["usd"].name == "skirt-1_swing.usdc"
    assert validate_usd(out["usd"]) == []
    info = read_usd_info(out["usd"])
    assert info["time_codes_per_second"] == 10.0 and info["metadata"]["garment"] == "skirt-1"

    meshes = read_usd_meshes(out["usd"])
    body_track = meshes["body"]
    garment_track = next(t for t in meshes.values() if t.role == "garment")
    ref = body.forward(betas, clip.poses, clip.trans)
    np.testing.assert_allclose(body_track.points, ref.vertices, atol=1e-5)
    # The garment: rest vertices moved by the shape blendshape at their closest body points (found
    # here by an exhaustive search), then skinned with the shaped body's transforms.
    _, _, tri, bary = brute_force_closest(body.v_template, body.faces, garment.vertices)
    offsets = np.einsum("pc,pcdb,b->pd", bary, body.shapedirs[body.faces[tri]], betas)
    expected = lbs(garment.vertices + offsets, garment.skin_weights, ref.transforms)
    np.testing.assert_allclose(garment_track.points, expected, atol=1e-5)
    np.testing.assert_array_equal(garment_track.faces, garment.faces)

    image = iio.imread(out["png"])
    assert image.shape == (72, 96, 3) and image.std() > 10
    import imageio.v2 as iio2

    with iio2.get_reader(out["video"], format="FFMPEG") as reader:
        frames = [np.asarray(f) for f in reader]
    assert len(frames) == clip.num_frames
    assert done[-1] == (clip.num_frames, clip.num_frames)
    assert np.abs(frames[0].astype(int) - frames[-1].astype(int)).mean() > 1.0  # it moves


def test_preview_at_template_shape_is_the_lbs_baseline(tmp_path, scene):
    body, garment, clip = scene
    out = preview_garment(garment, body, clip, out_dir=tmp_path, video=False, frames=[0, 2, 4], size=(64, 48))
    assert "video" not in out
    assert read_usd_info(out["usd"])["time_codes_per_second"] == clip.fps / 2  # every 2nd frame: real speed
    garment_track = next(t for t in read_usd_meshes(out["usd"]).values() if t.role == "garment")
    A = body.forward(pose=clip.poses[[0, 2, 4]], trans=clip.trans[[0, 2, 4]]).transforms
    np.testing.assert_allclose(garment_track.points, lbs(garment.vertices, garment.skin_weights, A), atol=1e-5)


def test_preview_shape_offsets_are_diffused_by_default(tmp_path, scene):
    body, garment, clip = scene
    betas = np.array([0.0, 2.0])
    out = preview_garment(garment, body, clip, out_dir=tmp_path, betas=betas, video=False, frames=1, size=(64, 48))
    garment_track = next(t for t in read_usd_meshes(out["usd"]).values() if t.role == "garment")
    A = body.forward(betas, clip.poses[:1], clip.trans[:1]).transforms
    rest = garment.vertices + shape_offsets(garment.vertices, body, betas, method="diffused")[0]
    np.testing.assert_allclose(garment_track.points, lbs(rest, garment.skin_weights, A), atol=1e-5)
    assert read_usd_info(out["usd"])["metadata"]["shape_offsets"] == "diffused"


def test_preview_refuses_bad_input(tmp_path, scene):
    body, garment, clip = scene
    other = dataclasses.replace(body, v_template=body.v_template * 1.01)
    with pytest.raises(InputError, match="made for body"):
        preview_garment(garment, other, clip, out_dir=tmp_path, video=False)
    with pytest.raises(InputError, match="frames"):
        preview_garment(garment, body, clip, out_dir=tmp_path, frames=99)
    with pytest.raises(InputError, match="betas"):
        preview_garment(garment, body, clip, out_dir=tmp_path, betas=np.ones(5))
    with pytest.raises(InputError, match="size"):
        preview_garment(garment, body, clip, out_dir=tmp_path, size=(8, 8))
    assert list(tmp_path.iterdir()) == []
