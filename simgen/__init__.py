"""simgen: garment simulation on animated parametric bodies (NVIDIA Warp), training datasets,
and learned garment models (PyTorch).

Data flows one way: body + motion + garment -> sim -> dataset -> physics -> learn, with io (USD,
renders) and the shared settings underneath (docs/architecture.md). The subpackages are imported
on demand so that ``import simgen`` stays light (torch and warp load only when used):

- ``simgen.body``: SMPL-format body model (numpy reference, torch, Warp), the open default body.
- ``simgen.motion``: MotionClip, the procedural library, AMASS/BVH loaders, slerp and resampling.
- ``simgen.io``: USD export and offscreen rendering.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

__all__ = ["__version__", "InputError", "body", "motion", "io"]

from simgen.errors import InputError


def __getattr__(name: str):
    if name in ("body", "motion", "io"):
        return importlib.import_module(f"simgen.{name}")
    raise AttributeError(f"module 'simgen' has no attribute {name!r}")
