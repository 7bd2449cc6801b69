"""SMPL-format forward pass on a Warp device, for the cloth solver (float32).

:class:`WarpBody` preallocates every device array for ``max_batch`` instances when it is built, so
the per-substep path, :meth:`WarpBody.pose_from_quats`, only launches kernels: no allocation, no
host transfer, safe inside a captured CUDA graph. The stages (shape blend, joint regression,
forward kinematics, pose correctives, skinning) are separate kernels in
``simgen.body._warp_kernels`` and separate methods here, so a solver can run only what changes.

Quaternion layout: Warp's ``wp.quat`` is (x, y, z, w), while ``simgen.rotations`` uses (w, x, y, z).
Every quaternion passed to or returned by this module is in Warp's (x, y, z, w) order;
:func:`quats_from_simgen` converts a (w, x, y, z) numpy array.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from simgen.body import _warp_kernels as K
from simgen.body.model import NUM_JOINTS, BodyModel
from simgen.errors import InputError
from simgen.rotations import axis_angle_to_quat

__all__ = ["WarpBody", "quats_from_simgen"]


def quats_from_simgen(quat_wxyz: np.ndarray) -> np.ndarray:
    """simgen's (w, x, y, z) quaternions, shape (..., 4) -> Warp's (x, y, z, w) order, float32 (..., 4)."""
    q = np.asarray(quat_wxyz)
    return np.ascontiguousarray(np.concatenate([q[..., 1:], q[..., :1]], axis=-1), dtype=np.float32)


class WarpBody:
    """A body model whose forward pass runs on a Warp device for up to ``max_batch`` instances.

    Device arrays (float32; N is the instance count of the last :meth:`set_shape`):
      shaped_vertices [m] (N, V) vec3; rest_joints [m] (N, 24) vec3 -- from :meth:`set_shape`.
      vertices [m] (N, V) vec3 and vertices_flat (N*V,) vec3 (the same memory, instance-major, for a
      ``wp.Mesh``); joints [m] (N, 24) vec3; transforms (N, 24) mat44 -- from :meth:`pose_from_quats`.
      faces (F*3,) int32 for one body; batched_faces (N*F*3,) int32 indexing vertices_flat.
    The properties return views of preallocated arrays: their memory never moves, so a ``wp.Mesh``
    built on ``vertices_flat`` can be refit after every call.
    """

    def __init__(self, model: BodyModel, max_batch: int, device=None):
        if int(max_batch) < 1:
            raise ValueError(f"max_batch must be at least 1, got {max_batch}")
        self.model = model
        self.max_batch = int(max_batch)
        self.device = wp.get_device(device)
        V, B, P = model.num_vertices, model.num_betas, int(model.posedirs.shape[2])
        self.num_vertices = V
        self.num_betas = B
        self.use_pose_correctives = model.has_pose_correctives
        dev = self.device

        def f32(a: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(a, dtype=np.float32)

        # Model constants. Blendshapes are laid out component-major, (B, V) and (P, V) of vec3, so the
        # threads of neighbouring vertices read neighbouring memory at each step of their loop. A model
        # without shape components gets one zero row (Warp arrays need a nonzero extent).
        shapedirs = np.zeros((max(B, 1), V, 3), dtype=np.float32)
        shapedirs[:B] = np.moveaxis(model.shapedirs, 2, 0)
        self._v_template = wp.array(f32(model.v_template), dtype=wp.vec3, device=dev)
        self._shapedirs = wp.array(shapedirs, dtype=wp.vec3, device=dev)
        if self.use_pose_correctives:
            self._posedirs = wp.array(f32(np.moveaxis(model.posedirs, 2, 0)), dtype=wp.vec3, device=dev)
        self._parents = wp.array(model.parents.astype(np.int32), dtype=wp.int32, device=dev)

        # Joint regressor in CSR form (SMPL's has ~1% nonzeros).
        rows, cols = np.nonzero(model.J_regressor)
        row_start = np.searchsorted(rows, np.arange(NUM_JOINTS + 1)).astype(np.int32)
        self._regressor_row_start = wp.array(row_start, dtype=wp.int32, device=dev)
        self._regressor_vertex = wp.array(cols.astype(np.int32), dtype=wp.int32, device=dev)
        self._regressor_weight = wp.array(f32(model.J_regressor[rows, cols]), dtype=wp.float32, device=dev)

        # Skinning influences: every nonzero weight of a vertex, padded to the largest count with weight 0.
        nonzero = model.weights != 0.0
        k_max = max(int(nonzero.sum(axis=1).max()), 1)
        order = np.argsort(~nonzero, axis=1, kind="stable")[:, :k_max]  # nonzero joints first
        influence_weight = np.take_along_axis(model.weights, order, axis=1)
        self._influence_joint = wp.array(order.astype(np.int32), dtype=wp.int32, device=dev)
        self._influence_weight = wp.array(f32(influence_weight), dtype=wp.float32, device=dev)
        self.influences_per_vertex = k_max

        # Per-instance state, allocated once for max_batch.
        M = self.max_batch
        self._betas = wp.zeros((M, max(B, 1)), dtype=wp.float32, device=dev)
        self._quats = wp.zeros((M, NUM_JOINTS), dtype=wp.quat, device=dev)
        self._trans = wp.zeros(M, dtype=wp.vec3, device=dev)
        self._v_shaped = wp.zeros((M, V), dtype=wp.vec3, device=dev)
        self._rest_joints = wp.zeros((M, NUM_JOINTS), dtype=wp.vec3, device=dev)
        self._global_rotation = wp.zeros((M, NUM_JOINTS), dtype=wp.quat, device=dev)
        self._global_position = wp.zeros((M, NUM_JOINTS), dtype=wp.vec3, device=dev)
        self._transforms = wp.zeros((M, NUM_JOINTS), dtype=wp.mat44, device=dev)
        self._joints = wp.zeros((M, NUM_JOINTS), dtype=wp.vec3, device=dev)
        self._pose_feature = wp.zeros((M, max(P, 1)), dtype=wp.float32, device=dev)
        self._v_posed = wp.zeros((M, V), dtype=wp.vec3, device=dev) if self.use_pose_correctives else self._v_shaped
        self._vertices_flat_all = wp.zeros(M * V, dtype=wp.vec3, device=dev)
        self._vertices = self._vertices_flat_all.reshape((M, V))

        faces = model.faces.astype(np.int32)
        offsets = (np.arange(M, dtype=np.int32) * V)[:, None, None]
        self._faces = wp.array(faces.reshape(-1), dtype=wp.int32, device=dev)
        self._batched_faces_all = wp.array((faces[None] + offsets).reshape(-1), dtype=wp.int32, device=dev)
        self.num_faces = int(faces.shape[0])

        # Host staging for numpy inputs: pinned host memory next to a GPU, the device arrays themselves
        # on the CPU (their .numpy() is a zero-copy view there).
        self._staging = {}
        for name in ("betas", "quats", "trans"):
            target = getattr(self, "_" + name)
            self._staging[name] = target if dev.is_cpu else wp.zeros(target.shape, dtype=target.dtype, device="cpu",
                                                                     pinned=True)

        self._num_instances = 0
        self._views: dict[tuple[str, int], wp.array] = {}
        self.set_shape(np.zeros((1, B)))

    # ------------------------------------------------------------------ views of the outputs
    def _view(self, name: str, n: int) -> wp.array:
        """A view of the first n instances of a preallocated array, cached so repeated calls are free."""
        key = (name, n)
        view = self._views.get(key)
        if view is None:
            if name == "vertices_flat":
                view = self._vertices_flat_all[: n * self.num_vertices]
            elif name == "batched_faces":
                view = self._batched_faces_all[: n * self.num_faces * 3]
            else:
                view = getattr(self, "_" + name)[:n]
            self._views[key] = view
        return view

    @property
    def num_instances(self) -> int:
        """N, the number of instances shaped by the last :meth:`set_shape`."""
        return self._num_instances

    @property
    def shaped_vertices(self) -> wp.array:
        """Rest-pose shaped vertices [m], shape (N, V) of vec3."""
        return self._view("v_shaped", self._num_instances)

    @property
    def rest_joints(self) -> wp.array:
        """Rest-pose joints [m], shape (N, 24) of vec3."""
        return self._view("rest_joints", self._num_instances)

    @property
    def vertices(self) -> wp.array:
        """Posed vertices [m], shape (N, V) of vec3."""
        return self._view("vertices", self._num_instances)

    @property
    def vertices_flat(self) -> wp.array:
        """Posed vertices [m], shape (N*V,) of vec3 (instance n at rows n*V..(n+1)*V-1), for a wp.Mesh."""
        return self._view("vertices_flat", self._num_instances)

    @property
    def faces(self) -> wp.array:
        """Triangles of one body as flat int32 vertex indices, shape (F*3,)."""
        return self._faces

    @property
    def batched_faces(self) -> wp.array:
        """Triangles of all N bodies as flat int32 indices into :attr:`vertices_flat`, shape (N*F*3,)."""
        return self._view("batched_faces", self._num_instances)

    @property
    def joints(self) -> wp.array:
        """Posed joints [m] (trans included), shape (N, 24) of vec3."""
        return self._view("joints", self._num_instances)

    @property
    def transforms(self) -> wp.array:
        """Skinning transforms, shape (N, 24) of mat44 (see :class:`simgen.body.model.BodyOutput`)."""
        return self._view("transforms", self._num_instances)

    # ------------------------------------------------------------------ input handling
    def _check_count(self, n: int, what: str) -> int:
        if not 1 <= n <= self.max_batch:
            raise ValueError(f"{what} has {n} instances but this WarpBody holds 1..{self.max_batch} (max_batch)")
        return n

    def _check_warp_array(self, array: wp.array, dtype, ndim: int, what: str) -> None:
        if array.dtype != dtype or array.ndim != ndim:
            raise ValueError(f"{what} must be a {ndim}-d Warp array of {dtype.__name__}, got {array.ndim}-d "
                             f"of {getattr(array.dtype, '__name__', array.dtype)}")
        if array.device != self.device:
            raise ValueError(f"{what} is on {array.device} but this WarpBody runs on {self.device}")

    def _upload(self, name: str, values: np.ndarray) -> wp.array:
        """Copy host values (float32-convertible, leading dim n) into the first n rows of a device buffer."""
        n = values.shape[0]
        staging = self._staging[name]
        target = getattr(self, "_" + name)
        if staging is target:
            target.numpy()[:n] = values
        else:
            # The previous upload may still be reading the pinned buffer on the device's stream.
            wp.synchronize_device(self.device)
            staging.numpy()[:n] = values
            row_size = int(np.prod(target.shape[1:])) if target.ndim > 1 else 1
            wp.copy(target, staging, count=n * row_size)
        return self._view(name, n)

    # ------------------------------------------------------------------ stages
    def set_shape(self, betas, num_instances: int | None = None) -> None:
        """Shape N instances: betas (N, B') or (B',) with B' <= B (missing components are zero).

        betas: numpy (float, validated like BodyModel.check_betas) or a Warp float32 array (N, B')
        on this device (used as is, no copy). num_instances: give a single row of betas to that many
        instances (default: one instance per row). Recomputes the shaped rest vertices and rest
        joints; N becomes the instance count that :meth:`pose_from_quats` expects.
        """
        if isinstance(betas, wp.array):
            self._check_warp_array(betas, wp.float32, 2, "betas")
            if betas.shape[1] > self.num_betas:
                raise InputError(f"betas has {betas.shape[1]} values but body model {self.model.name!r} has "
                                 f"{self.num_betas} shape components")
            rows = betas.shape[0]
        else:
            betas = self.model.check_betas(betas)
            rows = betas.shape[0]
        n = self._check_count(rows if num_instances is None else int(num_instances), "betas")
        if rows not in (1, n):
            raise InputError(f"betas has {rows} rows for {n} instances")
        if not isinstance(betas, wp.array):
            # One uploaded row serves every instance: the kernel reads row min(n, rows - 1).
            betas = self._upload("betas", betas if self.num_betas > 0 else np.zeros((rows, 1)))
        self.shape_blend(betas, n)
        self.regress_joints(n)
        self._num_instances = n

    def shape_blend(self, betas: wp.array, num_instances: int) -> None:
        """Stage 1: shaped_vertices of the first num_instances from device betas (N or 1, B'), float32."""
        wp.launch(K.shape_blend_kernel, dim=(num_instances, self.num_vertices),
                  inputs=[self._v_template, self._shapedirs, betas], outputs=[self._v_shaped], device=self.device)

    def regress_joints(self, num_instances: int) -> None:
        """Stage 2: rest_joints of the first num_instances from their shaped vertices."""
        wp.launch(K.joint_regression_kernel, dim=(num_instances, NUM_JOINTS),
                  inputs=[self._regressor_row_start, self._regressor_vertex, self._regressor_weight, self._v_shaped],
                  outputs=[self._rest_joints], device=self.device)

    def forward_kinematics(self, quats: wp.array, trans: wp.array) -> None:
        """Stage 3: transforms, posed joints and (with correctives) pose features for N instances.

        quats: (N, 24) wp.quat, (x, y, z, w), local joint rotations (normalised in the kernel);
        trans [m]: (N,) vec3.
        """
        n = quats.shape[0]
        wp.launch(K.forward_kinematics_kernel, dim=n,
                  inputs=[quats, self._rest_joints, trans, self._parents, int(self.use_pose_correctives)],
                  outputs=[self._global_rotation, self._global_position, self._transforms, self._joints,
                           self._pose_feature],
                  device=self.device)

    def pose_correctives(self, num_instances: int) -> None:
        """Stage 4 (models with pose correctives only): v_posed = v_shaped + posedirs . pose_feature."""
        if self.use_pose_correctives:
            wp.launch(K.pose_corrective_kernel, dim=(num_instances, self.num_vertices),
                      inputs=[self._v_shaped, self._posedirs, self._pose_feature], outputs=[self._v_posed],
                      device=self.device)

    def skin(self, num_instances: int) -> None:
        """Stage 5: linear blend skinning of the first num_instances into :attr:`vertices`."""
        wp.launch(K.skinning_kernel, dim=(num_instances, self.num_vertices),
                  inputs=[self._v_posed, self._transforms, self._influence_joint, self._influence_weight],
                  outputs=[self._vertices], device=self.device)

    # ------------------------------------------------------------------ the two entry points
    def pose_from_quats(self, quats: wp.array, trans: wp.array) -> wp.array:
        """Per-substep path: pose the N shaped instances. Launches kernels only (graph-capturable).

        quats: wp.array (N, 24) of wp.quat, local joint rotations in Warp's (x, y, z, w) order (need not
        be exactly unit, e.g. slerped); trans [m]: wp.array (N,) of vec3; N = :attr:`num_instances`.
        Returns :attr:`vertices` [m], (N, V) vec3; :attr:`joints` and :attr:`transforms` are updated too.
        """
        self._check_warp_array(quats, wp.quat, 2, "quats")
        self._check_warp_array(trans, wp.vec3, 1, "trans")
        n = quats.shape[0]
        if quats.shape[1] != NUM_JOINTS or n != self._num_instances or trans.shape[0] != n:
            raise ValueError(f"quats must have shape ({self._num_instances}, 24) and trans ({self._num_instances},) "
                             f"to match the shaped instances, got {quats.shape} and {trans.shape}")
        self.forward_kinematics(quats, trans)
        self.pose_correctives(n)
        self.skin(n)
        return self.vertices

    def forward(self, betas=None, pose=None, trans=None) -> tuple[wp.array, wp.array, wp.array]:
        """Convenience forward pass with BodyModel.forward's semantics.

        betas (N, B') or (B',) (a batch of 1 serves every instance); pose axis-angle [rad] (N, 24, 3)
        or (N, 72); trans [m] (N, 3). Each is numpy or, already on this device, a Warp array: betas
        float32 (N, B'), pose (N, 24) vec3, trans (N,) vec3. None is zero.
        Returns Warp arrays (vertices [m] (N, V) vec3, joints [m] (N, 24) vec3, transforms (N, 24) mat44),
        views that the next call overwrites.
        """
        n = 1
        if pose is not None and not isinstance(pose, wp.array):
            pose = np.asarray(pose, dtype=np.float64)
            if pose.ndim == 2 and pose.shape[1] == NUM_JOINTS * 3:
                pose = pose.reshape(-1, NUM_JOINTS, 3)
            elif pose.ndim == 2:
                pose = pose[None]
            if pose.ndim != 3 or pose.shape[1:] != (NUM_JOINTS, 3):
                raise InputError(f"pose must have shape (N, 24, 3), got {pose.shape}")
            if not np.all(np.isfinite(pose)):
                raise InputError("pose contains NaN or inf")
        if trans is not None and not isinstance(trans, wp.array):
            trans = np.asarray(trans, dtype=np.float64).reshape(-1, 3)
            if not np.all(np.isfinite(trans)):
                raise InputError("trans contains NaN or inf")
        for x in (pose, trans):
            if x is not None:
                n = max(n, x.shape[0])
        if betas is not None and not isinstance(betas, wp.array):
            betas = self.model.check_betas(betas)
        if betas is not None:
            n = max(n, betas.shape[0])
        self._check_count(n, "forward")
        for label, x in (("betas", betas), ("pose", pose), ("trans", trans)):
            if x is not None and x.shape[0] not in (1, n):
                raise InputError(f"{label} has batch size {x.shape[0]} but another argument has {n}")

        self.set_shape(np.zeros((1, self.num_betas)) if betas is None else betas, num_instances=n)

        if isinstance(pose, wp.array):
            self._check_warp_array(pose, wp.vec3, 2, "pose")
            if pose.shape != (n, NUM_JOINTS):
                raise ValueError(f"pose must have shape ({n}, 24) of vec3, got {pose.shape}")
            wp.launch(K.axis_angle_to_quat_kernel, dim=(n, NUM_JOINTS), inputs=[pose], outputs=[self._quats],
                      device=self.device)
            quats = self._view("quats", n)
        else:
            pose = np.zeros((1, NUM_JOINTS, 3)) if pose is None else pose
            quats_xyzw = quats_from_simgen(axis_angle_to_quat(np.broadcast_to(pose, (n, NUM_JOINTS, 3))))
            quats = self._upload("quats", quats_xyzw)

        if isinstance(trans, wp.array):
            self._check_warp_array(trans, wp.vec3, 1, "trans")
            if trans.shape[0] != n:
                raise ValueError(f"trans must have shape ({n},) of vec3, got {trans.shape}")
            device_trans = trans
        else:
            trans = np.zeros((1, 3)) if trans is None else trans
            device_trans = self._upload("trans", np.broadcast_to(trans, (n, 3)))

        self.pose_from_quats(quats, device_trans)
        return self.vertices, self.joints, self.transforms
