"""StVK membrane strain energy (SNUG eqs. 5.8-5.9), the torch twin of :mod:`simgen.sim.energies.membrane`.

Per triangle t with rest area A_t and the plane-stress Lame parameters times thickness (lambda h,
mu h [N/m]):

    E_t = A_t (lambda h / 2 tr(G)^2 + mu h tr(G^2)),   G = (F^T F - I) / 2,   F = Ds Dm^-1,

Ds = [x1 - x0, x2 - x0] (3x2, deformed), Dm the rest edges in the triangle's own 2D frame
(:class:`~simgen.physics.rest.ClothRest`). A_t h is SNUG's triangle "volume".
"""

from __future__ import annotations

import torch

from simgen.physics._common import like, reduce_frames
from simgen.physics.rest import ClothRest

__all__ = ["membrane", "membrane_per_triangle", "green_strain"]


def green_strain(x: torch.Tensor, rest: ClothRest) -> torch.Tensor:
    """Green strain G = (F^T F - I) / 2 of every triangle, (..., F, 2, 2), for positions x [m] (..., V, 3)."""
    f = rest.faces.to(x.device)
    x0, x1, x2 = x[..., f[:, 0], :], x[..., f[:, 1], :], x[..., f[:, 2], :]
    ds = torch.stack([x1 - x0, x2 - x0], dim=-1)               # (..., F, 3, 2)
    F = ds @ like(rest.tri_inv_rest, x)                         # (..., F, 3, 2)
    eye = torch.eye(2, dtype=x.dtype, device=x.device)
    return 0.5 * (F.transpose(-1, -2) @ F - eye)


def membrane_per_triangle(x: torch.Tensor, rest: ClothRest) -> torch.Tensor:
    """Membrane energy [J] of every triangle, (..., F), for positions x [m] (..., V, 3)."""
    g = green_strain(x, rest)
    g00, g01, g10, g11 = g[..., 0, 0], g[..., 0, 1], g[..., 1, 0], g[..., 1, 1]
    tr = g00 + g11
    tr_g2 = g00 * g00 + g01 * g10 + g10 * g01 + g11 * g11
    psi = 0.5 * like(rest.lam_h, x) * tr * tr + like(rest.mu_h, x) * tr_g2   # [N/m] = [J/m^2]
    return like(rest.tri_area, x) * psi


def membrane(x: torch.Tensor, rest: ClothRest, *, reduction: str = "mean") -> torch.Tensor:
    """StVK membrane energy [J] of positions x [m] (..., V, 3): summed over triangles, then reduced
    over the leading (batch, time) dims ("mean": J per frame, "sum", "none": shape (...))."""
    rest.check_positions(x)
    return reduce_frames(membrane_per_triangle(x, rest).sum(-1), reduction)
