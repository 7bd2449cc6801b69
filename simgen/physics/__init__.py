"""Torch versions of the solver's energies (SNUG's physics losses), shared by training and evaluation.

One module per term, with the names and parameter objects of :mod:`simgen.sim.energies` (a parity
test holds them equal to the Warp kernels in float64): ``membrane`` (StVK, eqs. 5.8-5.9),
``bending`` (dihedral, eq. 5.10), ``gravity`` (eq. 5.11, :class:`GravityParams`), ``inertia``
(eq. 5.6), ``contact`` (eq. 5.12, :class:`ContactParams`; SNUG's k = 250 J/m^3 is
``ContactParams.snug()``), ``friction`` (lagged, optional, :class:`FrictionParams`).

    import torch
    from simgen.physics import ClothRest, BodySurface, membrane, bending, gravity, inertia, contact
    rest = ClothRest.from_garment(garment, "cotton", dtype=torch.float32, device="cuda")
    surface = BodySurface.from_body(body).to("cuda")
    e = membrane(x, rest)                           # x [m] (B, T, V, 3) -> J per frame (mean over B, T)
    c = contact(x, body_vertices, surface, ContactParams.snug())   # body_vertices [m] (B, T, Vb, 3)
    loss = snug_loss(x, rest, 1 / 30, body_vertices, surface)["total"]

Conventions: positions (..., V, 3) with any leading (batch, time) dims; every term is summed over
its elements (vertices, triangles, hinges) at each frame, so a frame's value is in joules, and then
reduced over the leading dims by ``reduction``: "mean" (default: joules per frame), "sum" or "none"
(per-frame values). Every term is differentiable (autograd) and runs on the CPU and CUDA in
float32 or float64. Evaluation of sequences: :mod:`simgen.physics.evaluate` (``simgen eval physics``).
"""

from simgen.physics.rest import BENDING_REST_MODES, ClothRest, dihedral_angles
from simgen.physics.membrane import green_strain, membrane
from simgen.physics.bending import bending
from simgen.physics.gravity import GravityParams, gravity
from simgen.physics.inertia import inertia, inertia_sequence, predict
from simgen.physics.surface_query import BodyDistance, BodySurface, body_distance
from simgen.physics.contact import ContactParams, contact
from simgen.physics.friction import FrictionParams, LaggedContact, friction
from simgen.physics.potential import incremental_potential, snug_loss
from simgen.physics.evaluate import (COLUMNS, NORMALISATIONS, PhysicsReport, compare_potentials, evaluate_sequence,
                                     write_csv)
from simgen.physics.sources import GarmentSequence, load_dataset_sequences, load_simulation

TERMS = ("membrane", "bending", "gravity", "inertia", "contact", "friction")

__all__ = [
    "TERMS", "ClothRest", "BENDING_REST_MODES", "dihedral_angles", "green_strain", "membrane", "bending", "gravity",
    "GravityParams", "inertia", "inertia_sequence", "predict", "BodySurface", "BodyDistance", "body_distance",
    "contact", "ContactParams", "friction", "FrictionParams", "LaggedContact", "incremental_potential",
    "snug_loss", "PhysicsReport", "evaluate_sequence", "compare_potentials", "write_csv", "COLUMNS",
    "NORMALISATIONS", "GarmentSequence", "load_simulation", "load_dataset_sequences",
]
