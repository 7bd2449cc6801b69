"""N body shapes of one flesh mesh on one device: each shape's rest nodes, pinned nodes, lumped
masses, and its tetrahedra's rest shape and material (static data; the solver holds the state).

For shape beta the nodes are X = X0 + S beta (the mesh's extended shape blend shapes). A node is
pinned to the skeleton (u = 0) when it lies deeper under the shaped skin than its free layer:
``params.layer`` scaled by (BMI proxy of the shape / the template's)^``layer_exponent`` (the proxy:
the shaped body's volume times the flesh density over its height squared), times the region's
share (:meth:`FleshParams.layer_share`), and at most 60% of the deepest node within 8 cm (so a
thin limb keeps a core). A connected set of free nodes with no pinned neighbour would float: its
deepest node is pinned (``extra_pins`` counts them).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from simgen.softtissue.elastic import lame, rest_shape
from simgen.softtissue.mesh import FleshMesh
from simgen.softtissue.params import REGIONS, FleshParams

__all__ = ["FleshModel", "body_mass_proxy", "free_layer_pins"]


def body_mass_proxy(body, betas, density: float) -> float:
    """[kg/m^2] The shaped body's volume times ``density`` over its height squared (a BMI)."""
    v = body.shaped_vertices(np.asarray(betas, dtype=np.float64).reshape(1, -1))[0]
    f = np.asarray(body.faces)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = abs(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0
    height = v[:, 1].max() - v[:, 1].min()
    return density * volume / height ** 2


def free_layer_pins(x: np.ndarray, tets: np.ndarray, depth: np.ndarray, layer: np.ndarray) -> tuple[np.ndarray, int]:
    """Pinned nodes (Nn,) bool and how many floating free sets got a pin (module doc): nodes x [m],
    tets (T, 4), depth [m] under the skin (Nn,), the free layer [m] per node (Nn,)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    near = cKDTree(x).query_ball_point(x, r=0.08)
    local = np.array([depth[n].max() for n in near])
    pinned = depth >= np.minimum(layer, 0.6 * local)
    pairs = np.concatenate([tets[:, [a, b]] for a in range(4) for b in range(a + 1, 4)])
    free = ~pinned
    keep = free[pairs[:, 0]] & free[pairs[:, 1]]
    n = len(x)
    graph = coo_matrix((np.ones(int(keep.sum())), (pairs[keep, 0], pairs[keep, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    touches = np.zeros(label.max() + 1, dtype=bool)
    a, c = pairs[pinned[pairs[:, 0]] != pinned[pairs[:, 1]]].T
    touches[np.where(free[a], label[a], label[c])] = True
    extra = 0
    for comp in np.unique(label[free]):
        if not touches[comp]:
            members = np.nonzero((label == comp) & free)[0]
            pinned[members[np.argmax(depth[members])]] = True
            extra += 1
    return pinned, extra


class FleshModel:
    """The flesh of N instances of one tetrahedral mesh on ``device``.

    tets (T, 4) int; rest: N arrays of nodes [m] (Nn, 3); pinned: N (Nn,) bool; young [Pa] (T,);
    params: :class:`FleshParams` (density, Poisson's ratio). :meth:`for_body` makes the instances
    of body shapes (module doc). Host arrays per instance k: ``rest[k]``, ``pinned[k]``, ``mass[k]``
    [kg] (Nn,) lumped, ``flipped[k]``: rest tetrahedra the shape turned over (slivers; their
    volume is taken positive). Device arrays concatenate the instances (node i of instance k at k * Nn + i):
    ``rest_positions``, ``node_mass``, ``node_pinned``, ``node_instance``, ``tets``, ``inv_rest`` (Bm),
    ``volume``, ``mu``, ``lam``.
    """

    def __init__(self, tets, rest: list, pinned: list, young, params: FleshParams | None = None, *,
                 device=None) -> None:
        self.params = p = params if params is not None else FleshParams()
        self.tets_host = np.asarray(tets, dtype=np.int64)
        self.young = np.asarray(young, dtype=np.float64)
        self.num_instances, self.num_nodes = len(rest), len(rest[0])
        self.rest = [np.asarray(x, dtype=np.float64) for x in rest]
        self.pinned = [np.asarray(q, dtype=bool) for q in pinned]
        self.mass, bms, vols = [], [], []
        self.flipped, self.inv_rest_host = [], []
        for k, x in enumerate(self.rest):
            bm, vol = rest_shape(x, self.tets_host)
            # A sliver that the shape blend turned over keeps a positive stiffness (V B^T D B, V > 0).
            self.flipped.append(int(np.sum(vol <= 0)))
            vol = np.abs(vol)
            mass = np.zeros(len(x))
            np.add.at(mass, self.tets_host.ravel(), np.repeat(p.density * vol / 4.0, 4))
            self.mass.append(mass)
            self.inv_rest_host.append(bm)
            bms.append(bm)
            vols.append(vol)
        self._upload(np.concatenate(bms), np.concatenate(vols), device)

    @classmethod
    def for_body(cls, mesh: FleshMesh, body, betas, params: FleshParams | None = None, *, device=None) -> "FleshModel":
        """One instance per row of ``betas`` (N, B'): the shaped nodes, the pins of the free layer
        (module doc) and the regions' moduli. ``layer[k]`` [m] and ``extra_pins[k]`` are kept."""
        from simgen.body.surface import project_to_surface

        p = params if params is not None else FleshParams()
        b = body.check_betas(np.atleast_2d(np.asarray(betas, dtype=np.float64)))
        young = np.array([p.young(REGIONS[r]) for r in mesh.region])
        share = np.array([p.layer_share(REGIONS[r]) for r in mesh.region])
        node_share = np.ones(mesh.num_nodes)
        np.minimum.at(node_share, mesh.tets.ravel(), np.repeat(share, 4))
        proxy0 = body_mass_proxy(body, np.zeros(body.num_betas), p.density)
        rest, pinned, layers, extra = [], [], [], []
        f = np.asarray(body.faces)
        for beta in b:
            x = mesh.nodes + np.einsum("ncb,b->nc", mesh.shapedirs, beta[:mesh.shapedirs.shape[2]])
            depth = np.clip(-project_to_surface(x, body.shaped_vertices(beta[None])[0], f).signed_distance, 0, None)
            layer = p.layer * (body_mass_proxy(body, beta, p.density) / proxy0) ** p.layer_exponent
            pins, n_extra = free_layer_pins(x, mesh.tets, depth, layer * node_share)
            rest.append(x)
            pinned.append(pins)
            layers.append(float(layer))
            extra.append(n_extra)
        self = cls(mesh.tets, rest, pinned, young, p, device=device)
        self.mesh, self.body, self.betas, self.layer, self.extra_pins = mesh, body, b, layers, extra
        return self

    def _upload(self, bm: np.ndarray, vol: np.ndarray, device) -> None:
        N, Nn, T = self.num_instances, self.num_nodes, len(self.tets_host)
        dev = self.device = wp.get_device(device)
        mu, lam = lame(self.young, self.params.poisson)
        offsets = (np.arange(N) * Nn)[:, None, None]
        self.tets = wp.array((self.tets_host[None] + offsets).reshape(-1, 4).astype(np.int32), dtype=wp.vec4i, device=dev)
        self.inv_rest = wp.array(bm.astype(np.float32), dtype=wp.mat33, device=dev)
        self.volume = wp.array(vol.astype(np.float32), device=dev)
        self.mu = wp.array(np.tile(mu, N).astype(np.float32), device=dev)
        self.lam = wp.array(np.tile(lam, N).astype(np.float32), device=dev)
        self.rest_positions = wp.array(np.concatenate(self.rest).astype(np.float32), dtype=wp.vec3, device=dev)
        self.node_mass = wp.array(np.concatenate(self.mass).astype(np.float32), device=dev)
        self.node_pinned = wp.array(np.concatenate(self.pinned).astype(np.int32), device=dev)
        self.node_instance = wp.array(np.repeat(np.arange(N, dtype=np.int32), Nn), device=dev)
        self.num_tets_total = N * T

    @property
    def total_nodes(self) -> int:
        return self.num_instances * self.num_nodes
