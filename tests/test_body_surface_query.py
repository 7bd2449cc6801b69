"""The body-surface query (simgen.body.surface_query): its Warp and torch implementations equal in
float64 (closest point, signed distance, normal, face) on small closed meshes, around and inside
them, near their vertices and edges; the two sign variants; the body part rule as documented."""

import numpy as np
import pytest
import torch
import trimesh
import warp as wp

from simgen.body.parts import face_part_masks
from simgen.body.surface import SurfaceMesh, project_to_surface
from simgen.body.surface_query import contact_funcs
from simgen.dataset.quality import body_penetration
from simgen.physics.surface_query import BodySurface, body_distance, closest_point_triangle
from simgen.sim.energies import reference

_f64 = contact_funcs(wp.float64)
_closest_point_triangle, _body_contact = _f64.closest_point_triangle, _f64.body_contact


@wp.kernel(enable_backward=False)
def _triangles(p: wp.array(dtype=wp.vec3d), a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.vec3d),
               c: wp.array(dtype=wp.vec3d), closest: wp.array(dtype=wp.vec3d), bary: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    q, w, interior = _closest_point_triangle(p[i], a[i], b[i], c[i])
    closest[i] = q
    bary[i] = w


@wp.kernel(enable_backward=False)
def _contact(mesh: wp.uint64, part_masks: wp.array(dtype=wp.int32), home: wp.array(dtype=wp.int32),
             x: wp.array(dtype=wp.vec3d), pinch_distance: float, distance: wp.array(dtype=wp.float64),
             normal: wp.array(dtype=wp.vec3d), face: wp.array(dtype=wp.int32), own: wp.array(dtype=wp.int32)):
    i = wp.tid()
    found, d, n, f, u, v, took = _body_contact(mesh, part_masks, home[i], x[i], 1.0, pinch_distance)
    distance[i] = d
    normal[i] = n
    face[i] = f
    own[i] = took


@pytest.fixture(autouse=True)
def _on_cpu():
    """Arrays made without a device land on the CPU, where _launch runs (a GPU machine defaults to cuda)."""
    with wp.ScopedDevice("cpu"):
        yield


def _launch(kernel, dim, inputs, outputs):
    out = [wp.zeros(dim, dtype=dtype) for dtype in outputs]
    wp.launch(kernel, dim=dim, inputs=inputs, outputs=out, device="cpu")
    return [a.numpy() for a in out]


def test_closest_point_of_a_triangle_is_one_function_in_warp_and_torch():
    """Random points and triangles (thin ones too): Warp and torch agree to round-off, the point lies
    on the triangle and no point of a dense barycentric grid is closer (within its resolution)."""
    rng = np.random.default_rng(0)
    n = 200
    tri = rng.normal(size=(n, 3, 3))
    tri[: n // 4, 2] = tri[: n // 4, 0] + 1e-3 * rng.normal(size=(n // 4, 3))  # thin triangles too
    p = rng.normal(scale=1.5, size=(n, 3))
    t = torch.tensor(tri)
    c_torch, bary, _ = closest_point_triangle(torch.tensor(p), t[:, 0], t[:, 1], t[:, 2])
    bary, c_torch = bary.numpy(), c_torch.numpy()
    c_warp, bary_warp = _launch(_triangles, n, [wp.array(a, dtype=wp.vec3d) for a in (p, tri[:, 0], tri[:, 1],
                                                                                      tri[:, 2])],
                                [wp.vec3d, wp.vec3d])
    np.testing.assert_allclose(c_warp, c_torch, rtol=0, atol=1e-12)
    np.testing.assert_allclose(bary_warp, bary, rtol=0, atol=1e-9)
    assert np.all(bary >= -1e-12) and np.allclose(bary.sum(1), 1.0)
    ours = np.einsum("nk,nkd->nd", bary, tri)
    d_ours = np.linalg.norm(ours - p, axis=1)
    k = 150
    u, v = np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k))
    keep = u + v <= 1
    grid = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], 1)  # (G, 3)
    d_grid = np.linalg.norm(np.einsum("gk,nkd->ngd", grid, tri) - p[:, None], axis=2).min(1)
    edge = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(1)
    assert np.all(d_ours <= d_grid + 1e-12)
    assert np.all(d_ours >= d_grid - edge / (k - 1) * 1.5)


def _meshes():
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    torus = trimesh.creation.torus(major_radius=0.3, minor_radius=0.1, major_sections=24, minor_sections=12)
    return {"sphere": sphere, "torus": torus}


def _points(mesh, rng):
    """Points within 1 cm of the mesh's vertices and of its edges' midpoints, and random points of
    its bounding box (inside and outside)."""
    v, e = np.asarray(mesh.vertices), np.asarray(mesh.edges_unique)
    near_v = v + 0.01 * rng.uniform(-1, 1, size=v.shape)
    mid = 0.5 * (v[e[:, 0]] + v[e[:, 1]])
    near_e = mid + 0.01 * rng.uniform(-1, 1, size=mid.shape)
    lo, hi = v.min(0), v.max(0)
    box = rng.uniform(lo - 0.1, hi + 0.1, size=(400, 3))
    return np.concatenate([near_v, near_e, box])


@pytest.mark.parametrize("name", ["sphere", "torus"])
def test_warp_and_torch_queries_are_equal_in_float64(name):
    mesh = _meshes()[name]
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    pts = _points(mesh, np.random.default_rng(1))
    w = SurfaceMesh(v, f).project(pts, sign="normal")
    t = body_distance(torch.tensor(pts), torch.tensor(v), BodySurface(f, v))
    d, n, face = t.distance.numpy(), t.normal.numpy(), t.face.numpy()
    inside = reference.winding_numbers(pts, v, f) > 0.5
    assert 200 < inside.sum() < len(pts) - 200
    # Signed distances equal to round-off, except where the float32 BVH picks a face that is as near
    # within float32 resolution; signs right (away from the surface).
    diff = np.abs(w.signed_distance - d)
    assert diff.max() < 1e-7 and (diff < 1e-12).mean() > 0.99
    clear = np.abs(d) > 1e-6
    assert np.array_equal(d[clear] < 0, inside[clear]) and np.array_equal(w.signed_distance[clear] < 0, inside[clear])
    # Closest points and normals, and the face wherever the closest point is unique (not where two
    # distinct points are equally near: the medial surface, e.g. the sphere's centre).
    c_torch = pts - d[:, None] * n
    np.testing.assert_allclose(w.closest, pts - w.signed_distance[:, None] * w.normal, rtol=0, atol=1e-12)
    same = np.linalg.norm(w.closest - c_torch, axis=1) < 1e-9
    assert same.mean() > 0.99
    np.testing.assert_allclose(w.normal[same], n[same], rtol=0, atol=1e-9)
    interior = same & np.all(w.bary > 1e-6, axis=1)
    assert interior.sum() > 200 and np.array_equal(w.face[interior], face[interior])
    np.testing.assert_allclose(np.einsum("pk,pkd->pd", w.bary, v[f[w.face]]), w.closest, rtol=0, atol=1e-12)


def _two_spheres(torso_r=0.1, arm_r=0.05, arm_x=0.1485):
    """A 'torso' sphere at the origin and an 'arm' sphere centred on +x whose surface crosses the
    x axis at arm_x (inside the torso when arm_x < torso_r): one body mesh, its face parts
    (torso 0, arm 1) and part masks."""
    t = trimesh.creation.icosphere(subdivisions=4, radius=torso_r)
    a = trimesh.creation.icosphere(subdivisions=4, radius=arm_r)
    vertices = np.vstack([t.vertices, np.asarray(a.vertices) + [arm_x + arm_r, 0.0, 0.0]])
    faces = np.vstack([t.faces, np.asarray(a.faces) + len(t.vertices)])
    parts = np.r_[np.zeros(len(t.faces), int), np.ones(len(a.faces), int)]
    return vertices, faces, parts, face_part_masks(vertices, faces, parts)


def test_winding_sign_reads_the_overlap_of_two_parts_as_inside():
    """A point inside the arm sphere, outside the torso sphere's surface but nearest to it: the
    pseudo-normal sign reads the torso's outside, the winding number the body's inside; both give
    the same closest point."""
    v, f, parts, _ = _two_spheres(arm_x=0.09)        # the arm sunk 1 cm into the torso
    x = np.array([[0.1015, 0.0, 0.0]])               # 1.5 mm outside the torso, inside the arm
    normal = project_to_surface(x, v, f, sign="normal")
    winding = project_to_surface(x, v, f)
    assert parts[normal.face[0]] == 0 and normal.signed_distance[0] == pytest.approx(1.5e-3, abs=1e-4)
    assert winding.signed_distance[0] == pytest.approx(-normal.signed_distance[0], abs=1e-12)
    np.testing.assert_allclose(winding.normal, -normal.normal, atol=1e-12)
    np.testing.assert_allclose(winding.closest, normal.closest, atol=1e-12)


def test_part_rule_takes_the_own_part_only_inside_another_part_within_the_pinch_distance():
    """Torso cloth 1.5 mm outside the torso and 0.5 mm inside an arm pressing against it (the arm's
    surface is the closest): with the rule it keeps to the torso (+1.5 mm, normal +x). Without a
    home part, as arm cloth, beyond the pinch distance (8 mm from the torso), or outside the body
    (0.5 mm outside the arm) the plain closest surface holds."""
    pinch = 5.0e-3
    cases = [  # (cloth x, arm surface x, home part, expected d [m], expected own, expected part)
        (0.1015, 0.1010, 0, 1.5e-3, 1, 0),
        (0.1015, 0.1010, -1, -0.5e-3, 0, 1),
        (0.1015, 0.1010, 1, -0.5e-3, 0, 1),
        (0.1080, 0.1075, 0, -0.5e-3, 0, 1),
        (0.1015, 0.1020, 0, 0.5e-3, 0, 1),
    ]
    for x0, arm_x, home, d_expected, own_expected, part_expected in cases:
        v, f, parts, masks = _two_spheres(arm_x=arm_x)
        mesh = wp.Mesh(points=wp.array(v, dtype=wp.vec3), indices=wp.array(f.reshape(-1), dtype=wp.int32))
        d, n, face, own = _launch(_contact, 1, [mesh.id, wp.array(masks, dtype=wp.int32),
                                               wp.array([home], dtype=wp.int32),
                                               wp.array([[x0, 0.0, 0.0]], dtype=wp.vec3d), pinch],
                                  [wp.float64, wp.vec3d, wp.int32, wp.int32])
        assert own[0] == own_expected and parts[face[0]] == part_expected, (x0, arm_x, home)
        assert d[0] == pytest.approx(d_expected, abs=1e-4), (x0, arm_x, home)
        assert abs(n[0, 0]) > 0.99 and np.sign(n[0, 0]) == (1 if part_expected == 0 else -1)


def test_statistics_rule_counts_buried_surfaces_and_cloth_kept_on_its_part_as_self_intersections():
    """Inside the body by the winding number, at a self-intersection: a point whose closest surface
    is buried in another part (its closest point, moved ``probe`` out, is still inside), and torso
    cloth that the part rule keeps on the torso inside the arm; cloth plainly inside is not."""
    v, f, _, masks = _two_spheres(arm_x=0.1010)
    x = np.array([[0.1015, 0.0, 0.0],    # torso cloth 0.5 mm inside the arm, kept on the torso
                  [0.0, 0.095, 0.0],     # 5 mm inside the torso, far from the arm
                  [0.0, 0.105, 0.0]])    # outside
    depth, self_hit, distance = body_penetration(x, v, f, probe=0.2e-3, home_parts=[0, 0, 0], part_masks=masks)
    assert np.array_equal(depth > 0, [True, True, False])
    assert np.array_equal(self_hit, [True, False, False])
    assert depth[1] == pytest.approx(5e-3, abs=1e-4) and distance[2] == pytest.approx(5e-3, abs=1e-4)
    assert not body_penetration(x, v, f, probe=0.2e-3)[1].any()
    v, f, _, masks = _two_spheres(arm_x=0.09)    # the arm sunk 1 cm into the torso
    x = np.array([[0.092, 0.0, 0.0]])            # 2 mm inside the arm's surface, which is inside the torso
    depth, self_hit, _ = body_penetration(x, v, f)
    assert depth[0] == pytest.approx(2e-3, abs=1e-4) and self_hit[0]


@wp.kernel(enable_backward=False)
def _nearest(mesh: wp.uint64, x: wp.array(dtype=wp.vec3), distance: wp.array(dtype=wp.float32),
             sign: wp.array(dtype=wp.float32)):
    i = wp.tid()
    q = wp.mesh_query_point_no_sign(mesh, x[i], 0.2)
    distance[i] = -1.0
    if q.result:
        distance[i] = wp.length(x[i] - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
    w = wp.mesh_query_point_sign_winding_number(mesh, x[i], 1.0)
    sign[i] = w.sign


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not wp.is_cuda_available(), reason="needs a CUDA device"))])
def test_mesh_subset_refit_follows_moved_points(device):
    """MeshIdSubset.refit: after the meshes' points move, a query reaching 0.2 m finds the moved
    surface 0.1 m away (stale bounds would prune it) and the winding number (the frame statistics'
    inside test) puts the moved centre inside; on CUDA the graph of every refit is replayed again
    after a second move."""
    from simgen.body.surface_query import MeshIdSubset

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    rest = np.asarray(sphere.vertices, dtype=np.float32)
    points = [wp.array(rest, dtype=wp.vec3, device=device) for _ in range(3)]
    indices = wp.array(np.asarray(sphere.faces, dtype=np.int32).ravel(), dtype=wp.int32, device=device)
    meshes = [wp.Mesh(points=p, indices=indices, support_winding_number=True) for p in points]
    subset = MeshIdSubset(meshes, device)
    out, sign = (wp.zeros(2, dtype=wp.float32, device=device) for _ in range(2))
    for shift in (1.0, 2.5):
        for p in points:
            p.assign(rest + np.float32([shift, 0.0, 0.0]))
        subset.refit(range(3))
        probe = wp.array(np.float32([[shift + 0.6, 0.0, 0.0], [shift + 0.3, 0.0, 0.0]]), dtype=wp.vec3, device=device)
        for m in meshes:
            wp.launch(_nearest, dim=2, device=device, inputs=[m.id, probe], outputs=[out, sign])
            assert abs(float(out.numpy()[0]) - 0.1) < 0.01 and sign.numpy().tolist() == [1.0, -1.0]
