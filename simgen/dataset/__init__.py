"""Datasets: specs, job planning, resumable Zarr stores, local and Ray execution, ground truth, checks.

    from simgen.dataset import load_spec, generate_dataset, open_dataset, check_dataset
    reports = generate_dataset("tiny", out="datasets/tiny")          # a preset name or a TOML path
    ds = open_dataset("datasets/tiny")
    ds.sequence_ids(split="train"); seq = ds.sequence(ds.sequence_ids()[0])
    fit = ds.fit(seq["attrs"]["shape_id"]); tpl = ds.template
    from simgen.dataset import groundtruth                           # thesis eqs. 4.4 and 4.5

Heavy modules (warp, zarr, ray) load on first use.
"""

from __future__ import annotations

import importlib

from simgen.dataset import groundtruth
from simgen.dataset.groundtruth import (
    SmoothingParams,
    fit_displacement,
    reconstruct,
    skinning_transforms,
    smooth_garment,
    wrinkle_displacements,
)
from simgen.dataset.spec import DatasetSpec, list_presets, load_spec, parse_spec
from simgen.dataset.storage import StoreWriteError

__all__ = [
    "DatasetSpec", "load_spec", "parse_spec", "list_presets", "generate_dataset", "plan_jobs", "StoreReport",
    "GenerationError", "open_dataset", "Dataset", "check_dataset", "CheckReport", "export_sequence",
    "StoreWriteError", "groundtruth", "SmoothingParams", "smooth_garment", "fit_displacement",
    "skinning_transforms", "wrinkle_displacements", "reconstruct",
]

_LAZY = {
    "generate_dataset": "simgen.dataset.generate",
    "plan_jobs": "simgen.dataset.generate",
    "StoreReport": "simgen.dataset.generate",
    "GenerationError": "simgen.errors",
    "open_dataset": "simgen.dataset.reader",
    "Dataset": "simgen.dataset.reader",
    "check_dataset": "simgen.dataset.check",
    "CheckReport": "simgen.dataset.check",
    "export_sequence": "simgen.dataset.export",
}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'simgen.dataset' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
