"""Warp kernel of the collision post-process: closest body triangle of each point (BVH) and the
inside/outside sign from the angle-weighted pseudo-normal of the closest feature."""

import warp as wp


@wp.kernel
def closest_face_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    max_dist: float,
    face: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3),
    sign: wp.array(dtype=float),
):
    i = wp.tid()
    q = wp.mesh_query_point_sign_normal(mesh, points[i], max_dist)
    if q.result:
        face[i] = q.face
        # Warp's (u, v) weight the triangle's first two corners: p = u a + v b + (1 - u - v) c.
        bary[i] = wp.vec3(q.u, q.v, 1.0 - q.u - q.v)
        sign[i] = q.sign
    else:
        face[i] = -1
