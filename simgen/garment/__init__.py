"""Garments: templates on the body, OBJ import and validation, skinning weights, LBS preview.

    from simgen import garment
    g = garment.load_garment("tshirt", body=body)             # user garments first, then bundled
    w = garment.compute_skin_weights(g.vertices, body, method="diffused", faces=g.faces)
    posed = garment.lbs(g.vertices, g.skin_weights, body.forward(betas, pose, trans).transforms)
    g, report = garment.import_garment_obj("skirt.obj", "my_skirt", body)
    garment.preview_garment(g, body, "walk", out_dir="preview")

Template generation, building and the quality check (``generate_template``, ``TEMPLATE_NAMES``,
``build_garment``, ``build_all``, ``check_garment``, ``CheckReport``) load on first use.
"""

from __future__ import annotations

import importlib

from simgen.garment.garment import Garment
from simgen.garment.library import list_garments, load_garment
from simgen.garment.obj_import import GarmentImportError, ImportReport, import_garment_obj, validate_obj
from simgen.garment.preview import preview_garment
from simgen.garment.skinning import compute_skin_weights, inverse_lbs, lbs, shape_offsets

__all__ = [
    "Garment",
    "compute_skin_weights",
    "shape_offsets",
    "lbs",
    "inverse_lbs",
    "import_garment_obj",
    "validate_obj",
    "ImportReport",
    "GarmentImportError",
    "list_garments",
    "load_garment",
    "preview_garment",
]
# The template names below are left out of __all__ so that `from simgen.garment import *` never
# imports the template generator (and works while a module of it is missing).

# Resolved on first access: name -> (module, attribute).
_LAZY = {
    "generate_template": ("simgen.garment.templates", "generate_template"),
    "TEMPLATE_NAMES": ("simgen.garment.templates", "TEMPLATE_NAMES"),
    "build_garment": ("simgen.garment.build", "build_garment"),
    "build_all": ("simgen.garment.build", "build_all"),
    "check_garment": ("simgen.garment.check", "check_garment"),
    "CheckReport": ("simgen.garment.check", "CheckReport"),
}


def __getattr__(name: str):
    target = _LAZY.get(name)
    if target is None:
        raise AttributeError(f"module 'simgen.garment' has no attribute {name!r}")
    value = getattr(importlib.import_module(target[0]), target[1])
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
