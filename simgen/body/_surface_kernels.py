"""Warp kernels for closest-point queries against a triangle mesh (body surface)."""

import warp as wp


@wp.kernel
def closest_point_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    max_dist: float,
    signed_distance: wp.array(dtype=float),
    closest: wp.array(dtype=wp.vec3),
    face: wp.array(dtype=int),
    bary: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    p = points[i]
    q = wp.mesh_query_point_sign_winding_number(mesh, p, max_dist)
    if q.result:
        c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        closest[i] = c
        face[i] = q.face
        bary[i] = wp.vec3(q.u, q.v, 1.0 - q.u - q.v)
        signed_distance[i] = q.sign * wp.length(p - c)
    else:
        face[i] = -1
        signed_distance[i] = max_dist
