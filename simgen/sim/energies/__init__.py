"""The solver's energy terms, one module each, as Warp kernels with analytic gradients and Hessians.

Term names (shared with the torch losses of ``simgen.physics``): "membrane", "bending", "gravity",
"inertia", "contact", "friction", "damping"; "self_contact" (cloth-cloth repulsion), "floor" (the
ground plane) and "attachment" (vertices tied to the body: waistbands) are the solver's only. Every ``eval_<term>(model, positions, ..., *,
energy=None, gradient=None, hessian=None, scale=1.0)`` adds its contribution to whichever outputs
are given: per-instance energies [J] (num_instances,), the gradient [J/m] (V,) vec3, and the 3x3
block Hessian (the model's BsrMatrix, or its values) through the model's slot maps. Kernels exist
for wp.float32 (the solver) and wp.float64 (tests); the model's scalar type picks them.
``reference`` holds plain-numpy float64 versions of every term.
"""

import warp as wp

from simgen.sim.warp_toolkit import module_name
from simgen.sim.energies.attachment import attachment_kernels, eval_attachment
from simgen.sim.energies.bending import bending_kernels, eval_bending
from simgen.sim.energies.contact import ContactFrame, ContactParams, contact_kernels, eval_contact, update_contact_frame
from simgen.sim.energies.damping import damping_kernels, eval_damping
from simgen.sim.energies.floor import eval_floor, floor_kernels, project_floor
from simgen.sim.energies.friction import FrictionParams, eval_friction, friction_kernels
from simgen.sim.energies.gravity import GravityParams, eval_gravity, gravity_kernels
from simgen.sim.energies.inertia import eval_inertia, inertia_kernels
from simgen.sim.energies.membrane import eval_membrane, membrane_kernels
from simgen.sim.energies.self_contact import (SelfContactParams, SelfContactSet, eval_self_contact,
                                              self_contact_kernels)

TERMS = ("membrane", "bending", "gravity", "inertia", "contact", "friction", "damping", "self_contact", "floor", "attachment")

_FACTORIES = {
    "membrane": membrane_kernels, "bending": bending_kernels, "gravity": gravity_kernels,
    "inertia": inertia_kernels, "contact": contact_kernels, "friction": friction_kernels,
    "damping": damping_kernels, "self_contact": self_contact_kernels, "floor": floor_kernels,
    "attachment": attachment_kernels,
}

__all__ = [
    "TERMS", "eval_membrane", "eval_bending", "eval_gravity", "GravityParams", "eval_inertia", "eval_contact",
    "ContactParams", "ContactFrame", "update_contact_frame", "eval_friction", "FrictionParams", "eval_damping",
    "eval_self_contact", "SelfContactParams", "SelfContactSet", "eval_floor", "project_floor", "eval_attachment", "load_kernels",
]


def load_kernels(scalar=wp.float32, *, device=None) -> None:
    """Build and compile (or fetch from Warp's cache) every energy kernel for one scalar type.

    Call it before capturing a CUDA graph: a module must not be compiled during capture. The
    kernels of term T live in the Warp module ``simgen.sim.energies.T.<scalar>``.
    """
    for term, factory in _FACTORIES.items():
        factory(scalar)
        wp.load_module(module_name(f"simgen.sim.energies.{term}", scalar), device=device)
