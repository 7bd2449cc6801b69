"""Warp kernels of the SMPL-format forward pass (float32), one kernel per stage.

Kept in their own module so that Warp compiles and caches them as one unit; the host side is
:class:`simgen.body.warp_lbs.WarpBody`. Shapes below use N instances, V vertices, B shape
components, P pose features (207 or 0), K skinning influences per vertex, 24 joints. Launches put
the vertex index last so that neighbouring GPU threads handle neighbouring vertices.

Quaternions are Warp's ``wp.quat`` with component order (x, y, z, w).
"""

from __future__ import annotations

import warp as wp

NUM_JOINTS = wp.constant(24)


@wp.kernel
def shape_blend_kernel(
    v_template: wp.array(dtype=wp.vec3),
    shapedirs: wp.array2d(dtype=wp.vec3),
    betas: wp.array2d(dtype=wp.float32),
    v_shaped: wp.array2d(dtype=wp.vec3),
):
    """v_shaped[n, v] = v_template[v] + sum_b shapedirs[b, v] * betas[n, b].

    v_template [m] (V,); shapedirs [m] (B, V) (component-major, so neighbouring threads read
    neighbouring memory at each step of the loop); betas (N_b, B') with B' <= B (missing components are
    zero) and N_b = N, or N_b = 1 to give every instance the same shape; v_shaped [m] (N, V) output.
    Launch dim (N, V).
    """
    n, v = wp.tid()
    row = wp.min(n, betas.shape[0] - 1)
    p = v_template[v]
    for b in range(betas.shape[1]):
        p += shapedirs[b, v] * betas[row, b]
    v_shaped[n, v] = p


@wp.kernel
def joint_regression_kernel(
    row_start: wp.array(dtype=wp.int32),
    vertex_index: wp.array(dtype=wp.int32),
    weight: wp.array(dtype=wp.float32),
    v_shaped: wp.array2d(dtype=wp.vec3),
    rest_joints: wp.array2d(dtype=wp.vec3),
):
    """rest_joints[n, j] = sum over the nonzeros k of row j: weight[k] * v_shaped[n, vertex_index[k]].

    The joint regressor is stored CSR-like: row_start (25,), vertex_index and weight (nnz,).
    v_shaped [m] (N, V); rest_joints [m] (N, 24) output. Launch dim (N, 24).
    """
    n, j = wp.tid()
    acc = wp.vec3(0.0)
    for k in range(row_start[j], row_start[j + 1]):
        acc += v_shaped[n, vertex_index[k]] * weight[k]
    rest_joints[n, j] = acc


@wp.kernel
def axis_angle_to_quat_kernel(axis_angle: wp.array2d(dtype=wp.vec3), quats: wp.array2d(dtype=wp.quat)):
    """axis_angle [rad] (N, 24) -> unit quaternions (x, y, z, w) (N, 24). Launch dim (N, 24)."""
    n, j = wp.tid()
    aa = axis_angle[n, j]
    angle = wp.length(aa)
    # sin(angle / 2) / angle tends to 1/2; its series is exact to float32 precision below 1e-3 rad.
    scale = 0.5 - angle * angle / 48.0
    if angle > 1.0e-3:
        scale = wp.sin(0.5 * angle) / angle
    quats[n, j] = wp.quat(aa[0] * scale, aa[1] * scale, aa[2] * scale, wp.cos(0.5 * angle))


@wp.kernel
def forward_kinematics_kernel(
    local_rotation: wp.array2d(dtype=wp.quat),
    rest_joints: wp.array2d(dtype=wp.vec3),
    trans: wp.array(dtype=wp.vec3),
    parents: wp.array(dtype=wp.int32),
    write_pose_feature: wp.int32,
    global_rotation: wp.array2d(dtype=wp.quat),
    global_position: wp.array2d(dtype=wp.vec3),
    transforms: wp.array2d(dtype=wp.mat44),
    joints: wp.array2d(dtype=wp.vec3),
    pose_feature: wp.array2d(dtype=wp.float32),
):
    """Walk the kinematic tree of one instance (parents before children).

    Inputs: local_rotation (N, 24) quaternions (x, y, z, w), normalised here (slerped poses need not
    be exactly unit); rest_joints [m] (N, 24); trans [m] (N,); parents (24,), parents[0] = -1.
    Outputs: global_rotation (N, 24) and global_position [m] (N, 24), the joint frames without
    trans; transforms (N, 24) skinning matrices, [R_g | p_g - R_g J_rest + trans]; joints [m]
    (N, 24) posed, trans included; when write_pose_feature != 0, pose_feature (N, 207) =
    R_local - I of joints 1..23, row-major (SMPL's pose-corrective features).
    Launch dim (N,).
    """
    n = wp.tid()
    t = trans[n]
    identity = wp.identity(n=3, dtype=wp.float32)
    for j in range(NUM_JOINTS):
        q = wp.normalize(local_rotation[n, j])
        rest = rest_joints[n, j]
        parent = parents[j]
        q_global = q
        p_global = rest
        if parent >= 0:
            q_parent = global_rotation[n, parent]
            q_global = q_parent * q
            p_global = global_position[n, parent] + wp.quat_rotate(q_parent, rest - rest_joints[n, parent])
        global_rotation[n, j] = q_global
        global_position[n, j] = p_global

        R = wp.quat_to_matrix(q_global)
        offset = p_global - R @ rest + t
        transforms[n, j] = wp.mat44(
            R[0, 0], R[0, 1], R[0, 2], offset[0],
            R[1, 0], R[1, 1], R[1, 2], offset[1],
            R[2, 0], R[2, 1], R[2, 2], offset[2],
            0.0, 0.0, 0.0, 1.0,
        )
        joints[n, j] = p_global + t

        if write_pose_feature != 0 and j > 0:
            D = wp.quat_to_matrix(q) - identity
            base = (j - 1) * 9
            for r in range(3):
                for c in range(3):
                    pose_feature[n, base + r * 3 + c] = D[r, c]


@wp.kernel
def pose_corrective_kernel(
    v_shaped: wp.array2d(dtype=wp.vec3),
    posedirs: wp.array2d(dtype=wp.vec3),
    pose_feature: wp.array2d(dtype=wp.float32),
    v_posed: wp.array2d(dtype=wp.vec3),
):
    """v_posed[n, v] = v_shaped[n, v] + sum_p posedirs[p, v] * pose_feature[n, p].

    v_shaped [m] (N, V); posedirs [m] (P, V) (feature-major, so the loop's loads coalesce across
    neighbouring vertices); pose_feature (N, P); v_posed [m] (N, V) output.
    Launch dim (N, V).
    """
    n, v = wp.tid()
    p = v_shaped[n, v]
    for k in range(posedirs.shape[0]):
        p += posedirs[k, v] * pose_feature[n, k]
    v_posed[n, v] = p


@wp.kernel
def skinning_kernel(
    rest_vertices: wp.array2d(dtype=wp.vec3),
    transforms: wp.array2d(dtype=wp.mat44),
    influence_joint: wp.array2d(dtype=wp.int32),
    influence_weight: wp.array2d(dtype=wp.float32),
    vertices: wp.array2d(dtype=wp.vec3),
):
    """Linear blend skinning: vertices[n, v] = sum_k w[v, k] * transforms[n, joint[v, k]] (x, 1).

    rest_vertices [m] (N, V) (shaped, plus pose correctives when the model has them); transforms
    (N, 24); influence_joint and influence_weight (V, K): the nonzero skinning weights of each
    vertex, padded with weight 0 (K = the largest count over vertices, so nothing is truncated);
    vertices [m] (N, V) output. Launch dim (N, V).
    """
    n, v = wp.tid()
    x = rest_vertices[n, v]
    p = wp.vec3(0.0)
    for k in range(influence_joint.shape[1]):
        p += influence_weight[v, k] * wp.transform_point(transforms[n, influence_joint[v, k]], x)
    vertices[n, v] = p
