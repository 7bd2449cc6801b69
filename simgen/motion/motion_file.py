"""simgen's own motion files, and loading any supported motion file by its content.

simgen writes AMASS-style .npz archives (so AMASS tooling can read them) that are marked as Y-up:
  poses (T, 72) float32: SMPL axis-angle [rad], 24 joints x 3;
  trans (T, 3) float64: root translation [m] (SMPL's meaning, docs/architecture.md, "Motions");
  mocap_frame_rate () float64 [1/s]; gender 'neutral'; betas zeros(10);
  up_axis 'Y' (AMASS files are Z-up and have no such field);
  simgen_meta: JSON {"format": 1, "name": ..., "meta": {...}}.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np

from simgen._fileio import atomic_write_bytes
from simgen.body.model import NUM_JOINTS, BodyModel
from simgen.errors import InputError
from simgen.motion.amass import _numeric, _text, frame_rate, load_amass, read_npz
from simgen.motion.clip import MotionClip
from simgen.motion.ops import LOADER_MAX_SINK, put_on_floor

__all__ = ["save_motion", "load_motion_file", "read_simgen_npz", "SIMGEN_MOTION_FORMAT"]

SIMGEN_MOTION_FORMAT = 1


def save_motion(clip: MotionClip, path: str | Path) -> Path:
    """Write clip as a simgen motion .npz (module docstring) and return the path.

    The file is written to a temporary name in the same folder and renamed into place, so an
    interrupted write never leaves a half file under `path`.
    """
    path = Path(path)
    try:
        meta_json = json.dumps({"format": SIMGEN_MOTION_FORMAT, "name": clip.name, "meta": clip.meta})
    except (TypeError, ValueError) as exc:
        raise InputError(f"motion {clip.name!r}: field 'meta' is not JSON-serialisable ({exc})") from None
    arrays = {
        "poses": clip.poses.reshape(clip.num_frames, NUM_JOINTS * 3).astype(np.float32),
        "trans": clip.trans.astype(np.float64),
        "mocap_frame_rate": np.array(clip.fps, dtype=np.float64),
        "gender": np.array("neutral"),
        "betas": np.zeros(10),
        "up_axis": np.array("Y"),
        "simgen_meta": np.array(meta_json),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return atomic_write_bytes(path, buffer.getvalue())


def _is_simgen(data: dict) -> bool:
    return "simgen_meta" in data or _text(data, "up_axis") == "Y"


def read_simgen_npz(data: dict, path: Path, *, name: str | None = None) -> MotionClip:
    """A MotionClip from the arrays of a simgen motion .npz (as returned by amass.read_npz)."""
    fps = frame_rate(data, path, keys=("mocap_frame_rate", "mocap_framerate"))
    poses = _numeric(data, "poses", path, NUM_JOINTS * 3)
    trans = _numeric(data, "trans", path, 3)
    if trans.shape[0] != poses.shape[0]:
        raise InputError(f"motion file {path}: field 'trans' has {trans.shape[0]} frames but 'poses' has "
                         f"{poses.shape[0]}")
    stored_name, meta = None, {}
    if "simgen_meta" in data:
        raw = data["simgen_meta"]
        try:
            info = json.loads(str(raw.reshape(())[()]))
            stored_name, meta = info.get("name"), dict(info.get("meta", {}))
        except (ValueError, TypeError, AttributeError):
            raise InputError(f"motion file {path}: field 'simgen_meta' is not a JSON object") from None
    return MotionClip(name or stored_name or path.stem, fps, poses.reshape(-1, NUM_JOINTS, 3), trans, meta)


def _default_body() -> BodyModel:
    from simgen.body import load  # the bundled body; imported late so motion files load without it

    return load("open")


def load_motion_file(
    path: str | Path,
    *,
    body: BodyModel | None = None,
    name: str | None = None,
    on_floor: bool = True,
) -> MotionClip:
    """Load a motion file of any supported kind, chosen by its content.

    - simgen .npz (has 'up_axis' = 'Y' or 'simgen_meta'): returned as stored (it was put on the floor
      when made); when a body is given and on_floor is set, it is put on that body's floor.
    - AMASS .npz: :func:`simgen.motion.amass.load_amass`.
    - BVH text (starts with 'HIERARCHY'): :func:`simgen.motion.bvh.load_bvh` at 30 fps.
    AMASS and BVH need a body for the conversion; body=None uses the bundled 'open' body.
    Raises InputError for missing, unrecognised or malformed files.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"motion file {path} does not exist")
    with open(path, "rb") as fh:
        head = fh.read(64)
    if head.lstrip().startswith(b"HIERARCHY"):
        from simgen.motion.bvh import load_bvh

        return load_bvh(path, body=body if body is not None else _default_body(), name=name, on_floor=on_floor)
    if not zipfile.is_zipfile(path):
        raise InputError(f"motion file {path} is neither an .npz archive nor a BVH file")
    data = read_npz(path)
    if _is_simgen(data):
        clip = read_simgen_npz(data, path, name=name)
        if body is not None and on_floor:
            clip = put_on_floor(clip, body, max_sink=LOADER_MAX_SINK)
        return clip
    return load_amass(path, body=body if body is not None else _default_body(), name=name, on_floor=on_floor)
