"""The frame's last step with self-contact on: find cloth that passed through itself, untangle it.

Self-contact keeps layers apart and the impact filter stops most paths through cloth
(:mod:`simgen.sim.impact_filter`), but a substep can still end tangled (a slip of the solver or the
body projection). At the end of every frame, :class:`TangleRepair` counts each busy instance's
crossing edges on the device (:mod:`simgen.garment.crossings`) and, for the few that have some,
untangles their positions (:func:`simgen.garment.untangle.untangle`, on the host, with the frame's
start as the reference that tells which vertex went through) before the frame is recorded. A moved vertex keeps its velocity except the part that
pointed back through the layer it was moved out of, so the next substep does not push it straight
back. ``repaired`` counts, per instance, the frames that needed it; ``left`` the crossing edges
that the rounds could not remove at the last frame.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from simgen.garment.crossings import CrossingCounter
from simgen.garment.untangle import untangle

__all__ = ["TangleRepair"]


class TangleRepair:
    """Untangles the instances of a batched cloth state at frame ends (module doc).

    faces (F, 3): one copy's triangles; num_vertices V of one copy; instances N; device: the state's.
    """

    def __init__(self, faces, num_vertices: int, instances: int, device) -> None:
        self.faces = np.asarray(faces)
        self.num_vertices, self.instances = int(num_vertices), int(instances)
        self.counter = CrossingCounter(self.faces, self.num_vertices, str(device), instances=self.instances)
        self.single = CrossingCounter(self.faces, self.num_vertices, str(device))
        self.repaired = np.zeros(self.instances, dtype=np.int64)
        self.left = np.zeros(self.instances, dtype=np.int64)

    def __call__(self, state, pinned: wp.array, active: np.ndarray, reference: wp.array | None = None) -> list[int]:
        """Untangle the ``active`` (bool (N,)) instances of ``state`` (positions [m], velocities
        [m/s], (N V,) vec3) that cross themselves; ``pinned`` (N V,) int: vertices that stay;
        ``reference`` (N V,) vec3 [m]: the frame's start, whose sides tell which vertex went through.
        Returns the instances moved."""
        counts = self.counter.count_points(state.positions)
        todo = [k for k in np.flatnonzero(counts > 0) if active[k]]
        if not todo:
            return []
        x, v, fixed = state.positions.numpy(), state.velocities.numpy(), pinned.numpy() != 0
        ref = None if reference is None else reference.numpy()
        V = self.num_vertices
        for k in todo:
            rows = slice(k * V, (k + 1) * V)
            result = untangle(x[rows], self.faces, pinned=fixed[rows], counter=self.single,
                              reference=None if ref is None else ref[rows])
            shift = result.positions - x[rows]
            x[rows] = result.positions
            v[rows] = _drop_return_velocity(v[rows], shift)
            self.repaired[k] += 1
            self.left[k] = result.crossings_after
        state.positions.assign(x)
        state.velocities.assign(v)
        return todo


def _drop_return_velocity(v: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Velocities [m/s] (V, 3) without the part opposite to each vertex's untangling shift [m] (V, 3)."""
    length = np.linalg.norm(shift, axis=1, keepdims=True)
    direction = np.divide(shift, length, out=np.zeros_like(shift), where=length > 0)
    back = np.minimum(np.einsum("ij,ij->i", v, direction), 0.0)[:, None]
    return v - back * direction
