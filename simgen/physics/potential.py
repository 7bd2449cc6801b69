"""The incremental potential of backward Euler (SNUG eq. 5.4) and SNUG's self-supervised loss (eqs. 5.5-5.12).

    IP(x) = 1/(2 h^2) (x - x_hat)^T M (x - x_hat) + Phi(x),   Phi = membrane + bending + gravity + contact
            (+ friction, optional),

the objective whose minimiser is the backward-Euler step. Over a sequence of frames with step
h = 1/fps, frame t's prediction is x_hat = 2 x_{t-1} - x_{t-2} from the two frames before it. To
compare two candidates for the same frame (a simulated frame and the LBS one), both are measured
with the same history (the simulated previous frames): the lower IP is the more physical frame.
"""

from __future__ import annotations

import torch

from simgen.errors import InputError
from simgen.physics._common import reduce_frames
from simgen.physics.bending import bending
from simgen.physics.contact import contact
from simgen.physics.friction import FrictionParams, LaggedContact, friction
from simgen.physics.gravity import gravity
from simgen.physics.inertia import inertia, predict
from simgen.physics.membrane import membrane
from simgen.physics.rest import ClothRest
from simgen.physics.surface_query import BodyDistance, BodySurface, body_distance
from simgen.params import ContactParams, GravityParams

__all__ = ["incremental_potential", "snug_loss", "STATIC_TERMS"]

STATIC_TERMS = ("membrane", "bending", "gravity", "contact")


def incremental_potential(x: torch.Tensor, x_prev: torch.Tensor, x_prev2: torch.Tensor, rest: ClothRest, dt: float,
                          body_vertices: torch.Tensor | None = None, surface: BodySurface | None = None, *,
                          contact_params: ContactParams = ContactParams(),
                          gravity_params: GravityParams = GravityParams(),
                          friction_params: FrictionParams | None = None, body_prev: torch.Tensor | None = None,
                          distance: BodyDistance | None = None, reduction: str = "none") -> dict[str, torch.Tensor]:
    """Per-term values and their sum (key "total") of the incremental potential [J] of x (..., V, 3).

    x_prev, x_prev2 [m]: the two frames before x (the prediction is 2 x_prev - x_prev2); dt [s]: the
    frame step; body_vertices [m] (..., Vb, 3) and surface: the posed body at x's time (None: no
    contact term). friction_params: include the lagged friction, its contact set taken at x_prev
    against body_prev (the body at x_prev's time, required then). distance: a BodyDistance of x
    already computed (reused). Each value is reduced over the leading dims by ``reduction``
    ("none" by default: per frame).
    """
    out = {
        "inertia": inertia(x, predict(x_prev, x_prev2), rest, dt, reduction="none"),
        "membrane": membrane(x, rest, reduction="none"),
        "bending": bending(x, rest, reduction="none"),
        "gravity": gravity(x, rest, gravity_params, reduction="none"),
    }
    if body_vertices is not None:
        if surface is None:
            raise InputError("incremental_potential needs the body's BodySurface with body_vertices")
        if distance is None:
            distance = body_distance(x, body_vertices, surface)
        out["contact"] = contact(x, body_vertices, surface, contact_params, reduction="none", distance=distance)
        if friction_params is not None:
            if body_prev is None:
                raise InputError("friction needs body_prev, the body at the previous frame")
            lagged = LaggedContact.from_positions(x_prev, body_prev, body_vertices, surface, contact_params)
            out["friction"] = friction(x, x_prev, lagged, rest, dt, friction_params, reduction="none")
    out["total"] = sum(out.values())
    return {k: reduce_frames(v, reduction) for k, v in out.items()}


def snug_loss(x: torch.Tensor, rest: ClothRest, dt: float, body_vertices: torch.Tensor, surface: BodySurface, *,
              contact_params: ContactParams = ContactParams.snug(), gravity_params: GravityParams = GravityParams(),
              inertia_start: str = "rest") -> dict[str, torch.Tensor]:
    """SNUG's self-supervised loss on predicted windows x [m] (B, T, V, 3) with bodies (B, T, Vb, 3).

    The static terms (membrane, bending, gravity, contact with SNUG's k = 250 J/m^3 by default) are
    averaged over all B x T frames; inertia over the frames that have a prediction (``inertia_start``
    "rest": frames 1..T-1 with zero velocity before frame 0, as SNUG trains on 3-frame windows;
    "skip": frames 2..T-1). Every value is in joules per frame; "total" = their sum (eq. 5.5).
    """
    from simgen.physics.inertia import inertia_sequence

    if x.ndim != 4:
        raise InputError(f"snug_loss expects predictions of shape (B, T, V, 3), got {tuple(x.shape)}")
    out = {
        "membrane": membrane(x, rest),
        "bending": bending(x, rest),
        "gravity": gravity(x, rest, gravity_params),
        "contact": contact(x, body_vertices, surface, contact_params),
        "inertia": inertia_sequence(x, rest, dt, start=inertia_start),
    }
    out["total"] = sum(out.values())
    return out
