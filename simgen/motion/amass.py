"""AMASS motion files (.npz): SMPL-H (156 pose values) and SMPL-X layouts, Z-up -> Y-up.

AMASS stores each sequence as an .npz with the axis-angle pose of every joint in the body model's
own (Y-up) frame and a world frame that is Z-up. The loader keeps SMPL's 22 body joints, sets SMPL's
two hand joints from the first finger joint of each hand (see below), rotates the motion into
simgen's Y-up world with the root-translation rule (docs/architecture.md, "Motions") and puts it on the floor.

Hand joints: SMPL's left_hand / right_hand (22, 23) are single joints at the knuckles that bend all
fingers together. AMASS carries 15 joints per hand; the loader takes the first one of each hand
(left_index1 / right_index1, the index finger's knuckle joint, the first finger joint in the AMASS
order index, middle, pinky, ring, thumb), which sits where SMPL's hand joint sits and carries the
overall closing of the hand. Files without hand poses get zeros.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from simgen.body.model import NUM_JOINTS, BodyModel
from simgen.errors import InputError
from simgen.motion.clip import MotionClip
from simgen.motion.ops import LOADER_MAX_SINK, apply_world_rotation, put_on_floor

__all__ = ["load_amass", "Z_UP_TO_Y_UP", "read_npz"]

# (x, y, z) -> (x, z, -y): AMASS's up axis +Z becomes +Y and its -Y (the usual facing) becomes +Z.
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

_FPS_KEYS = ("mocap_framerate", "mocap_frame_rate")


def read_npz(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of an .npz file, read eagerly without unpickling anything.

    Raises InputError for a missing file, a file that is not an .npz archive, a damaged archive or
    one holding pickled objects.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"motion file {path} does not exist")
    try:
        archive = np.load(path, allow_pickle=False)
    except Exception as exc:  # corrupt input surfaces as many exception types (zip, zlib, format)
        raise InputError(f"motion file {path} is not a readable .npz archive ({type(exc).__name__})") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise InputError(f"motion file {path} holds a single .npy array, not an .npz archive")
    try:
        with archive:
            return {k: np.asarray(archive[k]) for k in archive.files}
    except Exception as exc:  # a damaged member shows up only when it is read
        raise InputError(f"motion file {path} is not a readable .npz archive ({type(exc).__name__})") from None


def _numeric(data: dict, key: str, path: Path, width: int | tuple[int, ...] | None = None) -> np.ndarray:
    """data[key] as a finite float64 array of shape (T, width) (or any shape when width is None)."""
    if key not in data:
        raise InputError(f"motion file {path} lacks the field {key!r}")
    a = data[key]
    if a.dtype.kind not in "fiu":
        raise InputError(f"motion file {path}: field {key!r} must be numeric, got dtype {a.dtype}")
    a = a.astype(np.float64)
    if width is not None:
        widths = (width,) if isinstance(width, int) else width
        if a.ndim != 2 or a.shape[1] not in widths or a.shape[0] < 1:
            want = " or ".join(f"(T, {w})" for w in widths)
            raise InputError(f"motion file {path}: field {key!r} must have shape {want} with T >= 1, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"motion file {path}: field {key!r} contains NaN or inf")
    return a


def frame_rate(data: dict, path: Path, keys=_FPS_KEYS) -> float:
    """The positive frame rate [1/s] stored under one of keys."""
    key = next((k for k in keys if k in data), None)
    if key is None:
        raise InputError(f"motion file {path} lacks a frame rate field ({' or '.join(repr(k) for k in keys)})")
    a = data[key]
    if a.dtype.kind not in "fiu" or a.size != 1:
        raise InputError(f"motion file {path}: field {key!r} must be one number, got {a.dtype} of shape {a.shape}")
    fps = float(a.reshape(()))
    if not np.isfinite(fps) or fps <= 0.0:
        raise InputError(f"motion file {path}: field {key!r} must be positive, got {fps}")
    return fps


def _text(data: dict, key: str) -> str | None:
    if key not in data or data[key].dtype.kind not in "US" or data[key].size != 1:
        return None
    v = data[key].reshape(())[()]
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)


def _smpl_poses_from_amass(data: dict, path: Path) -> tuple[np.ndarray, str]:
    """SMPL poses, shape (T, 24, 3), and the layout name read off an AMASS-style archive."""
    if "root_orient" in data and "pose_body" in data:
        root = _numeric(data, "root_orient", path, 3)
        full = _numeric(data, "pose_body", path, (63, 69))
        body = full[:, :63]
        T = root.shape[0]
        if body.shape[0] != T:
            raise InputError(f"motion file {path}: field 'pose_body' has {body.shape[0]} frames but "
                             f"'root_orient' has {T}")
        hands = full[:, 63:69] if full.shape[1] == 69 else np.zeros((T, 6))  # SMPL's 23 joints carry the hands
        if "pose_hand" in data:
            ph = _numeric(data, "pose_hand", path, 90)
            if ph.shape[0] != T:
                raise InputError(f"motion file {path}: field 'pose_hand' has {ph.shape[0]} frames but "
                                 f"'root_orient' has {T}")
            hands = np.concatenate([ph[:, 0:3], ph[:, 45:48]], axis=1)
        layout = _text(data, "surface_model_type") or ("smplx" if "pose_jaw" in data else "smplh")
        flat = np.concatenate([root, body, hands], axis=1)
    elif "poses" in data:
        p = _numeric(data, "poses", path, (72, 156, 165))
        if p.shape[1] == 156:  # SMPL-H: 22 body joints, then 15 left-hand and 15 right-hand joints
            flat, layout = np.concatenate([p[:, :66], p[:, 66:69], p[:, 111:114]], axis=1), "smplh"
        elif p.shape[1] == 165:  # SMPL-X: 22 body joints, jaw, left eye, right eye, 15 + 15 hand joints
            flat, layout = np.concatenate([p[:, :66], p[:, 75:78], p[:, 120:123]], axis=1), "smplx"
        else:
            flat, layout = p, "smpl"
    else:
        raise InputError(f"motion file {path} lacks the pose field ('poses', or 'root_orient' with 'pose_body')")
    return flat.reshape(-1, NUM_JOINTS, 3), layout


def load_amass(path: str | Path, *, body: BodyModel, name: str | None = None, on_floor: bool = True) -> MotionClip:
    """Load an AMASS .npz (SMPL-H, SMPL-X, or plain SMPL 72-value poses) as a Y-up MotionClip.

    Fields read: 'poses' (T, 156 | 165 | 72) or 'root_orient' (T, 3) + 'pose_body' (T, 63, or 69 with
    SMPL's two hand joints) [+ 'pose_hand' (T, 90)], axis-angle [rad]; 'trans' (T, 3) [m]; 'mocap_framerate' or 'mocap_frame_rate' [1/s].
    The Z-up world is rotated to Y-up with R: (x, y, z) -> (x, z, -y), global_orient -> R global_orient,
    trans -> R (trans + J0) - J0 with J0 the rest pelvis of `body` (template shape). With on_floor the
    lowest foot point of the first 0.5 s is moved to y = 0 and frames where a foot would still sink
    more than LOADER_MAX_SINK (2 cm) are lifted smoothly (see ops.put_on_floor).
    name defaults to the file's stem. Raises InputError for a missing, corrupt or malformed file.
    """
    path = Path(path)
    data = read_npz(path)
    fps = frame_rate(data, path)
    poses, layout = _smpl_poses_from_amass(data, path)
    trans = _numeric(data, "trans", path, 3)
    if trans.shape[0] != poses.shape[0]:
        raise InputError(f"motion file {path}: field 'trans' has {trans.shape[0]} frames but the poses have "
                         f"{poses.shape[0]}")
    meta = {"source": "amass", "source_file": path.name, "layout": layout, "source_fps": fps}
    gender = _text(data, "gender")
    if gender is not None:
        meta["gender"] = gender
    clip = MotionClip(name or path.stem, fps, poses, trans, meta)
    clip = apply_world_rotation(clip, Z_UP_TO_Y_UP, body.rest_joints()[0, 0])
    if on_floor:
        clip = put_on_floor(clip, body, max_sink=LOADER_MAX_SINK)
    return clip
