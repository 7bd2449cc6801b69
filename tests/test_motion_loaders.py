"""Tests of the motion loaders (simgen npz, AMASS, BVH) and the motion library.

Known answers come from outside the code under test: AMASS files are written in the Z-up convention
from a known Y-up clip (and the posed Z-up body rotated by hand must equal the loaded one); BVH files
are written from SMPL skeletons with scipy's Euler angles, so the loader must recover known poses
and bone directions; the real CMU clips (../shared/mocap/cmu) must come out upright, on the floor
and moving as described. Fuzzing (hypothesis) checks that broken files only ever raise InputError.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from test_motion_ops import random_clip, stick_body  # tests/ is on sys.path under pytest

from simgen.body.model import SMPL_JOINT_NAMES, SMPL_PARENTS, BodyModel
from simgen.assets import body_asset_id
from simgen.errors import InputError
from simgen.motion import (
    BvhMappingWarning,
    MotionClip,
    import_motion,
    library_split,
    list_motions,
    load_amass,
    load_bvh,
    load_motion,
    load_motion_file,
    save_motion,
)
from simgen.motion.amass import Z_UP_TO_Y_UP
from simgen.motion.bvh import parse_bvh
from simgen.motion.ops import foot_vertex_indices, lowest_foot_heights, posed_joints
from simgen.rotations import axis_angle_to_matrix

N = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
CMU_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "mocap" / "cmu"
FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return stick_body()


def _same_rotations(a, b, atol=1e-7) -> bool:
    return np.allclose(axis_angle_to_matrix(a), axis_angle_to_matrix(b), atol=atol)


def _angle_deg(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    c = np.sum(u * v, -1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


# ================================================================================ simgen .npz
def test_simgen_npz_round_trip(tmp_path):
    clip = random_clip(seed=20, frames=9, fps=25.0)
    clip.meta["description"] = "round trip"
    path = save_motion(clip, tmp_path / "clip.npz")
    data = np.load(path)
    assert data["poses"].shape == (9, 72) and data["poses"].dtype == np.float32
    assert str(data["up_axis"]) == "Y" and str(data["gender"]) == "neutral" and data["betas"].shape == (10,)
    back = load_motion_file(path)
    assert back.name == "random" and back.fps == 25.0 and back.meta["description"] == "round trip"
    np.testing.assert_allclose(back.poses, clip.poses, atol=1e-6)
    np.testing.assert_allclose(back.trans, clip.trans, atol=1e-12)
    assert [p.name for p in tmp_path.iterdir()] == ["clip.npz"]  # no temporary file left behind


# ================================================================================ AMASS
def _amass_arrays(clip: MotionClip, J0: np.ndarray, layout: str, rng) -> dict:
    """The Z-up AMASS arrays of a Y-up clip (hands: index1 = SMPL hand joints, other fingers random)."""
    R = Z_UP_TO_Y_UP
    root = Rotation.from_matrix(R.T @ axis_angle_to_matrix(clip.poses[:, 0])).as_rotvec()
    trans = (clip.trans + J0) @ R - J0  # R^T (trans + J0) - J0
    T = clip.num_frames
    body = clip.poses[:, 1:22].reshape(T, 63)
    lhand = rng.normal(scale=0.3, size=(T, 15, 3))
    rhand = rng.normal(scale=0.3, size=(T, 15, 3))
    lhand[:, 0], rhand[:, 0] = clip.poses[:, 22], clip.poses[:, 23]
    hands = np.concatenate([lhand.reshape(T, 45), rhand.reshape(T, 45)], axis=1)
    if layout == "smplh":
        return {"poses": np.concatenate([root, body, hands], axis=1), "trans": trans,
                "mocap_framerate": np.array(clip.fps), "gender": np.array("female"), "betas": np.zeros(16)}
    face = rng.normal(scale=0.2, size=(T, 9))
    if layout == "smplx":
        return {"poses": np.concatenate([root, body, face, hands], axis=1), "trans": trans,
                "mocap_frame_rate": np.array(clip.fps), "gender": np.array("neutral"),
                "surface_model_type": np.array("smplx")}
    return {"root_orient": root, "pose_body": body, "pose_hand": hands, "pose_jaw": face[:, :3], "trans": trans,
            "mocap_frame_rate": np.array(clip.fps)}


@pytest.mark.parametrize("layout", ["smplh", "smplx", "smplx_split"])
def test_amass_z_up_file_gives_the_y_up_clip(body, tmp_path, layout):
    rng = np.random.default_rng(21)
    clip = random_clip(seed=22, frames=10, fps=60.0, scale=0.4)
    J0 = body.rest_joints()[0, 0]
    arrays = _amass_arrays(clip, J0, layout, rng)
    path = tmp_path / f"{layout}.npz"
    np.savez(path, **arrays)
    loaded = load_amass(path, body=body, on_floor=False)
    assert loaded.fps == 60.0 and loaded.name == layout and loaded.num_frames == 10
    assert _same_rotations(loaded.poses, clip.poses, atol=1e-9)
    np.testing.assert_allclose(loaded.trans, clip.trans, atol=1e-12)
    # independent of the trans rule: the posed Z-up body, turned Y-up by hand, is the loaded body
    zposes = clip.poses.copy()
    zposes[:, 0] = Rotation.from_matrix(Z_UP_TO_Y_UP.T @ axis_angle_to_matrix(clip.poses[:, 0])).as_rotvec()
    zclip = MotionClip("z", 60.0, zposes, arrays["trans"])
    zverts = body.forward(pose=zclip.poses, trans=zclip.trans).vertices
    verts = body.forward(pose=loaded.poses, trans=loaded.trans).vertices
    np.testing.assert_allclose(verts, zverts @ Z_UP_TO_Y_UP.T, atol=1e-9)
    # on the floor: the same motion shifted along y, lowest foot point of the first 0.5 s at 0
    floored = load_motion_file(path, body=body)
    fverts = body.forward(pose=floored.poses, trans=floored.trans).vertices
    shift = fverts - verts
    np.testing.assert_allclose(shift[..., [0, 2]], 0.0, atol=1e-9)
    assert np.ptp(shift[..., 1]) < 1e-9 or floored.meta["history"][-1].get("lifted_frames", 0) > 0
    assert fverts[:30, foot_vertex_indices(body), 1].min() == pytest.approx(0.0, abs=1e-9)


def _valid_amass(tmp_path: Path, body: BodyModel, **changes) -> Path:
    arrays = _amass_arrays(random_clip(seed=23, frames=6, scale=0.3), body.rest_joints()[0, 0], "smplh",
                           np.random.default_rng(0))
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize("changes", [
    {"trans": None}, {"poses": None}, {"mocap_framerate": None},
    {"mocap_framerate": np.array(0.0)}, {"mocap_framerate": np.array(-120.0)},
    {"mocap_framerate": np.array([30.0, 60.0])},
    {"mocap_framerate": np.array("fast")},
    {"poses": np.zeros((6, 100))}, {"poses": np.zeros(156)}, {"trans": np.zeros((5, 3))}, {"trans": np.zeros((6, 2))},
    {"poses": np.full((6, 156), np.nan)}, {"poses": np.array(["a"] * 6)},
])
def test_amass_bad_fields_raise_input_error(body, tmp_path, changes):
    path = _valid_amass(tmp_path, body, **changes)
    with pytest.raises(InputError, match="bad.npz"):
        load_amass(path, body=body)


def test_amass_unreadable_files_raise_input_error(body, tmp_path):
    (tmp_path / "text.npz").write_text("not a zip")
    np.save(tmp_path / "array.npz.npy", np.zeros(3))
    (tmp_path / "array.npz.npy").rename(tmp_path / "array.npz")
    np.savez(tmp_path / "pickled.npz", poses=np.array([{"a": 1}], dtype=object))
    for name in ("text.npz", "array.npz", "pickled.npz", "missing.npz"):
        with pytest.raises(InputError, match=name):
            load_amass(tmp_path / name, body=body)
        with pytest.raises(InputError):
            load_motion_file(tmp_path / name, body=body)


@FUZZ
@given(data=st.data())
def test_fuzzed_npz_only_raises_input_error(body, tmp_path_factory, data):
    good = _valid_amass(tmp_path_factory.mktemp("npz"), body).read_bytes()
    blob = bytearray(good[: data.draw(st.integers(0, len(good)), label="cut")])
    for _ in range(data.draw(st.integers(0, 4), label="flips")):
        if blob:
            i = data.draw(st.integers(0, len(blob) - 1))
            blob[i] = data.draw(st.integers(0, 255))
    path = tmp_path_factory.mktemp("fuzz") / "f.npz"
    path.write_bytes(bytes(blob))
    try:
        clip = load_motion_file(path, body=body)
    except InputError:
        return
    assert isinstance(clip, MotionClip)


# ================================================================================ BVH writing
SMPL_STYLE = ["Pelvis", "L_Hip", "R_Hip", "Spine1", "L_Knee", "R_Knee", "Spine2", "L_Ankle", "R_Ankle", "Spine3",
              "L_Foot", "R_Foot", "Neck", "L_Collar", "R_Collar", "Head", "L_Shoulder", "R_Shoulder", "L_Elbow",
              "R_Elbow", "L_Wrist", "R_Wrist", "L_Hand", "R_Hand"]
MIXAMO = ["mixamorig:" + n for n in (
    "Hips", "LeftUpLeg", "RightUpLeg", "Spine", "LeftLeg", "RightLeg", "Spine1", "LeftFoot", "RightFoot", "Spine2",
    "LeftToeBase", "RightToeBase", "Neck", "LeftShoulder", "RightShoulder", "Head", "LeftArm", "RightArm",
    "LeftForeArm", "RightForeArm", "LeftHand", "RightHand", "LeftHandMiddle1", "RightHandMiddle1")]
LEAF_ENDS = {10: (0.0, 0.0, 0.07), 11: (0.0, 0.0, 0.07), 15: (0.0, 0.15, 0.0), 22: (0.09, 0.0, 0.0),
             23: (-0.09, 0.0, 0.0)}


def write_bvh(path, names, parents, offsets, ends, local_rots, root_pos, orders, fps=30.0, unit=1.0) -> Path:
    """Write a BVH: offsets (J, 3) [m], ends {joint: offset (3,)}, local_rots (F, J, 3, 3) world-from-
    local rotations relative to the rest pose, root_pos (F, 3) [m], orders: per joint 'ZYX'-style
    channel order (intrinsic, BVH's convention; angles from scipy). unit: file units per metre."""
    J, F = len(names), local_rots.shape[0]
    lines, dfs = ["HIERARCHY"], []

    def emit(j: int, depth: int) -> None:
        pad = "\t" * depth
        dfs.append(j)
        lines.append(f"{pad}{'ROOT' if parents[j] < 0 else 'JOINT'} {names[j]}")
        lines.append(pad + "{")
        lines.append(f"{pad}\tOFFSET " + " ".join(f"{x * unit:.10f}" for x in offsets[j]))
        chans = ["Xposition", "Yposition", "Zposition"] if parents[j] < 0 else []
        chans += [f"{a}rotation" for a in orders[j]]
        lines.append(f"{pad}\tCHANNELS {len(chans)} " + " ".join(chans))
        for c in range(J):
            if parents[c] == j:
                emit(c, depth + 1)
        if j in ends:
            lines.extend([f"{pad}\tEnd Site", pad + "\t{",
                          f"{pad}\t\tOFFSET " + " ".join(f"{x * unit:.10f}" for x in ends[j]), pad + "\t}"])
        lines.append(pad + "}")

    emit(0, 0)
    lines += ["MOTION", f"Frames: {F}", f"Frame Time: {1.0 / fps:.10f}"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy's gimbal-lock note: the angles still give the rotation
        eul = {j: Rotation.from_matrix(local_rots[:, j]).as_euler(orders[j], degrees=True) for j in range(J)}
    for f in range(F):
        vals = list(root_pos[f] * unit)
        for j in dfs:
            vals += list(eul[j][f])
        lines.append(" ".join(f"{v:.10f}" for v in vals))
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)


def _world_to_local(G: np.ndarray, parents) -> np.ndarray:
    """World rotations (F, J, 3, 3) -> local rotations relative to the parent."""
    L = G.copy()
    for j in range(1, G.shape[1]):
        L[:, j] = np.swapaxes(G[:, parents[j]], -1, -2) @ G[:, j]
    return L


def _smpl_world(body: BodyModel, poses: np.ndarray) -> np.ndarray:
    """World rotations of SMPL's joints for poses (F, 24, 3)."""
    R = axis_angle_to_matrix(poses)
    G = R.copy()
    for j in range(1, 24):
        G[:, j] = G[:, SMPL_PARENTS[j]] @ R[:, j]
    return G


def _smpl_bvh(body, tmp_path, names, pose0, poses, trans, orders=None, fps=30.0, unit=1.0, up=np.eye(3),
              name="clip.bvh") -> Path:
    """A BVH with SMPL's topology whose rest pose is the body posed by pose0 (24, 3) and whose frames
    reproduce poses (F, 24, 3) / trans (F, 3); up: rotation from simgen's Y-up world to the file's."""
    J = body.rest_joints()[0]
    G0 = _smpl_world(body, pose0[None])[0]
    offsets = np.zeros((24, 3))
    offsets[0] = J[0]
    for j in range(1, 24):
        offsets[j] = G0[SMPL_PARENTS[j]] @ (J[j] - J[SMPL_PARENTS[j]])
    ends = {j: G0[j] @ np.array(e) for j, e in LEAF_ENDS.items()}
    G1 = _smpl_world(body, poses)
    Q = up @ (G1 @ np.swapaxes(G0, -1, -2)[None]) @ up.T  # world rotations relative to the BVH rest pose
    root = (J[0] + trans) @ up.T
    orders = orders or ["ZYX"] * 24
    return write_bvh(tmp_path / name, names, SMPL_PARENTS, offsets @ up.T, {j: up @ e for j, e in ends.items()},
                     _world_to_local(Q, SMPL_PARENTS), root, orders, fps=fps, unit=unit)


# ================================================================================ BVH: known answers
def test_bvh_tpose_elbow_bend_is_a_90_degree_elbow_rotation(body, tmp_path):
    axis = np.array([0.0, 0.6, 0.8])
    poses = np.zeros((2, 24, 3))
    poses[1, N["left_elbow"]] = 0.5 * np.pi * axis
    path = _smpl_bvh(body, tmp_path, MIXAMO, np.zeros((24, 3)), poses, np.zeros((2, 3)))
    clip = load_bvh(path, body=body, on_floor=False)
    assert clip.fps == 30.0 and clip.num_frames == 2
    np.testing.assert_allclose(clip.poses[1, N["left_elbow"]], 0.5 * np.pi * axis, atol=1e-7)
    others = np.delete(clip.poses, N["left_elbow"], axis=1)
    np.testing.assert_allclose(others, 0.0, atol=1e-7)
    np.testing.assert_allclose(clip.poses[0], 0.0, atol=1e-7)
    np.testing.assert_allclose(clip.trans, 0.0, atol=1e-7)
    assert clip.meta["bvh_mapping"]["left_hand"] == "mixamorig:LeftHandMiddle1"
    assert clip.meta["bvh_mapping"]["left_collar"] == "mixamorig:LeftShoulder"


@pytest.mark.parametrize("unit, up", [(1.0, "Y"), (100.0, "Y"), (1.0 / 0.0254, "Z")])
def test_bvh_of_an_smpl_motion_round_trips(body, tmp_path, unit, up):
    rng = np.random.default_rng(24)
    clip = random_clip(seed=25, frames=5, scale=0.5)
    orders = ["".join(rng.permutation(list("XYZ"))) for _ in range(24)]  # channels in any order
    to_file = Z_UP_TO_Y_UP.T if up == "Z" else np.eye(3)
    path = _smpl_bvh(body, tmp_path, SMPL_STYLE, np.zeros((24, 3)), clip.poses, clip.trans, orders=orders,
                     unit=unit, up=to_file)
    out = load_bvh(path, body=body, on_floor=False)
    assert _same_rotations(out.poses, clip.poses, atol=1e-7)
    np.testing.assert_allclose(out.trans, clip.trans, atol=1e-7)
    assert out.meta["bvh_scale"] == pytest.approx(1.0 / unit)


def test_bvh_non_t_rest_pose_is_accounted_for(body, tmp_path):
    # Rest pose: arms down 45 deg, elbows bent, legs apart, a bit of everything else.
    pose0 = random_clip(seed=26, frames=1, scale=0.15).poses[0]
    pose0[N["left_shoulder"]] += [0.0, 0.0, -0.8]
    pose0[N["right_shoulder"]] += [0.0, 0.0, 0.8]
    pose0[N["left_elbow"]] += [0.0, -0.4, 0.0]
    pose0[N["left_hip"]] += [0.0, 0.0, 0.3]
    # zero motion channels: SMPL's bones must point like the BVH's rest bones
    still = _smpl_bvh(body, tmp_path, MIXAMO, pose0, pose0[None], np.zeros((1, 3)), name="still.bvh")
    out = load_bvh(still, body=body, on_floor=False)
    skel = parse_bvh(still)
    rest_bvh = skel.rest_positions()[[skel.names.index(n) for n in MIXAMO]]  # in SMPL order
    got = posed_joints(out, body)[0]
    bones = [(int(SMPL_PARENTS[j]), j) for j in range(1, 24)]
    err = [_angle_deg(got[c] - got[p], rest_bvh[c] - rest_bvh[p]) for p, c in bones]
    assert max(err) < 1e-5
    # a motion: the SMPL body reproduces the posed joints (directions and, same skeleton, positions)
    clip = random_clip(seed=27, frames=4, scale=0.5)
    moving = _smpl_bvh(body, tmp_path, MIXAMO, pose0, clip.poses, clip.trans, name="moving.bvh")
    out = load_bvh(moving, body=body, on_floor=False)
    np.testing.assert_allclose(posed_joints(out, body), posed_joints(clip, body), atol=1e-7)


CMU_NAMES = {  # name: (parent, SMPL joint whose rest position it takes)
    "Hips": (None, "pelvis"), "lowerback": ("Hips", "pelvis"), "Chest": ("lowerback", "spine2"),
    "Chest2": ("Chest", "spine3"), "lowerneck": ("Chest2", "spine3"), "Neck": ("lowerneck", "neck"),
    "Head": ("Neck", "head"),
}
for _s, _S in (("L", "Left"), ("R", "Right")):
    _side = "left" if _s == "L" else "right"
    CMU_NAMES.update({
        f"{_s}HipJoint": ("Hips", "pelvis"), f"{_S}Hip": (f"{_s}HipJoint", f"{_side}_hip"),
        f"{_S}Knee": (f"{_S}Hip", f"{_side}_knee"), f"{_S}Ankle": (f"{_S}Knee", f"{_side}_ankle"),
        f"{_S}Toe": (f"{_S}Ankle", f"{_side}_foot"), f"{_S}Collar": ("Chest2", "spine3"),
        f"{_S}Shoulder": (f"{_S}Collar", f"{_side}_shoulder"), f"{_S}Elbow": (f"{_S}Shoulder", f"{_side}_elbow"),
        f"{_S}Wrist": (f"{_S}Elbow", f"{_side}_wrist"), f"{_s.lower()}hand": (f"{_S}Wrist", f"{_side}_wrist"),
        f"{_s}Fingers": (f"{_s.lower()}hand", f"{_side}_hand"), f"{_s}Thumb": (f"{_S}Wrist", f"{_side}_wrist"),
    })
# (SMPL bone) <-> (BVH bone) pairs that the retargeting reproduces exactly
CMU_BONES = [("spine1", "spine2", "lowerback", "Chest"), ("spine2", "spine3", "Chest", "Chest2"),
             ("neck", "head", "Neck", "Head")]
for _s, _S in (("L", "Left"), ("R", "Right")):
    _side = "left" if _s == "L" else "right"
    CMU_BONES += [(f"{_side}_hip", f"{_side}_knee", f"{_S}Hip", f"{_S}Knee"),
                  (f"{_side}_knee", f"{_side}_ankle", f"{_S}Knee", f"{_S}Ankle"),
                  (f"{_side}_ankle", f"{_side}_foot", f"{_S}Ankle", f"{_S}Toe"),
                  (f"{_side}_shoulder", f"{_side}_elbow", f"{_S}Shoulder", f"{_S}Elbow"),
                  (f"{_side}_elbow", f"{_side}_wrist", f"{_S}Elbow", f"{_S}Wrist"),
                  (f"{_side}_wrist", f"{_side}_hand", f"{_S}Wrist", f"{_s}Fingers")]
CMU_MAPPING = {"pelvis": "Hips", "spine1": "lowerback", "spine2": "Chest", "spine3": "Chest2", "neck": "Neck",
               "head": "Head"}
for _s, _S in (("L", "Left"), ("R", "Right")):
    _side = "left" if _s == "L" else "right"
    CMU_MAPPING.update({f"{_side}_{p}": f"{_S}{q}" for p, q in (("hip", "Hip"), ("knee", "Knee"), ("ankle", "Ankle"),
                        ("foot", "Toe"), ("collar", "Collar"), ("shoulder", "Shoulder"), ("elbow", "Elbow"),
                        ("wrist", "Wrist"))})
    CMU_MAPPING[f"{_side}_hand"] = f"{_s}Fingers"


def _bone_errors(clip: MotionClip, body: BodyModel, bvh_path: Path) -> dict[str, np.ndarray]:
    """Angle [deg] per frame between each SMPL bone of CMU_BONES and its BVH bone."""
    skel = parse_bvh(bvh_path)
    _, P = skel.forward()
    idx = {n: i for i, n in enumerate(skel.names)}
    step = skel.fps / clip.fps
    frames = np.minimum(np.rint(np.arange(clip.num_frames) * step).astype(int), skel.num_frames - 1)
    Jt = posed_joints(clip, body)
    return {f"{a}->{b}": _angle_deg(Jt[:, N[b]] - Jt[:, N[a]], P[frames, idx[d]] - P[frames, idx[c]])
            for a, b, c, d in CMU_BONES}


def _smpl_world_rotations(clip: MotionClip) -> np.ndarray:
    """World rotation of every SMPL joint per frame, (T, 24, 3, 3), composed from the local poses."""
    local = Rotation.from_rotvec(clip.poses.reshape(-1, 3)).as_matrix().reshape(clip.num_frames, 24, 3, 3)
    G = np.empty_like(local)
    for j in range(24):
        p = int(SMPL_PARENTS[j])
        G[:, j] = local[:, j] if p < 0 else G[:, p] @ local[:, j]
    return G


def _collar_errors(clip: MotionClip, bvh_path: Path) -> dict[str, np.ndarray]:
    """Angle [deg] per frame between each SMPL collar's world rotation and its BVH clavicle's rotation
    from rest (the collars are retargeted rest-relative, not by bone direction)."""
    skel = parse_bvh(bvh_path)
    Q, _ = skel.forward()
    idx = {n: i for i, n in enumerate(skel.names)}
    step = skel.fps / clip.fps
    frames = np.minimum(np.rint(np.arange(clip.num_frames) * step).astype(int), skel.num_frames - 1)
    G = _smpl_world_rotations(clip)
    out = {}
    for side, bvh in (("left", "LeftCollar"), ("right", "RightCollar")):
        rel = np.swapaxes(G[:, N[f"{side}_collar"]], -1, -2) @ Q[frames, idx[bvh]]
        out[side] = np.degrees(np.linalg.norm(Rotation.from_matrix(rel).as_rotvec(), axis=-1))
    return out


def test_bvh_intermediate_joints_are_folded_into_the_mapped_ones(body, tmp_path):
    names = list(CMU_NAMES)
    parents = [-1 if CMU_NAMES[n][0] is None else names.index(CMU_NAMES[n][0]) for n in names]
    J = body.rest_joints()[0]
    pos = np.array([J[N[CMU_NAMES[n][1]]] for n in names])
    offsets = np.array([pos[i] - (pos[p] if p >= 0 else 0.0) for i, p in enumerate(parents)])
    ends = {names.index(n): e for n, e in (("LeftToe", (0, 0, 0.07)), ("RightToe", (0, 0, 0.07)),
                                           ("Head", (0, 0.15, 0)), ("LFingers", (0.05, 0, 0)),
                                           ("RFingers", (-0.05, 0, 0)), ("LThumb", (0.03, 0, 0.03)),
                                           ("RThumb", (-0.03, 0, 0.03)))}
    rng = np.random.default_rng(28)
    F = 4
    local = Rotation.from_rotvec(rng.normal(scale=0.35, size=(F * len(names), 3))).as_matrix().reshape(F, -1, 3, 3)
    root = J[0] + rng.normal(scale=0.2, size=(F, 3))
    path = write_bvh(tmp_path / "cmu_like.bvh", names, parents, offsets, ends, local, root,
                     ["ZYX"] * len(names), fps=120.0)
    with pytest.warns(BvhMappingWarning) as record:
        clip = load_bvh(path, body=body, on_floor=False, fps=120.0)
    message = str(record[0].message)
    assert all(n in message for n in ("LHipJoint", "RHipJoint", "lowerneck", "lhand", "rhand", "LThumb", "RThumb"))
    assert clip.meta["bvh_mapping"] == CMU_MAPPING
    for bone, err in _bone_errors(clip, body, path).items():
        assert err.max() < 1e-5, bone
    for side, err in _collar_errors(clip, path).items():
        assert err.max() < 1e-5, side


# ================================================================================ BVH: bad input
def test_bvh_with_no_mappable_joint_is_rejected(body, tmp_path):
    names = ["Foo", "Bar", "Baz"]
    path = write_bvh(tmp_path / "nomap.bvh", names, [-1, 0, 1], np.array([[0, 1, 0], [0, 0.3, 0], [0, 0.3, 0]]),
                     {2: np.array([0, 0.1, 0])}, np.broadcast_to(np.eye(3), (2, 3, 3, 3)), np.zeros((2, 3)),
                     ["ZYX"] * 3)
    with pytest.raises(InputError, match="nomap.bvh.*no joint name"):
        load_bvh(path, body=body)


def _valid_bvh_text(body, tmp_path) -> str:
    clip = random_clip(seed=29, frames=3, scale=0.3)
    return _smpl_bvh(body, tmp_path, SMPL_STYLE, np.zeros((24, 3)), clip.poses, clip.trans).read_text()


@pytest.mark.parametrize("edit", [
    lambda t: t.replace("Frame Time: 0.0333333333", "Frame Time: 0"),
    lambda t: t.replace("Frame Time: 0.0333333333", "Frame Time: -0.01"),
    lambda t: t.replace("Frames: 3", "Frames: 4"),
    lambda t: t.replace("Frames: 3", "Frames: three"),
    lambda t: t.rsplit("\n", 2)[0],
    lambda t: t.split("MOTION")[0],
    lambda t: t.replace("HIERARCHY", "HIERARCH"),
    lambda t: t.replace("OFFSET", "OFSET", 3),
    lambda t: t.replace("Zrotation", "Qrotation", 1),
    lambda t: t.replace("}", "", 1),
    lambda t: t.replace("CHANNELS 6", "CHANNELS 9"),
    lambda t: t.replace("0.", "nan", 1),
])
def test_bvh_bad_files_raise_input_error(body, tmp_path, edit):
    path = tmp_path / "bad.bvh"
    path.write_text(edit(_valid_bvh_text(body, tmp_path)))
    with pytest.raises(InputError, match="bad.bvh"):
        load_bvh(path, body=body)


@pytest.mark.parametrize("fps", [0.0, -30.0, float("nan")])
def test_bvh_non_positive_fps_argument_is_rejected(body, tmp_path, fps):
    path = tmp_path / "ok.bvh"
    path.write_text(_valid_bvh_text(body, tmp_path))
    with pytest.raises(InputError, match="fps"):
        load_bvh(path, body=body, fps=fps)


@FUZZ
@given(data=st.data())
def test_fuzzed_bvh_only_raises_input_error(body, tmp_path_factory, data):
    text = _valid_bvh_text(body, tmp_path_factory.mktemp("bvh")).encode()
    blob = bytearray(text[: data.draw(st.integers(0, len(text)), label="cut")])
    for _ in range(data.draw(st.integers(0, 4), label="edits")):
        if blob:
            i = data.draw(st.integers(0, len(blob) - 1))
            blob[i] = data.draw(st.sampled_from(list(b"{}0123456789.-eE \n\tXYZJOINTEnd") + [0, 200, 255]))
    path = tmp_path_factory.mktemp("fuzz") / "f.bvh"
    path.write_bytes(bytes(blob))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BvhMappingWarning)
        try:
            clip = load_motion_file(path, body=body)
        except InputError:
            return
    assert isinstance(clip, MotionClip)


# ================================================================================ BVH: real CMU clips
def _cmu_body() -> BodyModel:
    """The bundled body when it is baked, else the synthetic one."""
    try:
        from simgen.body import load

        return load("open")
    except InputError:
        return stick_body()


@pytest.fixture(scope="module")
def cmu_clips():
    if not (CMU_DIR / "131_01.bvh").is_file():
        pytest.skip(f"CMU clips not found under {CMU_DIR}")
    body = _cmu_body()
    clips = {}
    for name in ("131_01", "131_02", "131_03"):
        with pytest.warns(BvhMappingWarning):
            clips[name] = load_bvh(CMU_DIR / f"{name}.bvh", body=body)
    return body, clips


@pytest.mark.parametrize("name", ["131_01", "131_02", "131_03"])
def test_cmu_clip_is_upright_on_the_floor_and_follows_the_bvh(cmu_clips, name):
    body, clips = cmu_clips
    clip = clips[name]
    assert clip.fps == 30.0 and clip.meta["source_fps"] == 120.0
    assert clip.meta["bvh_mapping"] == CMU_MAPPING
    J = posed_joints(clip, body)
    ankles = np.maximum(J[:, N["left_ankle"], 1], J[:, N["right_ankle"], 1])
    assert np.all(J[:, N["head"], 1] > J[:, N["pelvis"], 1]) and np.all(J[:, N["pelvis"], 1] > ankles)
    low = lowest_foot_heights(clip, body)
    assert low[:15].min() == pytest.approx(0.0, abs=1e-9)
    assert low.min() >= -0.03
    assert abs(np.median(low)) < 0.03
    for bone, err in _bone_errors(clip, body, CMU_DIR / f"{name}.bvh").items():
        assert err.mean() < 0.01 and err.max() < 0.1, bone
    # Subject 131's clavicle channels barely move (about 6 degrees from rest): no shrug on the body.
    for side, err in _collar_errors(clip, CMU_DIR / f"{name}.bvh").items():
        assert err.max() < 0.5, side
    collar_angles = np.degrees(np.linalg.norm(clip.poses[:, [N["left_collar"], N["right_collar"]]], axis=-1))
    assert collar_angles.max() < 10.0


def _peak_speed(clip: MotionClip, J: np.ndarray, window_s: float = 1.0) -> float:
    w = int(round(window_s * clip.fps))
    d = np.linalg.norm(J[w:, 0, [0, 2]] - J[:-w, 0, [0, 2]], axis=-1)
    return float(d.max() / window_s)


@pytest.mark.parametrize("name", ["131_01", "131_02"])
def test_cmu_walks_advance_with_alternating_feet(cmu_clips, name):
    body, clips = cmu_clips
    clip = clips[name]
    J = posed_joints(clip, body)
    path = J[-1, 0, [0, 2]] - J[0, 0, [0, 2]]
    assert np.linalg.norm(path) > 1.0
    assert 0.3 < _peak_speed(clip, J) < 2.0
    # the foot in front (along the direction of travel) changes again and again
    lead = (J[:, N["left_ankle"], [0, 2]] - J[:, N["right_ankle"], [0, 2]]) @ (path / np.linalg.norm(path))
    lead = lead[np.abs(lead) > 0.05]
    assert np.sum(np.diff(np.sign(lead)) != 0) >= 4


def test_cmu_hop_lifts_the_body(cmu_clips):
    body, clips = cmu_clips
    clip = clips["131_03"]
    J = posed_joints(clip, body)
    assert J[:, 0, 1].max() > J[:15, 0, 1].mean() + 0.05
    assert lowest_foot_heights(clip, body).max() > 0.05  # both feet off the floor


# ================================================================================ library
@pytest.fixture()
def home(tmp_path, monkeypatch):
    monkeypatch.setenv("SIMGEN_HOME", str(tmp_path / "home"))
    return tmp_path / "home"


def test_import_list_and_load_a_user_motion(body, tmp_path, home):
    clip = random_clip(seed=30, frames=4, scale=0.3)
    bvh = _smpl_bvh(body, tmp_path, SMPL_STYLE, np.zeros((24, 3)), clip.poses, clip.trans)
    dest = import_motion(bvh, "my_walk", body=body)
    body_id = body_asset_id(body)  # a body other than the bundled one: its name and hash prefix
    assert dest == home / body_id / "motions" / "my_walk.npz" and dest.is_file()
    entry = next(e for e in list_motions(body_id) if e["name"] == "my_walk")
    assert entry["source"] == "user" and entry["frames"] == 4 and entry["fps"] == 30.0
    loaded = load_motion("my_walk", body_id=body_id)
    direct = load_bvh(bvh, body=body, name="my_walk")
    np.testing.assert_allclose(loaded.poses, direct.poses, atol=1e-6)
    np.testing.assert_allclose(loaded.trans, direct.trans, atol=1e-12)
    assert loaded.meta["imported_from"] == "clip.bvh"
    # existing name: refused without overwrite (file untouched), replaced with it
    before = dest.read_bytes()
    with pytest.raises(InputError, match="already exists"):
        import_motion(bvh, "my_walk", body=body)
    assert dest.read_bytes() == before
    amass = _valid_amass(tmp_path, body)
    import_motion(amass, "my_walk", body=body, overwrite=True)
    assert load_motion("my_walk", body_id=body_id).meta["source"] == "amass"
    with pytest.raises(InputError, match="my_walk"):
        load_motion("my_wlak", body_id=body_id)


@pytest.mark.parametrize("name", ["../evil", "a b", "", "x/y", "é"])
def test_import_rejects_bad_names_and_writes_nothing(body, tmp_path, home, name):
    amass = _valid_amass(tmp_path, body)
    with pytest.raises(InputError, match="name"):
        import_motion(amass, name, body=body)
    assert not home.exists() or not any(home.rglob("*"))


def test_import_of_a_bad_file_writes_nothing(body, tmp_path, home):
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT Foo\n{\n")
    with pytest.raises(InputError):
        import_motion(bad, "broken", body=body)
    folder = home / body_asset_id(body) / "motions"
    assert not folder.exists() or not any(folder.iterdir())


def test_library_split_and_unknown_names(home):
    split = library_split()
    assert set(split) == {"train", "test"} and not set(split["train"]) & set(split["test"])
    with pytest.raises(InputError, match="not in the library"):
        load_motion("no_such_motion_anywhere")
    with pytest.raises(InputError, match="name"):
        load_motion("../../etc/passwd")
    for entry in list_motions():
        assert entry["source"] in ("bundled", "user") and entry["fps"] > 0
        assert os.path.isfile(entry["path"])


def test_bvh_joint_map_overrides_and_validates(body, tmp_path):
    clip = random_clip(seed=31, frames=2, scale=0.3)
    path = _smpl_bvh(body, tmp_path, SMPL_STYLE, np.zeros((24, 3)), clip.poses, clip.trans)
    with pytest.warns(BvhMappingWarning, match="L_Hand"):
        out = load_bvh(path, body=body, on_floor=False, joint_map={"L_Hand": None})
    assert "left_hand" not in out.meta["bvh_mapping"]
    np.testing.assert_allclose(out.poses[:, N["left_hand"]], 0.0, atol=1e-12)  # unmapped: at rest
    assert _same_rotations(out.poses[:, N["left_wrist"]], clip.poses[:, N["left_wrist"]])
    for bad in ({"Nope": "head"}, {"Head": "noggin"}, {"Head": "head", "Neck": "head"}, {"Pelvis": None}):
        with pytest.raises(InputError, match="clip.bvh"):
            load_bvh(path, body=body, joint_map=bad)
