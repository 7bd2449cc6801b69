"""The Warp cloth solver: model/state, materials, one module per energy term.

    from simgen.sim import ClothModel, get_material
    model = ClothModel.from_mesh(vertices, faces, "cotton", device="cuda:0")
    state = model.state()
    solver = ImplicitSolver(model, SolverConfig())
    solver.step(state, state, body, dt)     # body: a BodyCollider or None
    result = simulate("tshirt", body_model, "walk", betas, SimulationConfig())  # garment on a moving body
    results = simulate_batch("tshirt", body_model, [SimulationJob("walk", betas), ...])  # N in one system
"""

from simgen.materials import MATERIALS, Material, get_material
from simgen.sim.model import ClothModel, ClothModelBuilder, ClothState
from simgen.sim.energies import ContactParams, FrictionParams, GravityParams
from simgen.sim.collider import BodyCollider
from simgen.sim.linear import BlockJacobiPCG
from simgen.sim.config import SimulationConfig, SolverConfig
from simgen.sim.solver import ImplicitSolver, SolverDivergedError
from simgen.sim.driver import (FRAME_STAT_KEYS, SimulationFailure, SimulationJob, SimulationResult,
                               simulate, simulate_batch)

__all__ = [
    "Material", "MATERIALS", "get_material", "ClothModel", "ClothModelBuilder", "ClothState",
    "ContactParams", "FrictionParams", "GravityParams", "BodyCollider", "BlockJacobiPCG", "ImplicitSolver",
    "SolverConfig", "SolverDivergedError", "SimulationConfig", "SimulationResult", "SimulationJob",
    "SimulationFailure", "simulate", "simulate_batch", "FRAME_STAT_KEYS",
]
