"""The template tetrahedral mesh of a body's volume, made once on the CPU, and what it carries from
the body: shape blend shapes and skinning weights extended harmonically into the volume, the
region of every tetrahedron, and where every body vertex sits in it.

:func:`build_flesh_mesh` tetrahedralizes the template body (rest pose, betas 0) with fTetWild
(``pytetwild``, MPL-2.0), graded: ``edge`` [m] at the skin, growing inward to 8 cm. On the skin
nodes (those of the volume's boundary) an attribute is the body's, interpolated at the closest
point of the body surface; inside it solves the graph Laplace equation (uniform weights on the
tetrahedra's edges) with those boundary values, so it is smooth and the shaped mesh keeps its
tetrahedra the right way round. A body vertex is carried by the tetrahedron that contains it
(barycentric weights; the few just outside fTetWild's envelope by the nearest one, clamped).

The bundled open body has its mesh in ``simgen/softtissue/data``; another body (a user's SMPL
file) gets one with ``simgen body flesh-mesh``, which the simulation then loads: the GPU machine
needs no mesher.
"""

from __future__ import annotations

import os
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from simgen.errors import InputError

__all__ = ["FleshMesh", "build_flesh_mesh", "flesh_mesh", "tet_regions", "BUNDLED"]

BUNDLED = Path(__file__).resolve().parent / "data"
_FIELDS = ("nodes", "tets", "shapedirs", "weights", "region", "skin_tet", "skin_bary", "boundary")


@dataclass
class FleshMesh:
    """A body's template tetrahedral mesh.

    nodes [m] (N, 3): on the template body in rest pose; tets (T, 4) int32, positively oriented;
    shapedirs [m] (N, 3, B): the body's shape blend shapes extended into the volume; weights (N, 24):
    its skinning weights likewise (rows sum to 1); region (T,) int32: index into
    :data:`simgen.softtissue.params.REGIONS`; skin_tet (V,) int32 and skin_bary (V, 4): each body
    vertex's tetrahedron and barycentric weights; boundary (N,) bool: nodes on the volume's surface;
    body_hash: the body model's :attr:`~simgen.body.BodyModel.hash`.
    """

    nodes: np.ndarray
    tets: np.ndarray
    shapedirs: np.ndarray
    weights: np.ndarray
    region: np.ndarray
    skin_tet: np.ndarray
    skin_bary: np.ndarray
    boundary: np.ndarray
    body_hash: str

    @property
    def num_nodes(self) -> int:
        return len(self.nodes)

    @property
    def num_tets(self) -> int:
        return len(self.tets)

    def skin(self, u: np.ndarray) -> np.ndarray:
        """Node values (..., N, 3) at the body's vertices: (..., V, 3)."""
        u = np.asarray(u)
        return np.einsum("...vkc,vk->...vc", u[..., self.tets[self.skin_tet], :], self.skin_bary)

    def save(self, path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(tmp, nodes=self.nodes.astype(np.float32), tets=self.tets.astype(np.int32),
                            shapedirs=self.shapedirs.astype(np.float32), weights=self.weights.astype(np.float32),
                            region=self.region.astype(np.int8), skin_tet=self.skin_tet.astype(np.int32),
                            skin_bary=self.skin_bary.astype(np.float32), boundary=self.boundary,
                            body_hash=np.asarray(self.body_hash))
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path) -> "FleshMesh":
        path = Path(path)
        try:
            with np.load(path) as d:
                missing = [k for k in _FIELDS + ("body_hash",) if k not in d]
                if missing:
                    raise InputError(f"{path}: not a flesh mesh (no {', '.join(missing)})")
                return cls(**{k: np.asarray(d[k]) for k in _FIELDS}, body_hash=str(d["body_hash"]))
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            raise InputError(f"{path}: cannot read the flesh mesh ({exc})") from None


def flesh_mesh(body, path=None) -> FleshMesh:
    """The flesh mesh of ``body``: the file at ``path``, or the bundled one of the open body.
    InputError when it belongs to another body or there is none."""
    if path is None:
        path = BUNDLED / f"{body.name}_flesh.npz"
        if not path.exists():
            raise InputError(f"no flesh mesh for body {body.name!r}: make one on a CPU machine with "
                             f"`simgen body flesh-mesh --body BODY_FILE --out FILE` and pass it")
    mesh = FleshMesh.load(path)
    if mesh.body_hash != body.hash:
        raise InputError(f"{path}: the flesh mesh was made for another body model (hash {mesh.body_hash[:12]}, "
                         f"this body {body.hash[:12]})")
    return mesh


def _tetrahedralize(vertices, faces, edge: float, quiet: bool):
    try:
        import pytetwild
    except ImportError:
        raise InputError("making a flesh mesh needs pytetwild: pip install 'simgen[softtissue]'") from None
    from simgen.body.surface import project_to_surface

    v = np.array(vertices, dtype=np.float64)
    f = np.array(faces, dtype=np.int32)
    # fTetWild writes a scratch file into the working folder: give it a temporary one (the process's
    # working folder changes meanwhile: not for threads).
    here = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="simgen-tetwild-") as scratch:
        os.chdir(scratch)
        try:
            coarse_v, coarse_t = pytetwild.tetrahedralize(v, f, edge_length_abs=0.06, epsilon=0.001, quiet=quiet)
            depth = np.abs(project_to_surface(coarse_v, v, f).signed_distance)
            sizing = np.clip(edge + 0.6 * depth, edge, 0.08)
            return pytetwild.tetrahedralize(v, f, edge_length_abs=0.08, epsilon=0.001, quiet=quiet,
                                            bg_vertices=np.array(coarse_v, dtype=np.float64),
                                            bg_tets=np.array(coarse_t, dtype=np.int32), bg_values=sizing)
        finally:
            os.chdir(here)


def _boundary_nodes(tets: np.ndarray, n: int) -> np.ndarray:
    faces = np.sort(np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]],
                                    tets[:, [1, 2, 3]]]), axis=1)
    uniq, counts = np.unique(faces, axis=0, return_counts=True)
    out = np.zeros(n, dtype=bool)
    out[uniq[counts == 1].ravel()] = True
    return out


def _harmonic(tets: np.ndarray, boundary: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Values (N, C) kept on the boundary nodes and solved inside from the graph Laplace equation."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    n = len(boundary)
    pairs = np.concatenate([tets[:, [a, b]] for a in range(4) for b in range(a + 1, 4)])
    pairs = np.unique(np.sort(pairs, axis=1), axis=0)
    adj = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    adj = adj + adj.T
    lap = sp.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj
    inner = np.nonzero(~boundary)[0]
    out = values.copy()
    if len(inner):
        rhs = -lap[inner][:, np.nonzero(boundary)[0]] @ values[boundary]
        out[inner] = spla.splu(lap[inner][:, inner].tocsc()).solve(np.asarray(rhs))
    return out


def tet_regions(nodes: np.ndarray, tets: np.ndarray, weights: np.ndarray, rest_joints: np.ndarray) -> np.ndarray:
    """Region of each tetrahedron (index into REGIONS): the joint with the largest summed skinning
    weight of its nodes names the limb; the torso's front is belly below the middle of spine2 and
    spine3 and chest above it, its back is buttocks below the pelvis joint (and the hips' upper back)
    and back above."""
    from simgen.softtissue.params import REGIONS

    J = np.asarray(rest_joints)
    j = np.asarray(weights)[tets].sum(axis=1).argmax(axis=1)
    centre = np.asarray(nodes)[tets].mean(axis=1)
    front = centre[:, 2] > J[j, 2]
    belly_top = 0.5 * (J[6, 1] + J[9, 1])
    by_joint = {4: "shin", 5: "shin", 7: "foot", 8: "foot", 10: "foot", 11: "foot", 12: "head", 15: "head",
                16: "upper_arm", 17: "upper_arm", 18: "forearm", 19: "forearm", 20: "hand", 21: "hand", 22: "hand",
                23: "hand"}
    names = []
    for jt, fr, (_, y, _) in zip(j, front, centre):
        if jt in by_joint:
            names.append(by_joint[jt])
        elif jt in (1, 2):                             # hips: the thigh, its upper back the buttocks
            names.append("buttocks" if not fr and y > J[jt, 1] - 0.12 else "thigh")
        elif fr:
            names.append("belly" if y < belly_top else "chest")
        else:
            names.append("buttocks" if y < J[0, 1] else "back")
    return np.array([REGIONS.index(n) for n in names], dtype=np.int32)


def _embed(points: np.ndarray, nodes: np.ndarray, tets: np.ndarray, k: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Each point's tetrahedron (the one containing it, else the nearest of the k by centroid) and
    barycentric weights (clamped to >= 0, summing to 1)."""
    from scipy.spatial import cKDTree

    x = nodes[tets]
    centroids = x.mean(axis=1)
    _, cand = cKDTree(centroids).query(points, k=min(k, len(tets)))
    dm = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)
    inv = np.linalg.inv(dm)
    rel = points[:, None, :] - x[cand, 0]
    l123 = np.einsum("pkij,pkj->pki", inv[cand], rel)
    bary = np.concatenate([1.0 - l123.sum(axis=2, keepdims=True), l123], axis=2)
    best = bary.min(axis=2).argmax(axis=1)
    rows = np.arange(len(points))
    b = np.clip(bary[rows, best], 0.0, None)
    return cand[rows, best].astype(np.int32), b / b.sum(axis=1, keepdims=True)


def build_flesh_mesh(body, *, edge: float = 0.025, quiet: bool = True) -> FleshMesh:
    """Tetrahedralize ``body``'s template (module doc) with ``edge`` [m] at the skin. CPU, minutes."""
    from simgen.body.surface import project_to_surface

    if not (0.005 <= edge <= 0.1):
        raise InputError(f"flesh mesh edge must be in [0.005, 0.1] m, got {edge!r}")
    v, f = np.asarray(body.v_template, dtype=np.float64), np.asarray(body.faces)
    nodes, tets = _tetrahedralize(v, f, edge, quiet)
    nodes = np.asarray(nodes, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    x = nodes[tets]
    det = np.linalg.det(np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2))
    tets[det < 0] = tets[det < 0][:, [1, 0, 2, 3]]
    boundary = _boundary_nodes(tets, len(nodes))
    proj = project_to_surface(nodes[boundary], v, f)
    corners = f[proj.face]
    B = body.num_betas
    attrs = np.concatenate([body.shapedirs.reshape(len(v), 3 * B), body.weights], axis=1)      # (V, 3B + 24)
    on_skin = np.einsum("pk,pkc->pc", proj.bary, attrs[corners])
    values = np.zeros((len(nodes), attrs.shape[1]))
    values[boundary] = on_skin
    values = _harmonic(tets, boundary, values)
    shapedirs = values[:, :3 * B].reshape(len(nodes), 3, B)
    weights = np.clip(values[:, 3 * B:], 0.0, None)
    weights /= weights.sum(axis=1, keepdims=True)
    region = tet_regions(nodes, tets, weights, body.rest_joints()[0])
    skin_tet, skin_bary = _embed(v, nodes, tets)
    return FleshMesh(nodes=nodes, tets=tets.astype(np.int32), shapedirs=shapedirs, weights=weights, region=region,
                     skin_tet=skin_tet, skin_bary=skin_bary, boundary=boundary, body_hash=body.hash)
