"""Differentiable SMPL-format forward pass in PyTorch.

:class:`TorchBody` computes exactly what :meth:`simgen.body.model.BodyModel.forward` computes (shape
blendshapes, joint regression, pose correctives when the model has them, forward kinematics,
linear blend skinning), batched and differentiable with respect to betas, pose and trans. It is
what the learning code (garment fit, SNUG losses, SoftSMPL) puts inside its graphs.
"""

from __future__ import annotations

import numpy as np
import torch

from simgen.body.model import NUM_JOINTS, BodyModel
from simgen.errors import InputError

__all__ = ["axis_angle_to_matrix_torch", "TorchBody"]

# Below this squared angle [rad^2] the Rodrigues coefficients come from their Taylor series. The
# closed forms lose precision there (and their gradients divide by ~0); the series truncated after
# the theta^4 term is exact to ~1e-13 at the threshold, below float64 round-off of the closed form.
_SERIES_THRESHOLD_SQ = 1e-3


def _depth_levels(parents) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """A kinematic tree by depth. parents (J,) with parents[0] = -1 (every parent before its child)
    -> (nodes (J,): the joints ordered by depth, stable; parent_slot (J,): per entry of nodes the
    position of its parent among the level above (0 for the root); bounds: the levels' start
    indices into nodes, and J)."""
    parents = np.asarray(parents, dtype=np.int64)
    depth = np.zeros(len(parents), dtype=np.int64)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    nodes = np.argsort(depth, kind="stable")
    bounds = [0] + [int(np.searchsorted(depth[nodes], d, side="right")) for d in range(int(depth.max()) + 1)]
    position = np.empty(len(parents), dtype=np.int64)
    for s, e in zip(bounds[:-1], bounds[1:]):
        position[nodes[s:e]] = np.arange(e - s)
    parent_slot = np.where(nodes == 0, 0, position[np.maximum(parents[nodes], 0)])
    return nodes, parent_slot, bounds


def axis_angle_to_matrix_torch(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula with gradients that stay finite and exact at zero angle.

    axis_angle [rad], shape (..., 3) -> rotation matrices, shape (..., 3, 3).

    Writes R = I + a K + b K^2 with K the cross-product matrix of the (unnormalised) axis-angle
    vector, a = sin(t)/t and b = (1 - cos(t))/t^2 (t the angle). Both coefficients are smooth
    functions of t^2, evaluated from their series near zero, so no division by the angle happens
    where it vanishes and the rest pose (all zeros) has the correct derivative dR/daa = [e_i]_x.
    """
    theta_sq = (axis_angle * axis_angle).sum(dim=-1)
    small = theta_sq < _SERIES_THRESHOLD_SQ
    # The closed-form branch is evaluated everywhere by torch.where; feed it a harmless angle where
    # the series is used so that neither branch produces NaN gradients.
    safe_theta_sq = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    safe_theta = torch.sqrt(safe_theta_sq)
    a_closed = torch.sin(safe_theta) / safe_theta
    b_closed = (1.0 - torch.cos(safe_theta)) / safe_theta_sq
    a_series = 1.0 - theta_sq / 6.0 + theta_sq * theta_sq / 120.0
    b_series = 0.5 - theta_sq / 24.0 + theta_sq * theta_sq / 720.0
    a = torch.where(small, a_series, a_closed)[..., None, None]
    b = torch.where(small, b_series, b_closed)[..., None, None]

    x, y, z = axis_angle.unbind(dim=-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(axis_angle.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return eye + a * K + b * (K @ K)


class TorchBody(torch.nn.Module):
    """An SMPL-format body as a differentiable torch module.

    Built from a :class:`~simgen.body.model.BodyModel`; the model arrays are registered as buffers
    (they follow ``.to(device)`` and are saved in ``state_dict``), cast to ``dtype``.

    Buffers: v_template [m] (V, 3); shapedirs [m] (V, 3, B); posedirs [m] (V*3, P) (P = 0 when the
    model has no pose correctives); joint_template [m] (24, 3) and joint_shapedirs [m] (24, 3, B),
    the joint regressor already applied to the template and shape blendshapes (regression is
    linear, so regressing them once equals regressing every shaped body); weights (V, 24); faces
    (F, 3) int64; parents (24,) int64.
    """

    def __init__(self, model: BodyModel, dtype: torch.dtype = torch.float32, device=None):
        super().__init__()
        self.model_name = model.name
        self.num_vertices = model.num_vertices
        self.num_betas = model.num_betas
        self.num_pose_features = int(model.posedirs.shape[2])

        def buffer(array: np.ndarray, as_dtype=dtype) -> torch.Tensor:
            return torch.tensor(np.asarray(array), dtype=as_dtype, device=device)

        V = model.num_vertices
        self.register_buffer("v_template", buffer(model.v_template))
        self.register_buffer("shapedirs", buffer(model.shapedirs))
        self.register_buffer("posedirs", buffer(model.posedirs.reshape(V * 3, -1)))
        self.register_buffer("joint_template", buffer(model.J_regressor @ model.v_template))
        self.register_buffer("joint_shapedirs", buffer(np.einsum("jv,vcb->jcb", model.J_regressor, model.shapedirs)))
        self.register_buffer("weights", buffer(model.weights))
        self.register_buffer("faces", buffer(model.faces, torch.int64))
        self.register_buffer("parents", buffer(model.parents, torch.int64))
        # Forward kinematics by depth (:meth:`kinematics`): the joints in order of depth, each one's
        # parent as a position in the level above, the way back to joint order, the levels' bounds.
        nodes, parent_slot, self._fk_bounds = _depth_levels(model.parents)
        self.register_buffer("fk_nodes", buffer(nodes, torch.int64))
        self.register_buffer("fk_parent_slot", buffer(parent_slot, torch.int64))
        self.register_buffer("fk_joint_order", buffer(np.argsort(nodes), torch.int64))

    @property
    def dtype(self) -> torch.dtype:
        return self.v_template.dtype

    @property
    def device(self) -> torch.device:
        return self.v_template.device

    # ------------------------------------------------------------------ argument handling
    def _batch_inputs(self, betas, pose, trans) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Cast to the module's dtype/device and broadcast to a common batch size N."""

        def as_tensor(x):
            if x is None:
                return None
            if isinstance(x, torch.Tensor):
                return x.to(dtype=self.dtype, device=self.device)  # differentiable cast
            return torch.as_tensor(np.asarray(x), dtype=self.dtype, device=self.device)

        betas, pose, trans = as_tensor(betas), as_tensor(pose), as_tensor(trans)
        if pose is not None:
            if pose.dim() == 2 and pose.shape[-1] == NUM_JOINTS * 3:
                pose = pose.reshape(-1, NUM_JOINTS, 3)
            elif pose.dim() == 2:
                pose = pose[None]
            if pose.dim() != 3 or tuple(pose.shape[1:]) != (NUM_JOINTS, 3):
                raise InputError(f"pose must have shape (N, 24, 3), got {tuple(pose.shape)}")
        if betas is not None:
            if betas.dim() == 1:
                betas = betas[None]
            if betas.dim() != 2:
                raise InputError(f"betas must have shape (B,) or (N, B), got {tuple(betas.shape)}")
            if betas.shape[1] > self.num_betas:
                raise InputError(f"betas has {betas.shape[1]} values but body model {self.model_name!r} has "
                                 f"{self.num_betas} shape components")
        if trans is not None:
            trans = trans.reshape(-1, 3)

        n = max([x.shape[0] for x in (betas, pose, trans) if x is not None], default=1)
        for label, x in (("betas", betas), ("pose", pose), ("trans", trans)):
            if x is not None and x.shape[0] not in (1, n):
                raise InputError(f"{label} has batch size {x.shape[0]} but another argument has {n}")
        if betas is None:
            betas = torch.zeros((n, 0), dtype=self.dtype, device=self.device)
        if pose is None:
            pose = torch.zeros((n, NUM_JOINTS, 3), dtype=self.dtype, device=self.device)
        if trans is None:
            trans = torch.zeros((n, 3), dtype=self.dtype, device=self.device)
        return betas.expand(n, -1), pose.expand(n, -1, -1), trans.expand(n, -1)

    # ------------------------------------------------------------------ stages
    def shaped_vertices(self, betas: torch.Tensor) -> torch.Tensor:
        """betas (N, B') with B' <= B (missing components are zero) -> v_shaped [m], shape (N, V, 3)."""
        used = betas.shape[1]
        return self.v_template + torch.einsum("vcb,nb->nvc", self.shapedirs[:, :, :used], betas)

    def rest_joints(self, betas: torch.Tensor) -> torch.Tensor:
        """betas (N, B') -> rest-pose joints [m], shape (N, 24, 3)."""
        used = betas.shape[1]
        return self.joint_template + torch.einsum("jcb,nb->njc", self.joint_shapedirs[:, :, :used], betas)

    def kinematics(self, J: torch.Tensor, R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Forward kinematics: rest joints J [m] (N, 24, 3) and local rotations R (N, 24, 3, 3) ->
        global rotations (N, 24, 3, 3) and joint positions [m] (N, 24, 3) (without trans).

        Level by level of the tree's depth (8 levels for SMPL's 24 joints): every joint of a level
        composes its parent's global transform in one batched product, so a call costs a few dozen
        tensor operations instead of a few per joint (kernel launches on a GPU). Out of place, so
        autograd sees a clean graph.
        """
        rel = torch.cat([J[:, :1], J[:, 1:] - J.index_select(1, self.parents[1:])], dim=1)
        rots, poss = [], []
        for level, (s, e) in enumerate(zip(self._fk_bounds[:-1], self._fk_bounds[1:])):
            nodes = self.fk_nodes[s:e]
            r_local, t_local = R.index_select(1, nodes), rel.index_select(1, nodes)
            if level == 0:
                rots.append(r_local)
                poss.append(t_local)
                continue
            slot = self.fk_parent_slot[s:e]
            r_parent, p_parent = rots[-1].index_select(1, slot), poss[-1].index_select(1, slot)
            rots.append(r_parent @ r_local)
            poss.append(p_parent + (r_parent @ t_local[..., None])[..., 0])
        order = self.fk_joint_order
        return torch.cat(rots, dim=1).index_select(1, order), torch.cat(poss, dim=1).index_select(1, order)

    def forward(self, betas=None, pose=None, trans=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Posed bodies, differentiable in all inputs.

        betas (N, B') or (B',), B' <= B (zero-padded like BodyModel.forward); pose axis-angle [rad],
        shape (N, 24, 3) or (N, 72); trans [m], shape (N, 3). A batch of 1 broadcasts; None is zero.
        Returns (vertices [m] (N, V, 3), joints [m] (N, 24, 3) posed with trans,
        transforms (N, 24, 4, 4)) with the meaning of :class:`~simgen.body.model.BodyOutput`.
        """
        betas, pose, trans = self._batch_inputs(betas, pose, trans)
        n = pose.shape[0]
        v_shaped = self.shaped_vertices(betas)
        J = self.rest_joints(betas)
        R = axis_angle_to_matrix_torch(pose)  # (N, 24, 3, 3)

        v_posed = v_shaped
        if self.num_pose_features > 0:
            eye = torch.eye(3, dtype=self.dtype, device=self.device)
            pose_feature = (R[:, 1:] - eye).reshape(n, -1)  # (N, 207), SMPL's row-major R_j - I
            v_posed = v_shaped + (pose_feature @ self.posedirs.T).reshape(n, -1, 3)

        G_rot, G_pos = self.kinematics(J, R)

        joints = G_pos + trans[:, None]
        # Skinning translation: a rest point x attached to joint j goes to G_rot (x - J_j) + G_pos + trans.
        A_pos = G_pos - (G_rot @ J[..., None])[..., 0] + trans[:, None]
        bottom = torch.zeros((n, NUM_JOINTS, 1, 4), dtype=self.dtype, device=self.device)
        bottom[..., 0, 3] = 1.0
        transforms = torch.cat([torch.cat([G_rot, A_pos[..., None]], dim=-1), bottom], dim=-2)

        # Blend the 3x4 affine parts per vertex: T_v = sum_j w_vj A_j.
        blended = torch.einsum("vj,njab->nvab", self.weights, transforms[:, :, :3, :])  # (N, V, 3, 4)
        vertices = (blended[..., :3] @ v_posed[..., None])[..., 0] + blended[..., 3]
        return vertices, joints, transforms
