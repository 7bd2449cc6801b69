"""Inertia term of backward Euler as minimisation (SNUG eqs. 5.4, 5.6), twin of :mod:`simgen.sim.energies.inertia`.

    E = 1 / (2 h^2) (x - x_hat)^T M (x - x_hat)   [J],   x_hat = x_t + h v_t,

with the lumped (diagonal) masses of :class:`~simgen.physics.rest.ClothRest`. Over a sequence of
frames h is the frame step 1/fps and v_t = (x_t - x_{t-1}) / h, so the prediction for frame t+1 is
x_hat = 2 x_t - x_{t-1} (:func:`predict`): frame t of a sequence needs the two frames before it.
"""

from __future__ import annotations

import torch

from simgen.errors import InputError
from simgen.physics._common import like, reduce_frames
from simgen.physics.rest import ClothRest

__all__ = ["inertia", "inertia_sequence", "predict", "INERTIA_START"]

INERTIA_START = ("skip", "rest")


def predict(x_prev: torch.Tensor, x_prev2: torch.Tensor) -> torch.Tensor:
    """Explicit prediction x_hat = x_t + h v_t = 2 x_t - x_{t-1} [m] from the last two frames (..., V, 3)."""
    return 2.0 * x_prev - x_prev2


def inertia(x: torch.Tensor, x_hat: torch.Tensor, rest: ClothRest, dt: float, *,
            reduction: str = "mean") -> torch.Tensor:
    """Inertia term [J] of positions x [m] (..., V, 3) against the prediction x_hat [m] (same shape,
    or broadcastable) with step dt [s]: summed over vertices, then reduced over the leading dims."""
    rest.check_positions(x)
    if not dt > 0:
        raise InputError(f"time step must be > 0, got {dt!r}")
    d = x - x_hat
    per_frame = 0.5 / (dt * dt) * (like(rest.vertex_mass, x) * (d * d).sum(-1)).sum(-1)
    return reduce_frames(per_frame, reduction)


def inertia_sequence(x: torch.Tensor, rest: ClothRest, dt: float, *, start: str = "skip",
                     reduction: str = "mean") -> torch.Tensor:
    """Inertia of every frame of sequences x [m] (..., T, V, 3) with frame step dt [s].

    start="skip": frames 2..T-1 (each has the two frames its prediction needs), per-frame shape
      (..., T-2);
    start="rest": frames 1..T-1 with a zero velocity before frame 0 (x_hat = x_0 for frame 1), as
      SNUG's training code does on its 3-frame windows; per-frame shape (..., T-1).
    """
    rest.check_positions(x)
    if x.ndim < 3:
        raise InputError(f"sequence positions must have shape (..., T, V, 3), got {tuple(x.shape)}")
    if start == "skip":
        if x.shape[-3] < 3:
            raise InputError(f"inertia needs at least 3 frames, got {x.shape[-3]}")
        x_hat = predict(x[..., 1:-1, :, :], x[..., :-2, :, :])
        return inertia(x[..., 2:, :, :], x_hat, rest, dt, reduction=reduction)
    if start == "rest":
        if x.shape[-3] < 2:
            raise InputError(f"inertia needs at least 2 frames, got {x.shape[-3]}")
        prev2 = torch.cat([x[..., :1, :, :], x[..., :-2, :, :]], dim=-3)
        x_hat = predict(x[..., :-1, :, :], prev2)
        return inertia(x[..., 1:, :, :], x_hat, rest, dt, reduction=reduction)
    raise InputError(f"start must be one of {INERTIA_START}, got {start!r}")
