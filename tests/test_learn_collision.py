"""The collision post-process: exact point-triangle distances, both closest-triangle backends against
each other and against the Warp winding-number query, and push-out leaving nothing inside a sphere
or a posed body."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from simgen.body import load, project_to_surface
from simgen.learn.collision import BodySurface, closest_point_on_triangles, push_out

CLEARANCE = 0.002


def test_closest_point_on_triangles_beats_a_dense_search():
    """For random points and triangles the returned point is on the triangle and no point of a dense
    barycentric grid is closer (within the grid's resolution)."""
    rng = np.random.default_rng(0)
    n = 200
    tri = rng.normal(size=(n, 3, 3))
    tri[: n // 4, 2] = tri[: n // 4, 0] + 1e-3 * rng.normal(size=(n // 4, 3))  # thin triangles too
    p = rng.normal(scale=1.5, size=(n, 3))
    t = torch.tensor(tri)
    bary = closest_point_on_triangles(torch.tensor(p), t[:, 0], t[:, 1], t[:, 2]).numpy()
    assert np.all(bary >= 0) and np.allclose(bary.sum(1), 1.0)
    ours = np.einsum("nk,nkd->nd", bary, tri)
    d_ours = np.linalg.norm(ours - p, axis=1)
    k = 300
    u, v = np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k))
    keep = u + v <= 1
    grid = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], 1)  # (G, 3)
    pts = np.einsum("gk,nkd->ngd", grid, tri)
    d_grid = np.linalg.norm(pts - p[:, None], axis=2).min(1)
    edge = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(1)
    assert np.all(d_ours <= d_grid + 1e-12)
    assert np.all(d_ours >= d_grid - edge / (k - 1) * 1.5)


def _sphere(radius=0.3):
    m = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return np.asarray(m.vertices), np.asarray(m.faces)


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_push_out_leaves_nothing_inside_a_sphere(backend):
    v, f = _sphere()
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(500, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radii = rng.uniform(0.05, 0.36, size=500)
    pts = dirs * radii[:, None]
    surface = BodySurface(f, len(v), backend=backend)
    out, moved = push_out(torch.tensor(pts), torch.tensor(v), surface, clearance=CLEARANCE)
    out = out.numpy()
    sd_after = project_to_surface(out, v, f).signed_distance  # winding number: independent of the push-out
    assert sd_after.min() > 0.0
    sd_before = project_to_surface(pts, v, f).signed_distance
    inside = sd_before < 0
    assert inside.sum() > 300 and np.all(moved.numpy()[inside])
    # Moved points end `clearance` from their closest primitive: on a convex body, from the body.
    assert np.abs(sd_after[inside] - CLEARANCE).max() < 2e-6
    # Points farther out than the clearance do not move at all.
    far = sd_before > CLEARANCE + 1e-6
    assert far.sum() > 50 and np.array_equal(out[far], pts[far])


def test_backends_agree_with_each_other_and_with_warp_winding_numbers():
    body = load("open")
    from simgen.garment.library import load_garment
    from simgen.garment.skinning import lbs

    g = load_garment("tshirt_1k", body=body)
    rng = np.random.default_rng(2)
    pose = rng.normal(scale=0.25, size=(1, 24, 3))
    out = body.forward(np.zeros((1, body.num_betas)), pose, np.zeros((1, 3)))
    garment = lbs(g.vertices, g.skin_weights, out.transforms)[0]
    garment += rng.normal(scale=0.01, size=garment.shape)  # push some vertices into the body
    bv = torch.tensor(out.vertices[0], dtype=torch.float32)
    x = torch.tensor(garment, dtype=torch.float32)
    qw = BodySurface(body.faces, body.num_vertices, backend="warp").query(x, bv)
    qt = BodySurface(body.faces, body.num_vertices, backend="torch").query(x, bv)
    assert (qw.closest - qt.closest).norm(dim=-1).max() < 1e-4
    assert torch.allclose(qw.signed_distance.abs(), qt.signed_distance.abs(), atol=1e-5)
    ref = project_to_surface(garment, out.vertices[0], body.faces)
    d_ref = np.abs(ref.signed_distance)
    assert np.abs(np.abs(qw.signed_distance[0].numpy()) - d_ref).max() < 1e-5
    # Pseudo-normal (warp) and winding-number signs agree; the torch backend's smooth-normal sign too,
    # away from the surface.
    assert np.array_equal(qw.signed_distance[0].numpy() < 0, ref.signed_distance < 0)
    clear = np.abs(ref.signed_distance) > 1e-3
    assert np.array_equal(qt.signed_distance[0].numpy()[clear] < 0, ref.signed_distance[clear] < 0)
    assert (ref.signed_distance < 0).sum() >= 10

    fixed, moved = push_out(x, bv, BodySurface(body.faces, body.num_vertices))
    after = project_to_surface(fixed.numpy(), out.vertices[0], body.faces).signed_distance
    assert after.min() > 0.0 and moved.sum() >= (ref.signed_distance < 0).sum()
