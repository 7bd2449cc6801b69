"""The Warp cloth solver: model/state, materials, one module per energy term.

    from simgen.sim import ClothModel, get_material
    model = ClothModel.from_mesh(vertices, faces, "cotton", device="cuda:0")
    state = model.state()
"""

from simgen.sim.materials import MATERIALS, Material, get_material
from simgen.sim.model import ClothModel, ClothModelBuilder, ClothState
from simgen.sim.energies import ContactParams, FrictionParams, GravityParams

__all__ = [
    "Material", "MATERIALS", "get_material", "ClothModel", "ClothModelBuilder", "ClothState",
    "ContactParams", "FrictionParams", "GravityParams",
]
