"""Gravity potential (SNUG eq. 5.11), the torch twin of :mod:`simgen.sim.energies.gravity`.

    E = -sum_v m_v g . (x_v - o)   [J],

g the acceleration (:class:`simgen.sim.GravityParams`, (0, -9.81, 0): Y-up) and o the datum, the
world origin by default (the floor is y = 0, so E = m g h with h the height above the floor, as in
the solver). The datum shifts E by a constant per frame and never changes a difference between two
garments on the same body; ``origin`` (e.g. the body's root joint per frame) only changes where zero
is, e.g. to compare magnitudes with SNUG, whose bodies live in SMPL's body-centred frame.
"""

from __future__ import annotations

import torch

from simgen.physics._common import like, reduce_frames
from simgen.physics.rest import ClothRest
from simgen.params import GravityParams

__all__ = ["gravity", "GravityParams"]


def gravity(x: torch.Tensor, rest: ClothRest, params: GravityParams = GravityParams(), *,
            origin: torch.Tensor | None = None, reduction: str = "mean") -> torch.Tensor:
    """Gravity potential [J] of positions x [m] (..., V, 3), summed over vertices, then reduced.

    origin [m]: optional datum point, shape (3,) or (..., 3) (one per frame); None = world origin.
    """
    rest.check_positions(x)
    g = torch.as_tensor(params.gravity, dtype=x.dtype, device=x.device)
    heights = x @ g                                              # (..., V) [m^2/s^2] per kg
    per_frame = -(like(rest.vertex_mass, x) * heights).sum(-1)
    if origin is not None:
        origin = torch.as_tensor(origin, dtype=x.dtype, device=x.device)
        per_frame = per_frame + rest.vertex_mass.sum().to(x.dtype) * (origin @ g)
    return reduce_frames(per_frame, reduction)
