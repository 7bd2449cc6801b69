"""Dihedral bending energy (SNUG eq. 5.10), the torch twin of :mod:`simgen.sim.energies.bending`.

Per hinge e (interior edge x0-x1 with wings x2, x3):

    E_e = k_e (theta - theta_rest)^2 / 2,   k_e = k_bend l^2 / (4 (a1 + a2))   [J],

theta the signed angle between the two face normals (0 when flat), theta_rest the template's angle
or 0 ("flat", as SNUG), the difference wrapped into (-pi, pi]. l, a1, a2 are the REST edge length and
face areas (the solver's choice, fixed per hinge; SNUG's public code scales by the deformed edge
length instead, which differs at second order in the strain).
"""

from __future__ import annotations

import math

import torch

from simgen.physics._common import like, reduce_frames
from simgen.physics.rest import ClothRest, dihedral_angles

__all__ = ["bending", "bending_per_hinge", "wrap_angle"]


def wrap_angle(a: torch.Tensor) -> torch.Tensor:
    """Angles [rad] wrapped into (-pi, pi] (one period, as the solver's kernel)."""
    return torch.where(a > math.pi, a - 2 * math.pi, torch.where(a <= -math.pi, a + 2 * math.pi, a))


def bending_per_hinge(x: torch.Tensor, rest: ClothRest) -> torch.Tensor:
    """Bending energy [J] of every hinge, (..., E), for positions x [m] (..., V, 3)."""
    theta, _ = dihedral_angles(x, rest.hinges.to(x.device))
    delta = wrap_angle(theta - like(rest.hinge_rest_angle, x))
    return 0.5 * like(rest.hinge_stiffness, x) * delta * delta


def bending(x: torch.Tensor, rest: ClothRest, *, reduction: str = "mean") -> torch.Tensor:
    """Dihedral bending energy [J] of positions x [m] (..., V, 3): summed over hinges, then reduced
    over the leading dims ("mean": J per frame, "sum", "none")."""
    rest.check_positions(x)
    return reduce_frames(bending_per_hinge(x, rest).sum(-1), reduction)
