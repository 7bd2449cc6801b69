"""Body contact penalty (SNUG eq. 5.12), the torch twin of :mod:`simgen.sim.energies.contact`.

Per cloth vertex with signed distance d [m] to the posed body surface:

    E_v = k max(margin - d, 0)^p   [J],

with :class:`simgen.sim.ContactParams` (margin [m], stiffness k [J/m^p], power p, query_distance [m]).
SNUG trains with margin 2 mm, p = 3 and k = 250 J/m^3 (:meth:`ContactParams.snug`; J/m^3 = N/m^2 =
Pa); the solver's default is k = 1e4 J/m^3.

Signed distance d and its nearest body triangle: the body-surface query in torch
(:mod:`simgen.physics.surface_query`, the twin of the solver's, pseudo-normal sign; it goes through
the body's nearest TRIANGLE, not the nearest body vertex as SNUG's code does). A vertex farther than
query_distance from every body triangle gets no penalty (the solver's BVH query does not look
further).
"""

from __future__ import annotations

import torch

from simgen.params import ContactParams
from simgen.physics._common import reduce_frames
from simgen.physics.surface_query import BodyDistance, BodySurface, body_distance

__all__ = ["contact", "contact_per_vertex", "ContactParams"]


def contact_per_vertex(x: torch.Tensor, body_vertices: torch.Tensor, surface: BodySurface,
                       params: ContactParams = ContactParams(), *,
                       distance: BodyDistance | None = None) -> torch.Tensor:
    """Contact penalty [J] of every cloth vertex, (..., V) (``distance``: reuse a computed BodyDistance)."""
    if distance is None:
        distance = body_distance(x, body_vertices, surface)
    d = distance.distance
    found = d.detach().abs() < params.query_distance
    pen = torch.clamp(params.margin - d, min=0.0)
    pen = torch.where(found, pen, torch.zeros_like(pen))
    return params.stiffness * pen ** params.power


def contact(x: torch.Tensor, body_vertices: torch.Tensor, surface: BodySurface,
            params: ContactParams = ContactParams(), *, reduction: str = "mean",
            distance: BodyDistance | None = None) -> torch.Tensor:
    """Body contact penalty [J] of positions x [m] (..., V, 3) against the posed body vertices [m]
    (..., Vb, 3): summed over cloth vertices, then reduced over the leading dims."""
    e = contact_per_vertex(x, body_vertices, surface, params, distance=distance)
    return reduce_frames(e.sum(-1), reduction)
