"""The Warp cloth solver: model/state, materials, one module per energy term.

    from simgen.sim import ClothModel, get_material
    model = ClothModel.from_mesh(vertices, faces, "cotton", device="cuda:0")
    state = model.state()
    solver = ImplicitSolver(model, SolverConfig())
    solver.step(state, state, body, dt)     # body: a BodyCollider or None
    result = simulate("tshirt", body_model, "walk", betas, SimulationConfig())  # garment on a moving body
    results = simulate_batch("tshirt", body_model, [SimulationJob("walk", betas), ...])  # N in one system
    pool = SimulationPool("tshirt", body_model, 64, config, fps=30.0)   # N slots that take jobs as they free up
"""

import importlib

# Public names -> the module that defines them, imported on first use (PEP 562), so that
# ``import simgen.sim.config`` (the settings, read by dataset specs and the CLI) does not load Warp.
_EXPORTS = {
    "simgen.materials": ("Material", "MATERIALS", "get_material"),
    "simgen.params": ("ContactParams", "FrictionParams", "GravityParams", "SelfContactParams"),
    "simgen.sim.model": ("ClothModel", "ClothModelBuilder", "ClothState"),
    "simgen.sim.collider": ("BodyCollider",),
    "simgen.sim.linear": ("BlockJacobiPCG",),
    "simgen.sim.config": ("SimulationConfig", "SolverConfig"),
    "simgen.sim.solver": ("ImplicitSolver", "SolverDivergedError"),
    "simgen.sim.driver": ("FRAME_STAT_KEYS", "SimulationFailure", "SimulationJob", "SimulationResult", "simulate",
                          "simulate_batch"),
    "simgen.sim.pool": ("SimulationPool",),
}
_LAZY = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = list(_LAZY)


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'simgen.sim' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
