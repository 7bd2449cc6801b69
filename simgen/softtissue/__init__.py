"""Soft-tissue ground truth by simulation (thesis ch. 3's data, made here instead of captured).

    from simgen.softtissue import simulate_softtissue
    results = simulate_softtissue("open", "run", betas=[[0.0], [-2.0]])   # one SoftTissueResult per shape

The flesh is a tetrahedral mesh of the body's volume (:mod:`simgen.softtissue.mesh`), driven by the
skinned skeleton and solved for the displacement u in the unposed frame, x = skin(x_rest + u)
(:mod:`simgen.softtissue.simulate`), with linear elasticity (:mod:`simgen.softtissue.elastic`) and
an energy-conserving implicit integrator (:mod:`simgen.softtissue.solver`). docs/softtissue.md
tells the model and its validation.
"""

import importlib

_EXPORTS = {
    "simgen.softtissue.params": ("FleshParams", "REGIONS", "SOFT_REGIONS"),
    "simgen.softtissue.mesh": ("FleshMesh", "build_flesh_mesh", "flesh_mesh"),
    "simgen.softtissue.model": ("FleshModel",),
    "simgen.softtissue.solver": ("FleshSolver",),
    "simgen.softtissue.simulate": ("simulate_softtissue", "skeleton_tracks", "SoftTissueResult", "mean_speed"),
}
_LAZY = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = list(_LAZY)


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'simgen.softtissue' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
