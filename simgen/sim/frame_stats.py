"""Per-frame statistics of a batched simulation: penetration of the body, whether the garment is on
it (:mod:`simgen.sim.placement`), its crossing edges and its most stretched triangle, for every
instance at every frame.

Self-intersection rule: a cloth vertex inside the body (by the generalised winding number, > 0.5)
counts as *at a body self-intersection* when (a) its closest body point, moved
``SELF_INTERSECTION_PROBE`` (2 mm) outward along the contact normal, is still inside the body: a
closest surface buried in another body part (arm in torso at the armpit, thigh in thigh at the
crotch) cannot be exited along its normal, and the projection cannot resolve such vertices; or (b)
the solver's contact, with its body part rule, sees it outside: cloth lying on its own part where
another part presses into that one (a forearm sunk into the belly) is kept on its own part and
so lies inside the other (the part rule of :mod:`simgen.body.surface_query`).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from simgen.body.surface_query import SELF_INTERSECTION_PROBE, MeshIdSubset, classify_inside
from simgen.garment.crossings import CrossingCounter
from simgen.params import ContactParams
from simgen.sim.collider import BodyCollider
from simgen.sim.energies.contact import part_inputs
from simgen.sim.energies.membrane import membrane_funcs
from simgen.sim.model import ClothModel

__all__ = ["FRAME_STAT_KEYS", "FrameStats", "stack_stats"]

# Per-frame statistics (each an array over frames in SimulationResult.stats / protocol_stats).
FRAME_STAT_KEYS = (
    "max_depth",                  # [m] deepest cloth vertex inside the body at the output frame (0 if none)
    "max_depth_regular",          # [m] the same over vertices not at a body self-intersection
    "inside_count",               # vertices inside the body at the output frame
    "inside_share",               # inside_count / V
    "self_intersection_count",    # inside vertices at a body self-intersection (module doc's rule)
    "depth_before_projection",    # [m] deepest vertex the solver's projections found over the frame
    "retries",                    # half-step retries of the solver's divergence guard
    "unresolved",                 # steps still failing the guard after every retry (finite)
    "newton_iterations",          # Newton iterations over the frame's substeps
    "cg_iterations",              # PCG iterations over the frame's substeps
    "step_time",                  # [s] the frame's stepping (posing, refits, solver), synchronised
    "wall_time",                  # [s] host wall time of the frame, statistics included
    "body_share",                 # share of the garment's vertices within 5 cm of the body (simgen.sim.placement)
    "lbs_offset",                 # [m] median distance of the garment's support from its skinned (LBS) position
    "support_drop",               # [m] median sag of the support below its skinned position (along the body's up)
    "min_height",                 # [m] the lowest garment vertex (the floor: SolverConfig.floor)
    "crossing_edges",             # garment edges through a garment triangle (simgen.garment.crossings)
    "strain_max",                 # [-] the most stretched triangle's largest principal stretch - 1
                                  #     (simgen.dataset.quality.triangle_strain's measure, float32 here)
    "strain_max_regular",         # [-] the same over triangles with no vertex at a body self-intersection
)                                 #     (the dataset check's strain rule)


_membrane = membrane_funcs(wp.float32)


@wp.kernel(enable_backward=False)
def triangle_stretch_max(x: wp.array(dtype=wp.vec3), triangles: wp.array(dtype=wp.int32, ndim=2),
                         inv_rest: wp.array(dtype=wp.mat22), tri_instance: wp.array(dtype=wp.int32),
                         measured: wp.array(dtype=wp.int32), self_hit: wp.array(dtype=wp.int32),
                         out: wp.array(dtype=wp.float32), out_regular: wp.array(dtype=wp.float32)):
    """For the instances i with measured[i] != 0: out[i] = max over i's triangles of sqrt(largest
    eigenvalue of F^T F) - 1, F = Ds Dm^-1 (3 x 2); out_regular[i] the same over the triangles with
    no vertex at a body self-intersection (self_hit: the module doc's rule). Both reset to -1 before
    (the least a stretch can be)."""
    t = wp.tid()
    i = tri_instance[t]
    if measured[i] == 0:
        return
    a0 = triangles[t, 0]
    a1 = triangles[t, 1]
    a2 = triangles[t, 2]
    f = _membrane.deformation_gradient(x[a0], x[a1], x[a2], inv_rest[t])
    c = wp.transpose(f) * f
    stretch = wp.sqrt(0.5 * (c[0, 0] + c[1, 1]) + wp.sqrt(wp.max(0.25 * (c[0, 0] - c[1, 1]) * (c[0, 0] - c[1, 1])
                                                                 + c[0, 1] * c[0, 1], 0.0))) - 1.0
    wp.atomic_max(out, i, stretch)
    if self_hit[a0] == 0 and self_hit[a1] == 0 and self_hit[a2] == 0:
        wp.atomic_max(out_regular, i, stretch)


class FrameStats:
    """Per-frame statistics of every instance: penetration, and whether the garment is on the body
    (:mod:`simgen.sim.placement`) at the output frame."""

    def __init__(self, model: ClothModel, collider: BodyCollider, wbody, garment, body, *,
                 contact: ContactParams) -> None:
        """contact: the solver's contact parameters (its part rule's pinch_distance; the query reaches
        its query_distance [m], at least the placement's on-body distance)."""
        from simgen.sim.placement import ON_BODY_DISTANCE, garment_reference

        dev = model.device
        self.model, self.collider, self.wbody = model, collider, wbody
        self.pinch_distance = float(contact.pinch_distance)
        n = model.num_vertices
        self.distance = wp.zeros(n, dtype=wp.float32, device=dev)
        self.depth = wp.zeros(n, dtype=wp.float32, device=dev)
        self.inside = wp.zeros(n, dtype=wp.int32, device=dev)
        self.self_hit = wp.zeros(n, dtype=wp.int32, device=dev)
        # The collider's meshes lack winding-number support; a second BVH per instance on the same
        # points adds it and is refit only when statistics are taken.
        nv = collider.num_body_vertices
        self.winding_meshes = [
            wp.Mesh(points=collider.points[k * nv:(k + 1) * nv], indices=collider.faces, support_winding_number=True)
            for k in range(collider.num_instances)]
        self.winding_ids = wp.array([m.id for m in self.winding_meshes], dtype=wp.uint64, device=dev)
        # The ids classify_inside reads: 0 for the instances a measure leaves out (a pool's idle slots).
        self._measured = MeshIdSubset(self.winding_meshes, dev)
        self.starts = np.asarray(model.vertex_start)
        self.query_distance = max(float(contact.query_distance), ON_BODY_DISTANCE)
        # The garment's LBS positions: its template on each instance's shape, posed on the device by
        # the body's own skinning kernel with the garment's weights.
        self.reference = garment_reference(garment, body, device=str(dev))
        self.template = np.asarray(garment.vertices, dtype=np.float64)
        ni, nvg = model.num_instances, len(self.template)
        self.lbs_rest = wp.zeros((ni, nvg), dtype=wp.vec3, device=dev)
        self.lbs_rest_up = wp.zeros((ni, nvg), dtype=wp.vec3, device=dev)
        self.lbs = wp.zeros((ni, nvg), dtype=wp.vec3, device=dev)
        self.lbs_up = wp.zeros((ni, nvg), dtype=wp.vec3, device=dev)
        self.skin_joint = wp.array(self.reference.skin_joint, dtype=wp.int32, device=dev)
        self.skin_weight = wp.array(self.reference.skin_weight.astype(np.float32), dtype=wp.float32, device=dev)
        self.betas = None
        if model.num_vertices != ni * nvg:
            raise ValueError("every instance of the model must be a copy of the garment")
        self.crossings = CrossingCounter(garment.faces, nvg, str(dev), instances=ni)
        self.strain_max = wp.zeros(ni, dtype=wp.float32, device=dev)
        self.strain_max_regular = wp.zeros(ni, dtype=wp.float32, device=dev)
        self.measured = wp.zeros(ni, dtype=wp.int32, device=dev)

    def _strain_max(self, positions: wp.array, chosen) -> tuple[np.ndarray, np.ndarray]:
        """(N,) each instance's largest triangle stretch - 1, over all its triangles and over those
        away from body self-intersections (``self_hit`` as classified this frame); -1 for the
        instances not in ``chosen``."""
        flags = np.zeros(len(self.winding_meshes), dtype=np.int32)
        flags[list(chosen)] = 1
        self.measured.assign(flags)
        self.strain_max.fill_(-1.0)
        self.strain_max_regular.fill_(-1.0)
        m = self.model
        wp.launch(triangle_stretch_max, dim=m.num_triangles, device=m.device,
                  inputs=[positions, m.triangles, m.tri_inv_rest, m.tri_instance, self.measured, self.self_hit],
                  outputs=[self.strain_max, self.strain_max_regular])
        return self.strain_max.numpy(), self.strain_max_regular.numpy()

    def measure(self, positions: wp.array, betas: np.ndarray, instances=None, host_positions=None) -> list[dict | None]:
        """One dict per instance (keys: the penetration and placement entries of FRAME_STAT_KEYS);
        betas (N, B): each instance's body shape now; instances: those to measure (None: all), the
        others' entries are None (a pool's idle slots: never queried; their bodies are refit only
        inside the CUDA graph of :meth:`MeshIdSubset.refit`);
        host_positions: ``positions`` already on the host (V, 3), to spare a second copy."""
        from simgen.body._warp_kernels import skinning_kernel
        from simgen.sim.placement import placement_rows

        chosen = range(len(self.winding_meshes)) if instances is None else sorted(instances)
        self._measured.refit(chosen)
        model = self.model
        wp.launch(classify_inside, dim=model.num_vertices, device=model.device,
                  inputs=[positions, model.vertex_instance, self._measured.of(chosen), self.query_distance,
                          SELF_INTERSECTION_PROBE,
                          *part_inputs(model, self.collider.part_masks, self.pinch_distance),
                          self.distance, self.depth, self.inside, self.self_hit])
        if self.betas is None or not np.array_equal(self.betas, betas):
            self.betas = np.array(betas, dtype=np.float64)
            rest = self.reference.rest_vertices(self.template, self.betas)
            self.lbs_rest.assign(rest.astype(np.float32))
            self.lbs_rest_up.assign((rest + np.array([0.0, 1.0, 0.0])).astype(np.float32))
        for rest, out in ((self.lbs_rest, self.lbs), (self.lbs_rest_up, self.lbs_up)):
            wp.launch(skinning_kernel, dim=out.shape, device=model.device,
                      inputs=[rest, self.wbody.transforms, self.skin_joint, self.skin_weight], outputs=[out])
        # Every instance is a copy of the garment: per-instance arrays are rows of (N, V) ones.
        ni, nvg = len(self.winding_meshes), len(self.template)
        k = np.asarray(chosen, dtype=np.int64)
        x = (positions.numpy() if host_positions is None else host_positions).reshape(ni, nvg, 3)[k]
        lbs = self.lbs.numpy()[k]
        up = self.lbs_up.numpy()[k] - lbs
        dist, depth, inside, self_hit = (a.numpy().reshape(ni, nvg)[k]
                                         for a in (self.distance, self.depth, self.inside, self.self_hit))
        crossing = self.crossings.count_points(positions, chosen)[k]
        strain, strain_regular = (a[k] for a in self._strain_max(positions, chosen))
        regular = (inside != 0) & (self_hit == 0)
        cols = dict(max_depth=depth.max(axis=1, initial=0.0),
                    max_depth_regular=np.where(regular, depth, -np.inf).max(axis=1, initial=0.0),
                    inside_count=inside.sum(axis=1), self_intersection_count=self_hit.sum(axis=1),
                    crossing_edges=crossing, strain_max=strain, strain_max_regular=strain_regular,
                    **placement_rows(x, lbs, up, dist, self.reference.support))
        cols["inside_share"] = cols["inside_count"] / max(nvg, 1)
        ints = ("inside_count", "self_intersection_count", "crossing_edges")
        rows: list = [None] * ni
        for j, i in enumerate(k):
            rows[i] = {key: (int(v[j]) if key in ints else float(v[j])) for key, v in cols.items()}
        return rows


def stack_stats(rows: list[dict]) -> dict:
    out = {}
    for k in FRAME_STAT_KEYS:
        dtype = np.int64 if k in ("inside_count", "self_intersection_count", "crossing_edges", "retries", "unresolved",
                                  "newton_iterations", "cg_iterations") else np.float64
        out[k] = np.array([r[k] for r in rows], dtype=dtype)
    return out
