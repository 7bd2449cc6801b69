"""Impact filter: no substep carries cloth through cloth (continuous collision detection).

The repulsion of :mod:`.energies.self_contact` keeps two layers about a thickness apart, but a
penalty acts only where it is evaluated: a vertex that travels further than the thickness in one
substep, or that the body projection or the strain limiter moves after the solve, can pass through
a triangle and leave the cloth tangled for good. This filter runs after everything that moves the
cloth in a substep and guarantees that the motion from the substep's start ``x0`` to its end ``x1``
crosses nothing, by the route of Bridson, Fedkiw and Anderson (2002)'s final safety pass, with the
time of impact of Li et al. (2021)'s additive CCD:

1. Candidates: the swept box of every vertex against the swept boxes of the triangles, and the swept
   box of every edge against those of the edges (two BVHs, built once by SAH and refit each
   substep; see ``BVH_CONSTRUCTOR``), same instance only, primitives that share a vertex skipped.
2. Time of impact of each vertex-triangle and edge-edge pair on the straight paths x0 -> x1, by
   additive CCD: advance t by (1 - s) d / l_p (never past t = 1), where d is the pair's distance
   at t and l_p bounds the pair's relative displacement over the whole path, until the distance
   has shrunk below s = 10% of the start distance (an impact: the last safe t is returned) or t
   reaches 1 with the pair still farther apart (none). It is conservative by construction and
   needs no cubic solve, so it holds in float32. (Until 2026-11-29 a step could land past t = 1
   and measure the distance on the paths' extension, calling a pair that ends 0.6 mm apart from
   3 mm, sliding 2 mm, an impact; the false zones this made cost time and strain: BENCHMARKS.md.)
3. Response: rigid impact zones (Bridson, Fedkiw and Anderson 2002; Harmon et al. 2008, as in
   ARCSim). The vertices of every impacting pair join one zone (a lock-free union-find), and a
   zone moves as one body: every vertex by the zone's mass-weighted mean displacement, with its
   mean velocity, so the zone's momentum is kept and nothing inside it moves relative to anything
   else in it. Zones only grow within a substep; they are translated, not rotated, so spin inside a
   zone is lost (an inelastic impact). Pinned vertices keep their own motion and a zone with any
   follows them. A zone without any follows its vertices that touch the body (found within the
   contact margin by this substep's body projection, which also hands over each one's half-space
   n . x >= plane, ``offset`` outside the body): its translation starts from their mean
   displacement and is then corrected, by ``BODY_ITERATIONS`` averaged projections, onto the
   intersection of their half-spaces, so that no member ends inside the body (where the
   half-spaces of a squeezed zone do not meet, the correction is a compromise). This is ARCSim's
   body-as-obstacle, for translations. Without it the mass-weighted mean displacement carried hem
   vertices that lay on a running thigh into it (up to 30 mm on the T-shirt in ``run``; 21 mm
   with the touching members' mean alone), and a hem layer over them then kept every later
   substep from taking them out. Touching vertices are not made kinematic one by one: where cloth
   is squeezed between two body parts that move differently, they would press two layers of one
   zone into each other. Moving zones changes the paths, so detection repeats, at most ``rounds``
   times.
   The zones of the last round are moved and not checked again: a path that still crosses cloth
   then is rare, and the frame's end untangles it (:mod:`simgen.sim.tangle_repair`). (Moving a
   still-impacting instance as one zone, which cannot cross itself, was the first fallback: on
   the GPU it took whole garments off their bodies, up to 34 mm inside them.)

Why zones and not a per-vertex time of impact (each vertex stopped at its earliest impact, as this
filter first did): stopping vertices in the world frame leaves them behind cloth that moves with
a running body; the next substep pulls them harder into the same impact and on the coarse T-shirt
in ``run`` the same few vertices were stopped for hundreds of substeps, 12 cm behind their
neighbours. A zone moves with its surroundings' mean and loses only its internal motion.

A round costs one refit of each BVH and one pass over vertices and edges; the next round runs
only if this one found an impact (a ``wp.capture_while`` loop on a device flag, so a substep
without impacts costs one round, also inside a CUDA graph).
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from simgen.body.surface_query import contact_funcs
from simgen.garment.mesh import unique_edges
from simgen.sim.warp_toolkit import BVH_CONSTRUCTOR, instance_offsets, module_name, scalar_types

__all__ = ["ImpactFilter", "impact_kernels"]

GAP_KEPT = 0.1          # share of a pair's start distance (beyond the separation) that additive CCD never closes
MIN_SEPARATION = 1.0e-4  # [m] no impact brings two primitives closer (float32 keeps ~1e-6 m at 10 m)
MAX_CCD_ITERATIONS = 64  # additive CCD stops here and returns its (conservative) time so far
BODY_ITERATIONS = 4      # averaged projections of a zone's translation onto its touching members' body half-spaces


@functools.cache
def impact_kernels(scalar) -> SimpleNamespace:
    """Kernels for one scalar type: ``.boxes`` (swept boxes of triangles or edges), ``.vertex_triangle``
    and ``.edge_edge`` (impacting pairs into zones), ``.zone_sums``, ``.body_sums``, ``.body_step``
    and ``.move_zones`` (the zones' rigid translation, kept out of the body), ``.start``, ``.clear``,
    ``.next_round`` and ``.time_of_impact``."""
    T = scalar_types(scalar)
    vec3 = T.vec3
    zero, one = scalar(0.0), scalar(1.0)
    tiny = scalar(1.0e-12)
    kept = scalar(GAP_KEPT)
    closest_point_triangle = contact_funcs(scalar).closest_point_triangle
    closest_points_segments = contact_funcs(scalar).closest_points_segments
    mod = module_name(__name__, scalar)

    @wp.func
    def segment_distance(p1: vec3, q1: vec3, p2: vec3, q2: vec3):
        s, t = closest_points_segments(p1, q1, p2, q2)
        return wp.length((p1 + s * (q1 - p1)) - (p2 + t * (q2 - p2)))

    @wp.func
    def pair_distance(kind: int, a: vec3, b: vec3, c: vec3, d: vec3):
        # kind 0: point a against triangle (b, c, d); kind 1: segment a-b against segment c-d.
        if kind == 0:
            q, w, inside = closest_point_triangle(a, b, c, d)
            return wp.length(a - q)
        return segment_distance(a, b, c, d)

    @wp.func
    def time_of_impact(kind: int, a: vec3, b: vec3, c: vec3, d: vec3, da: vec3, db: vec3, dc: vec3, dd: vec3):
        # Additive CCD (Li et al. 2021) on x(t) = x + t dx, t in [0, 1]: 1 if no impact.
        mean = (da + db + dc + dd) * scalar(0.25)
        da = da - mean
        db = db - mean
        dc = dc - mean
        dd = dd - mean
        if kind == 0:
            lp = wp.length(da) + wp.max(wp.max(wp.length(db), wp.length(dc)), wp.length(dd))
        else:
            lp = wp.max(wp.length(da), wp.length(db)) + wp.max(wp.length(dc), wp.length(dd))
        if lp <= tiny:
            return one
        dist = pair_distance(kind, a, b, c, d)
        xi = scalar(MIN_SEPARATION)
        if dist <= scalar(2.0) * xi:
            xi = zero  # already that close (a slip elsewhere): only crossing is an impact
        if dist <= tiny:
            return zero
        gap = kept * (dist - xi)
        t = zero
        step = (one - kept) * (dist - xi) / lp
        for _ in range(MAX_CCD_ITERATIONS):
            u = wp.min(t + step, one)  # never past the path's end (a pair ending apart is no impact)
            dist = pair_distance(kind, a + u * da, b + u * db, c + u * dc, d + u * dd)
            if dist - xi < gap and (t > zero or u >= one):
                return t
            if u >= one:
                return one
            t = u
            step = scalar(0.9) * (dist - xi) / lp
        return t

    @wp.func
    def find(parent: wp.array(dtype=wp.int32), i: int):
        # Root of i's zone; atomic reads, since other threads hook roots during the same launch.
        p = wp.atomic_add(parent, i, 0)
        while p != i:
            i = p
            p = wp.atomic_add(parent, i, 0)
        return i

    @wp.func
    def union(parent: wp.array(dtype=wp.int32), a: int, b: int):
        # Lock-free union: hook the larger root under the smaller; retry when another thread won.
        for _ in range(1 << 20):
            ra = find(parent, a)
            rb = find(parent, b)
            if ra == rb:
                return
            hi = wp.max(ra, rb)
            if wp.atomic_cas(parent, hi, hi, wp.min(ra, rb)) == hi:
                return

    @wp.func
    def record(parent: wp.array(dtype=wp.int32), inst: int, i0: int, i1: int, i2: int, i3: int,
               impacts: wp.array(dtype=wp.int32), pending: wp.array(dtype=wp.int32)):
        pending[0] = 1
        wp.atomic_add(impacts, inst, 1)
        union(parent, i0, i1)
        union(parent, i0, i2)
        union(parent, i0, i3)

    @wp.func
    def swept_box(x0: vec3, x1: vec3, offset: wp.vec3, pad: float):
        a = wp.vec3(x0) + offset
        b = wp.vec3(x1) + offset
        return wp.min(a, b) - wp.vec3(pad), wp.max(a, b) + wp.vec3(pad)

    @wp.kernel(enable_backward=False, module=mod)
    def boxes(x0: wp.array(dtype=vec3), x1: wp.array(dtype=vec3), elements: wp.array(dtype=wp.int32, ndim=2),
              vertex_instance: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.vec3), pad: float,
              lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
        e = wp.tid()
        v = elements[e, 0]
        lo, hi = swept_box(x0[v], x1[v], offsets[vertex_instance[v]], pad)
        for k in range(1, elements.shape[1]):
            v = elements[e, k]
            l2, h2 = swept_box(x0[v], x1[v], offsets[vertex_instance[v]], pad)
            lo = wp.min(lo, l2)
            hi = wp.max(hi, h2)
        lowers[e] = lo
        uppers[e] = hi

    @wp.kernel(enable_backward=False, module=mod)
    def vertex_triangle(x0: wp.array(dtype=vec3), x1: wp.array(dtype=vec3), triangles: wp.array(dtype=wp.int32, ndim=2),
                        vertex_instance: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.vec3), bvh: wp.uint64,
                        pad: float, parent: wp.array(dtype=wp.int32), impacts: wp.array(dtype=wp.int32),
                        pending: wp.array(dtype=wp.int32)):
        i = wp.tid()
        inst = vertex_instance[i]
        lo, hi = swept_box(x0[i], x1[i], offsets[inst], pad)
        query = wp.bvh_query_aabb(bvh, lo, hi)
        f = int(0)
        while wp.bvh_query_next(query, f):
            ia = triangles[f, 0]
            ib = triangles[f, 1]
            ic = triangles[f, 2]
            if ia == i or ib == i or ic == i or vertex_instance[ia] != inst:
                continue
            toi = time_of_impact(0, x0[i], x0[ia], x0[ib], x0[ic], x1[i] - x0[i], x1[ia] - x0[ia],
                                 x1[ib] - x0[ib], x1[ic] - x0[ic])
            if toi < one:
                record(parent, inst, i, ia, ib, ic, impacts, pending)

    @wp.kernel(enable_backward=False, module=mod)
    def edge_edge(x0: wp.array(dtype=vec3), x1: wp.array(dtype=vec3), edges: wp.array(dtype=wp.int32, ndim=2),
                  vertex_instance: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.vec3), bvh: wp.uint64,
                  pad: float, parent: wp.array(dtype=wp.int32), impacts: wp.array(dtype=wp.int32),
                  pending: wp.array(dtype=wp.int32)):
        e = wp.tid()
        a = edges[e, 0]
        b = edges[e, 1]
        inst = vertex_instance[a]
        lo, hi = swept_box(x0[a], x1[a], offsets[inst], pad)
        l2, h2 = swept_box(x0[b], x1[b], offsets[inst], pad)
        query = wp.bvh_query_aabb(bvh, wp.min(lo, l2), wp.max(hi, h2))
        f = int(0)
        while wp.bvh_query_next(query, f):
            if f <= e:  # each pair once
                continue
            c = edges[f, 0]
            d = edges[f, 1]
            if c == a or c == b or d == a or d == b or vertex_instance[c] != inst:
                continue
            toi = time_of_impact(1, x0[a], x0[b], x0[c], x0[d], x1[a] - x0[a], x1[b] - x0[b],
                                 x1[c] - x0[c], x1[d] - x0[d])
            if toi < one:
                record(parent, inst, a, b, c, d, impacts, pending)

    @wp.kernel(enable_backward=False, module=mod)
    def zone_sums(x0: wp.array(dtype=vec3), target: wp.array(dtype=vec3), target_v: wp.array(dtype=vec3),
                  mass: wp.array(dtype=scalar), pinned: wp.array(dtype=wp.int32), touching: wp.array(dtype=wp.int32),
                  parent: wp.array(dtype=wp.int32), zone: wp.array(dtype=wp.int32), size: wp.array(dtype=wp.int32),
                  weight: wp.array(dtype=scalar), motion: wp.array(dtype=vec3), velocity: wp.array(dtype=vec3)):
        # Each vertex's zone and the zone's sums: size, weight and weighted displacement and
        # velocity. Pinned vertices count alone when the zone has any, else those touching the body
        # (each tier outweighs the next by 1e6): a zone follows them.
        i = wp.tid()
        r = find(parent, i)
        zone[i] = r
        wp.atomic_add(size, r, 1)
        w = mass[i]
        if pinned[i] != 0:
            w = w * scalar(1.0e12)
        elif touching[i] != 0:
            w = w * scalar(1.0e6)
        wp.atomic_add(weight, r, w)
        wp.atomic_add(motion, r, w * (target[i] - x0[i]))
        wp.atomic_add(velocity, r, w * target_v[i])

    @wp.kernel(enable_backward=False, module=mod)
    def move_zones(x0: wp.array(dtype=vec3), target: wp.array(dtype=vec3), target_v: wp.array(dtype=vec3),
                   pinned: wp.array(dtype=wp.int32), zone: wp.array(dtype=wp.int32), size: wp.array(dtype=wp.int32),
                   weight: wp.array(dtype=scalar), motion: wp.array(dtype=vec3), correction: wp.array(dtype=vec3),
                   velocity: wp.array(dtype=vec3), x: wp.array(dtype=vec3), v: wp.array(dtype=vec3)):
        # A vertex alone, or pinned, keeps its own motion; a zone translates as one body.
        i = wp.tid()
        r = zone[i]
        if size[r] > 1 and pinned[i] == 0:
            x[i] = x0[i] + motion[r] / weight[r] + correction[r]
            v[i] = velocity[r] / weight[r]
        else:
            x[i] = target[i]
            v[i] = target_v[i]

    @wp.kernel(enable_backward=False, module=mod)
    def body_sums(x0: wp.array(dtype=vec3), touching: wp.array(dtype=wp.int32), normal: wp.array(dtype=vec3),
                  plane: wp.array(dtype=scalar), zone: wp.array(dtype=wp.int32), size: wp.array(dtype=wp.int32),
                  weight: wp.array(dtype=scalar), motion: wp.array(dtype=vec3), correction: wp.array(dtype=vec3),
                  push: wp.array(dtype=vec3), pushes: wp.array(dtype=wp.int32)):
        # Each touching member of a zone whose translation would leave it inside its body half-space
        # adds its projection onto that half-space (averaged per zone by body_step).
        i = wp.tid()
        if touching[i] == 0:
            return
        r = zone[i]
        if size[r] <= 1:
            return
        n = normal[i]
        short = plane[i] - wp.dot(n, x0[i] + motion[r] / weight[r] + correction[r])
        if short > zero:
            wp.atomic_add(push, r, short * n)
            wp.atomic_add(pushes, r, 1)

    @wp.kernel(enable_backward=False, module=mod)
    def body_step(push: wp.array(dtype=vec3), pushes: wp.array(dtype=wp.int32), correction: wp.array(dtype=vec3)):
        r = wp.tid()
        if pushes[r] > 0:
            correction[r] = correction[r] + push[r] / scalar(pushes[r])
            push[r] = vec3()
            pushes[r] = 0

    @wp.kernel(enable_backward=False, module=mod)
    def start(parent: wp.array(dtype=wp.int32), round_index: wp.array(dtype=wp.int32),
              pending: wp.array(dtype=wp.int32)):
        i = wp.tid()
        parent[i] = i
        if i == 0:
            round_index[0] = 0
            pending[0] = 1

    @wp.kernel(enable_backward=False, module=mod)
    def clear(size: wp.array(dtype=wp.int32), weight: wp.array(dtype=scalar), motion: wp.array(dtype=vec3),
              velocity: wp.array(dtype=vec3), correction: wp.array(dtype=vec3), pending: wp.array(dtype=wp.int32)):
        i = wp.tid()
        size[i] = 0
        weight[i] = zero
        motion[i] = vec3()
        velocity[i] = vec3()
        correction[i] = vec3()
        if i == 0:
            pending[0] = 0

    @wp.kernel(enable_backward=False, module=mod)
    def next_round(round_index: wp.array(dtype=wp.int32), rounds: int, pending: wp.array(dtype=wp.int32)):
        # Another round only after one that found an impact, and none after the last one (what it
        # moved is not checked again: a path through cloth left then is untangled at the frame's end).
        round_index[0] = round_index[0] + 1
        if round_index[0] >= rounds:
            pending[0] = 0

    return SimpleNamespace(boxes=boxes, vertex_triangle=vertex_triangle, edge_edge=edge_edge, zone_sums=zone_sums,
                           body_sums=body_sums, body_step=body_step, move_zones=move_zones, start=start,
                           clear=clear, next_round=next_round,
                           time_of_impact=time_of_impact, pair_distance=pair_distance)


class ImpactFilter:
    """Device buffers of the filter for one :class:`~simgen.sim.model.ClothModel` (module doc).

    rounds: detection passes per substep (>= 1; the zones of the last one are moved and not checked
    again). pad [m]: swept boxes are grown by it (float32 broad phase round-off). After
    :meth:`apply`, per instance (I,) int32: ``impacts`` the pairs found impacting in the last round
    that ran (0: none were left, or none were found). touching (V,) int32, touch_normal (V,) vec3 and
    touch_plane (V,) [m]: the vertices in contact with the body in this substep and their
    half-spaces n . x >= plane (:meth:`BodyCollider.project` writes them, see :meth:`touch_outputs`;
    the solver zeroes ``touching`` at each substep's start).
    """

    def __init__(self, model, rounds: int = 4, pad: float = 1.0e-4) -> None:
        self.model, self.rounds, self.pad = model, int(rounds), float(pad)
        dev, n, ni = model.device, model.num_vertices, model.num_instances
        tris = np.asarray(model.host.triangles, dtype=np.int32)
        self.edges = wp.array(unique_edges(tris).astype(np.int32), dtype=wp.int32, device=dev)
        self.offsets = wp.array(instance_offsets(ni), dtype=wp.vec3, device=dev)
        self.impacts = wp.zeros(ni, dtype=wp.int32, device=dev)
        self.touching = wp.zeros(n, dtype=wp.int32, device=dev)
        self.touch_normal = wp.zeros(n, dtype=model.vec3, device=dev)
        self.touch_plane = wp.zeros(n, dtype=model.scalar, device=dev)
        self._correction = wp.zeros(n, dtype=model.vec3, device=dev)
        self._push = wp.zeros(n, dtype=model.vec3, device=dev)
        self._pushes = wp.zeros(n, dtype=wp.int32, device=dev)
        self._parent = wp.zeros(n, dtype=wp.int32, device=dev)
        self._zone = wp.zeros(n, dtype=wp.int32, device=dev)
        self._size = wp.zeros(n, dtype=wp.int32, device=dev)
        self._weight = wp.zeros(n, dtype=model.scalar, device=dev)
        self._motion = wp.zeros(n, dtype=model.vec3, device=dev)
        self._velocity = wp.zeros(n, dtype=model.vec3, device=dev)
        self._target = wp.zeros(n, dtype=model.vec3, device=dev)
        self._target_v = wp.zeros(n, dtype=model.vec3, device=dev)
        self._round = wp.zeros(1, dtype=wp.int32, device=dev)
        self._pending = wp.zeros(1, dtype=wp.int32, device=dev)
        self._bvhs = []
        rest = model.rest_positions
        for elements in (model.triangles, self.edges):
            lo = wp.zeros(elements.shape[0], dtype=wp.vec3, device=dev)
            hi = wp.zeros(elements.shape[0], dtype=wp.vec3, device=dev)
            self._boxes(rest, rest, elements, lo, hi)
            # Built once on the rest shape (its topology follows the garment), refit afterwards.
            self._bvhs.append((elements, lo, hi, wp.Bvh(lo, hi, constructor=BVH_CONSTRUCTOR)))

    def touch_outputs(self) -> dict:
        """The keyword arguments of :meth:`BodyCollider.project` that fill this filter's touching
        vertices and their half-spaces."""
        return {"touching": self.touching, "touch_normal": self.touch_normal, "touch_plane": self.touch_plane}

    def _boxes(self, x0, x1, elements, lo, hi) -> None:
        m = self.model
        wp.launch(impact_kernels(m.scalar).boxes, dim=elements.shape[0], device=m.device,
                  inputs=[x0, x1, elements, m.vertex_instance, self.offsets, self.pad, lo, hi])

    def apply(self, x0, state) -> None:
        """Move ``state`` from ``x0`` [m], (V,) vec3 (the substep's start, crossing nothing) so that
        the motion crosses nothing either: positions and velocities in place. A round runs only
        after one that found an impact (a conditional loop, inside a CUDA graph too)."""
        m, k = self.model, impact_kernels(self.model.scalar)
        wp.copy(self._target, state.positions)
        wp.copy(self._target_v, state.velocities)
        wp.launch(k.start, dim=m.num_vertices, device=m.device,
                  inputs=[self._parent, self._round, self._pending])
        wp.capture_while(self._pending, self._one_round, x0=x0, state=state)

    def _one_round(self, x0, state) -> None:
        m, k = self.model, impact_kernels(self.model.scalar)
        x = state.positions
        for elements, lo, hi, bvh in self._bvhs:
            self._boxes(x0, x, elements, lo, hi)
            bvh.refit()
        wp.launch(k.clear, dim=m.num_vertices, device=m.device,
                  inputs=[self._size, self._weight, self._motion, self._velocity, self._correction, self._pending])
        self.impacts.zero_()
        (tris, *_, tri_bvh), (edges, *_, edge_bvh) = self._bvhs
        common = [m.vertex_instance, self.offsets]
        tail = [self.pad, self._parent, self.impacts, self._pending]
        wp.launch(k.vertex_triangle, dim=m.num_vertices, device=m.device,
                  inputs=[x0, x, tris, *common, tri_bvh.id, *tail])
        wp.launch(k.edge_edge, dim=edges.shape[0], device=m.device, inputs=[x0, x, edges, *common, edge_bvh.id, *tail])
        zone_sums = [self._zone, self._size, self._weight, self._motion, self._velocity]
        wp.launch(k.zone_sums, dim=m.num_vertices, device=m.device, inputs=[
            x0, self._target, self._target_v, m.vertex_mass, m.vertex_pinned, self.touching, self._parent, *zone_sums])
        for _ in range(BODY_ITERATIONS):
            wp.launch(k.body_sums, dim=m.num_vertices, device=m.device, inputs=[
                x0, self.touching, self.touch_normal, self.touch_plane, self._zone, self._size, self._weight,
                self._motion, self._correction, self._push, self._pushes])
            wp.launch(k.body_step, dim=m.num_vertices, device=m.device,
                      inputs=[self._push, self._pushes, self._correction])
        wp.launch(k.move_zones, dim=m.num_vertices, device=m.device, inputs=[
            x0, self._target, self._target_v, m.vertex_pinned, self._zone, self._size, self._weight, self._motion,
            self._correction, self._velocity, x, state.velocities])
        wp.launch(k.next_round, dim=1, device=m.device, inputs=[self._round, self.rounds, self._pending])
