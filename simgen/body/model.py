"""The SMPL-format body model and its numpy reference forward pass.

One class serves every body (the bundled open default and real SMPL files). Arrays follow SMPL's
names and layout; units are metres, Y-up. The numpy forward here is the reference that the torch
(``simgen.body.torch_lbs``) and Warp (``simgen.body.warp_lbs``) versions are tested against.
"""

from __future__ import annotations

import functools

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from simgen.errors import InputError
from simgen.rotations import axis_angle_to_matrix

__all__ = ["BodyModel", "BodyOutput", "SMPL_JOINT_NAMES", "SMPL_PARENTS", "NUM_JOINTS", "skinning_transforms"]

NUM_JOINTS = 24

SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hand", "right_hand",
)

SMPL_PARENTS = np.array([-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21],
                        dtype=np.int64)


@dataclass
class BodyOutput:
    """Result of a body forward pass (numpy, float64).

    vertices [m], shape (N, V, 3); joints [m], shape (N, 24, 3) (posed joint positions, trans
    included); transforms, shape (N, 24, 4, 4): the skinning transform of each joint, which maps a
    point of the shaped rest body attached rigidly to that joint to its posed world position (trans
    included), so posed vertex = sum_j weights[v, j] * transforms[j] @ (v_shaped + pose correctives).
    """

    vertices: np.ndarray
    joints: np.ndarray
    transforms: np.ndarray


@dataclass(eq=False)
class BodyModel:
    """An SMPL-format body model.

    Arrays (float64 unless stated):
      v_template [m], shape (V, 3): rest-pose template vertices (Y-up; the open body stands on y = 0).
      shapedirs [m], shape (V, 3, B): shape blendshapes; betas ~ N(0, 1).
      posedirs [m], shape (V, 3, P): pose corrective blendshapes over P = 207 pose features
        (R_j - I for joints 1..23, row-major), or P = 0 when the model has none.
      J_regressor, shape (24, V): rest joints = J_regressor @ v_shaped.
      weights, shape (V, 24): linear blend skinning weights, rows summing to 1.
      parents, int64 shape (24,): kinematic tree, parents[0] = -1.
      faces, int64 shape (F, 3): triangles, counter-clockwise seen from outside.
    name: short identifier ("open", "smpl_female", ...); meta: provenance (source, licence, ...).
    """

    v_template: np.ndarray
    shapedirs: np.ndarray
    posedirs: np.ndarray
    J_regressor: np.ndarray
    weights: np.ndarray
    parents: np.ndarray
    faces: np.ndarray
    name: str = "custom"
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.v_template = np.ascontiguousarray(self.v_template, dtype=np.float64)
        self.shapedirs = np.ascontiguousarray(self.shapedirs, dtype=np.float64)
        self.posedirs = np.ascontiguousarray(self.posedirs, dtype=np.float64)
        self.J_regressor = np.ascontiguousarray(self.J_regressor, dtype=np.float64)
        self.weights = np.ascontiguousarray(self.weights, dtype=np.float64)
        self.parents = np.ascontiguousarray(self.parents, dtype=np.int64).reshape(-1)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64)
        self._validate()
        self._hash: str | None = None

    # ------------------------------------------------------------------ validation and identity
    def _validate(self) -> None:
        where = f"body model {self.name!r}"
        V = self.v_template.shape[0] if self.v_template.ndim == 2 else -1
        if self.v_template.ndim != 2 or self.v_template.shape[1] != 3 or V < 4:
            raise InputError(f"{where}: field 'v_template' must have shape (V, 3), got {self.v_template.shape}")
        if self.shapedirs.ndim != 3 or self.shapedirs.shape[:2] != (V, 3):
            raise InputError(f"{where}: field 'shapedirs' must have shape ({V}, 3, B), got {self.shapedirs.shape}")
        if self.posedirs.ndim != 3 or self.posedirs.shape[:2] != (V, 3) or self.posedirs.shape[2] not in (0, 207):
            raise InputError(f"{where}: field 'posedirs' must have shape ({V}, 3, 207) or ({V}, 3, 0), "
                             f"got {self.posedirs.shape}")
        if self.J_regressor.shape != (NUM_JOINTS, V):
            raise InputError(f"{where}: field 'J_regressor' must have shape (24, {V}), got {self.J_regressor.shape}")
        if self.weights.shape != (V, NUM_JOINTS):
            raise InputError(f"{where}: field 'weights' must have shape ({V}, 24), got {self.weights.shape}")
        if self.parents.shape != (NUM_JOINTS,) or self.parents[0] != -1 or np.any(
            self.parents[1:] >= np.arange(1, NUM_JOINTS)) or np.any(self.parents[1:] < 0):
            raise InputError(f"{where}: field 'parents' must list 24 parents with parents[0] = -1 and each parent "
                             f"before its child, got {self.parents.tolist()}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or self.faces.shape[0] < 1:
            raise InputError(f"{where}: field 'faces' must have shape (F, 3), got {self.faces.shape}")
        if self.faces.min() < 0 or self.faces.max() >= V:
            raise InputError(f"{where}: field 'faces' indexes vertex {int(self.faces.max())} but there are {V}")
        for fname in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights"):
            if not np.all(np.isfinite(getattr(self, fname))):
                raise InputError(f"{where}: field {fname!r} contains NaN or inf")

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_betas(self) -> int:
        return int(self.shapedirs.shape[2])

    @property
    def has_pose_correctives(self) -> bool:
        return self.posedirs.shape[2] > 0 and bool(np.any(self.posedirs != 0.0))

    @property
    def hash(self) -> str:
        """SHA-256 (hex) of the model arrays as float32/int32 bytes: identifies the body in stores and assets."""
        if self._hash is None:
            h = hashlib.sha256()
            for a in (self.v_template, self.shapedirs, self.posedirs, self.J_regressor, self.weights):
                h.update(np.ascontiguousarray(a, dtype=np.float32).tobytes())
            for a in (self.parents, self.faces):
                h.update(np.ascontiguousarray(a, dtype=np.int32).tobytes())
            self._hash = h.hexdigest()
        return self._hash

    @property
    def model_id(self) -> str:
        """Folder-safe identifier "<name>-<first 12 hex of hash>" (used under SIMGEN_HOME)."""
        return f"{self.name}-{self.hash[:12]}"

    # ------------------------------------------------------------------ argument checking
    def check_betas(self, betas, batch: int | None = None) -> np.ndarray:
        """Validate betas and return them as float64 (N, B), zero-padding a shorter vector.

        betas: shape (B',) or (N, B') with B' <= B. More components than the model has is an error.
        """
        b = np.asarray(betas, dtype=np.float64)
        if b.ndim == 1:
            b = b[None]
        if b.ndim != 2:
            raise InputError(f"betas must have shape (B,) or (N, B), got {b.shape}")
        if b.shape[1] > self.num_betas:
            raise InputError(f"betas has {b.shape[1]} values but body model {self.name!r} has {self.num_betas} "
                             f"shape components")
        if not np.all(np.isfinite(b)):
            raise InputError("betas contains NaN or inf")
        if b.shape[1] < self.num_betas:
            b = np.concatenate([b, np.zeros((b.shape[0], self.num_betas - b.shape[1]))], axis=1)
        if batch is not None and b.shape[0] == 1 and batch > 1:
            b = np.repeat(b, batch, axis=0)
        return b

    # ------------------------------------------------------------------ forward (numpy reference)
    def shaped_vertices(self, betas) -> np.ndarray:
        """Rest-pose vertices for shapes: betas (N, B') -> v_shaped [m], shape (N, V, 3)."""
        b = self.check_betas(betas)
        return self.v_template[None] + np.einsum("vcb,nb->nvc", self.shapedirs, b)

    def rest_joints(self, betas=None) -> np.ndarray:
        """Rest-pose joint positions [m], shape (N, 24, 3) (N = 1 when betas is None)."""
        if betas is None:
            betas = np.zeros((1, self.num_betas))
        return np.einsum("jv,nvc->njc", self.J_regressor, self.shaped_vertices(betas))

    def forward(self, betas=None, pose=None, trans=None) -> BodyOutput:
        """Posed bodies: betas (N, B') or (B',), pose axis-angle [rad] (N, 24, 3), trans [m] (N, 3).

        Any argument left None is zero; N is taken from the arguments given (betas broadcasts).
        Returns a :class:`BodyOutput` of float64 arrays.
        """
        n = 1
        if pose is not None:
            pose = np.asarray(pose, dtype=np.float64)
            if pose.ndim == 2:
                pose = pose[None]
            if pose.ndim != 3 or pose.shape[1:] != (NUM_JOINTS, 3):
                raise InputError(f"pose must have shape (N, 24, 3), got {pose.shape}")
            n = pose.shape[0]
        if trans is not None:
            trans = np.asarray(trans, dtype=np.float64).reshape(-1, 3)
            n = max(n, trans.shape[0])
        b = self.check_betas(np.zeros(self.num_betas) if betas is None else betas, batch=n)
        n = b.shape[0]
        for label, given in (("pose", pose), ("trans", trans)):
            if given is not None and given.shape[0] not in (1, n):
                raise InputError(f"{label} has batch size {given.shape[0]} but betas has {n}")
        pose = np.zeros((n, NUM_JOINTS, 3)) if pose is None else np.broadcast_to(pose, (n, NUM_JOINTS, 3))
        trans = np.zeros((n, 3)) if trans is None else np.broadcast_to(trans, (n, 3))

        v_shaped = self.v_template[None] + np.einsum("vcb,nb->nvc", self.shapedirs, b)
        J = np.einsum("jv,nvc->njc", self.J_regressor, v_shaped)  # (N, 24, 3)
        R = axis_angle_to_matrix(pose)  # (N, 24, 3, 3)
        v_posed = v_shaped
        if self.posedirs.shape[2] > 0:
            pose_feature = (R[:, 1:] - np.eye(3)).reshape(n, -1)  # (N, 207)
            v_posed = v_shaped + np.einsum("vcp,np->nvc", self.posedirs, pose_feature)

        G = np.zeros((n, NUM_JOINTS, 4, 4))
        G[:, :, 3, 3] = 1.0
        G[:, 0, :3, :3] = R[:, 0]
        G[:, 0, :3, 3] = J[:, 0]
        for j in range(1, NUM_JOINTS):
            p = self.parents[j]
            local = np.zeros((n, 4, 4))
            local[:, :3, :3] = R[:, j]
            local[:, :3, 3] = J[:, j] - J[:, p]
            local[:, 3, 3] = 1.0
            G[:, j] = G[:, p] @ local
        joints = G[:, :, :3, 3] + trans[:, None]
        A = G.copy()
        A[:, :, :3, 3] = G[:, :, :3, 3] - np.einsum("njab,njb->nja", G[:, :, :3, :3], J) + trans[:, None]

        T = np.einsum("vj,njab->nvab", self.weights, A)  # (N, V, 4, 4)
        verts = np.einsum("nvab,nvb->nva", T[:, :, :3, :3], v_posed) + T[:, :, :3, 3]
        return BodyOutput(vertices=verts, joints=joints, transforms=A)

    __call__ = forward

    def forward_sequence(self, betas, poses, trans, *, chunk: int = 32, progress=None) -> BodyOutput:
        """Pose one body over a whole clip, in chunks of frames to bound memory.

        betas (B',) or (T, B'); poses [rad] (T, 24, 3); trans [m] (T, 3). progress: optional
        callable(frames_done, frames_total). Returns vertices (T, V, 3) and joints (T, 24, 3) as
        float32, transforms (T, 24, 4, 4) float64.
        """
        poses = np.asarray(poses, dtype=np.float64)
        trans = np.asarray(trans, dtype=np.float64)
        T = poses.shape[0]
        b = self.check_betas(betas, batch=T)
        if b.shape[0] != T:
            raise InputError(f"betas has {b.shape[0]} rows but the sequence has {T} frames")
        verts = np.empty((T, self.num_vertices, 3), dtype=np.float32)
        joints = np.empty((T, NUM_JOINTS, 3), dtype=np.float32)
        transforms = np.empty((T, NUM_JOINTS, 4, 4))
        for start in range(0, T, chunk):
            sl = slice(start, min(start + chunk, T))
            out = self.forward(b[sl], poses[sl], trans[sl])
            verts[sl], joints[sl], transforms[sl] = out.vertices, out.joints, out.transforms
            if progress is not None:
                progress(sl.stop, T)
        return BodyOutput(vertices=verts, joints=joints, transforms=transforms)

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> Path:
        """Write the model as a compressed .npz (float32 arrays, sparse J_regressor) readable by ``load``."""
        import json

        path = Path(path)
        nz = np.nonzero(self.J_regressor)
        np.savez_compressed(
            path,
            v_template=self.v_template.astype(np.float32),
            shapedirs=self.shapedirs.astype(np.float32),
            posedirs=self.posedirs.astype(np.float32),
            J_regressor_rows=nz[0].astype(np.int32),
            J_regressor_cols=nz[1].astype(np.int32),
            J_regressor_vals=self.J_regressor[nz].astype(np.float64),
            weights=self.weights.astype(np.float32),
            kintree_table=np.stack([self.parents, np.arange(NUM_JOINTS)]).astype(np.int64),
            f=self.faces.astype(np.int32),
            simgen_name=np.array(self.name),
            simgen_meta=np.array(json.dumps(self.meta)),
        )
        return path


@functools.lru_cache(maxsize=4)
def _joint_regression(body) -> tuple[np.ndarray, np.ndarray]:
    """Rest joints of the template body (24, 3) and their shape directions (24, 3, B)."""
    J0 = body.J_regressor @ body.v_template
    JS = np.einsum("jv,vcb->jcb", body.J_regressor, body.shapedirs)
    return J0, JS


def skinning_transforms(body, betas, poses, trans) -> np.ndarray:
    """The body's joint skinning transforms A(beta, theta) of every frame (the W of the thesis's eqs.
    3.2, 4.3, 4.5).

    body: :class:`simgen.body.BodyModel`; betas (T, B') or (B',) (missing components zero);
    poses [rad] axis-angle (T, 24, 3); trans [m] (T, 3). Returns (T, 24, 4, 4) float64: joint j
    maps a point of the shaped rest body to its posed world position, root translation included
    (the same as ``body.forward(...).transforms``, computed from the joints only: no vertices).
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim == 2:
        poses = poses[None]
    if poses.ndim != 3 or poses.shape[1:] != (NUM_JOINTS, 3):
        raise InputError(f"poses must have shape (T, 24, 3), got {poses.shape}")
    n = len(poses)
    trans = np.asarray(trans, dtype=np.float64).reshape(-1, 3)
    if len(trans) not in (1, n):
        raise InputError(f"trans has {len(trans)} rows but poses has {n} frames")
    trans = np.broadcast_to(trans, (n, 3))
    b = body.check_betas(betas, batch=n)
    if len(b) != n:
        raise InputError(f"betas has {len(b)} rows but poses has {n} frames")
    J0, JS = _joint_regression(body)
    J = J0[None] + np.einsum("jcb,nb->njc", JS, b)
    R = axis_angle_to_matrix(poses)
    G = np.zeros((n, NUM_JOINTS, 4, 4))
    G[:, :, 3, 3] = 1.0
    G[:, 0, :3, :3] = R[:, 0]
    G[:, 0, :3, 3] = J[:, 0]
    parents = body.parents
    for j in range(1, NUM_JOINTS):
        p = parents[j]
        local = np.zeros((n, 4, 4))
        local[:, :3, :3] = R[:, j]
        local[:, :3, 3] = J[:, j] - J[:, p]
        local[:, 3, 3] = 1.0
        G[:, j] = G[:, p] @ local
    A = G.copy()
    A[:, :, :3, 3] = G[:, :, :3, 3] - np.einsum("njab,njb->nja", G[:, :, :3, :3], J) + trans[:, None]
    return A
