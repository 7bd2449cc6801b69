"""Lagged Coulomb friction against the body (optional), the torch twin of :mod:`simgen.sim.energies.friction`.

For every cloth vertex in contact in a lagged contact set (normal force lambda [N] > 0, outward
normal n, and the body's displacement db over the step at the closest body point, all frozen at the
step's start x_t):

    u = (I - n n^T) (x - x_t - db),   y = |u|,   D = mu lambda f0(y)   [J],

f0(y) = y for y >= eps and -y^3 / (3 eps^2) + y^2 / eps + eps / 3 below (IPC's C1 mollifier), eps =
eps_v dt (:class:`simgen.sim.FrictionParams`), mu the material's Coulomb coefficient, and lambda
capped, as in the solver, at ``max_normal_load`` times the vertex's weight m_v * 9.81 m/s^2 (cloth
pinched between body parts would otherwise be glued to the limb). Lagging makes D an exact potential
of x within one step, as in the solver.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from simgen.errors import InputError
from simgen.physics._common import like, reduce_frames
from simgen.physics.rest import ClothRest
from simgen.physics.surface_query import BodySurface, body_distance
from simgen.params import ContactParams, FrictionParams

__all__ = ["LaggedContact", "friction", "FrictionParams"]


@dataclass
class LaggedContact:
    """The frozen contact set of one step (all detached), shapes (..., V[, 3]).

    normal: outward unit normal; force [N]: k p (margin - d)^(p-1) inside the margin, else 0;
    body_displacement [m]: the body's motion over the step at the closest body point.
    """

    normal: torch.Tensor
    force: torch.Tensor
    body_displacement: torch.Tensor

    @classmethod
    def from_positions(cls, x_start: torch.Tensor, body_start: torch.Tensor, body_end: torch.Tensor,
                       surface: BodySurface, params: ContactParams = ContactParams()) -> "LaggedContact":
        """The contact set at the step's start: cloth x_start [m] (..., V, 3) against the body at
        body_start [m] (..., Vb, 3); the body moves to body_end [m] over the step."""
        with torch.no_grad():
            dist = body_distance(x_start.detach(), body_start, surface)
            d = dist.distance
            inside = (d < params.margin) & (d.abs() < params.query_distance)
            force = torch.where(inside, params.stiffness * params.power
                                * torch.clamp(params.margin - d, min=0.0) ** (params.power - 1.0),
                                torch.zeros_like(d))
            move = (body_end - body_start).to(x_start.dtype)
            lead = dist.face.shape[:-1]
            move = move.expand(lead + move.shape[-2:])
            corners = surface.faces[dist.face]                                    # (..., V, 3)
            flat = move.reshape((-1,) + move.shape[-2:])
            idx = corners.reshape(flat.shape[0], -1)
            db = torch.stack([flat[i][idx[i]] for i in range(flat.shape[0])]).reshape(corners.shape + (3,))
            db = (dist.bary[..., None] * db).sum(-2)
        return cls(normal=dist.normal, force=force, body_displacement=db)


def friction(x: torch.Tensor, x_start: torch.Tensor, lagged: LaggedContact, rest: ClothRest, dt: float,
             params: FrictionParams = FrictionParams(), *, reduction: str = "mean") -> torch.Tensor:
    """Lagged friction potential [J] of positions x [m] (..., V, 3) over a step of dt [s] from
    x_start [m]: summed over vertices, then reduced over the leading dims."""
    rest.check_positions(x)
    if not dt > 0:
        raise InputError(f"time step must be > 0, got {dt!r}")
    eps = params.smoothing_velocity * dt
    n = lagged.normal.to(x.dtype)
    disp = x - x_start - lagged.body_displacement.to(x.dtype)
    u = disp - (disp * n).sum(-1, keepdim=True) * n
    y2 = (u * u).sum(-1)
    stick = y2 < eps * eps
    y = torch.where(y2 > 0, y2, torch.ones_like(y2)).sqrt()
    y = torch.where(y2 > 0, y, torch.zeros_like(y))
    f0 = torch.where(stick, -y**3 / (3 * eps**2) + y**2 / eps + eps / 3, y)
    # The solver's cap on the lagged normal force: max_normal_load x the vertex weight (9.81 m/s^2).
    cap = min(getattr(params, "max_normal_load", float("inf")) * 9.81, 1.0e30) * like(rest.vertex_mass, x)
    c = like(rest.friction_coefficient, x) * torch.minimum(lagged.force.to(x.dtype), cap)
    per_vertex = torch.where(c > 0, c * f0, torch.zeros_like(f0))
    return reduce_frames(per_vertex.sum(-1), reduction)
