"""The collision post-process: both backends against each other and against the winding-number
query, and push-out leaving nothing inside a sphere or a posed body. (The point-triangle closest
point and the two implementations of the body-surface query: tests/test_body_surface_query.py.)"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from simgen.body import load, project_to_surface
from simgen.learn.collision import CollisionSurface, push_out

CLEARANCE = 0.002


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
    surface = CollisionSurface(f, v, backend=backend)
    out, moved = push_out(torch.tensor(pts), torch.tensor(v), surface, clearance=CLEARANCE)
    out = out.numpy()
    sd_after = project_to_surface(out, v, f).signed_distance  # winding-number sign: not the push-out's
    assert sd_after.min() > 0.0
    sd_before = project_to_surface(pts, v, f).signed_distance
    inside = sd_before < 0
    assert inside.sum() > 300 and np.all(moved.numpy()[inside])
    # Moved points end `clearance` from their closest primitive: on a convex body, from the body.
    assert np.abs(sd_after[inside] - CLEARANCE).max() < 2e-6
    # Points farther out than the clearance do not move at all.
    far = sd_before > CLEARANCE + 1e-6
    assert far.sum() > 50 and np.array_equal(out[far], pts[far])


def test_backends_agree_with_each_other_and_with_winding_numbers():
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
    qw = CollisionSurface(body.faces, body.v_template, backend="warp").query(x, bv)
    qt = CollisionSurface(body.faces, body.v_template, backend="torch").query(x, bv)
    # The same query (pseudo-normal sign) by its two implementations, in float32.
    assert qw.distance.shape == (1, len(garment))
    assert (qw.distance - qt.distance).abs().max() < 1e-5
    cw, ct = x - qw.distance[0, :, None] * qw.normal[0], x - qt.distance[0, :, None] * qt.normal[0]
    assert (cw - ct).norm(dim=-1).max() < 1e-4
    ref = project_to_surface(garment, out.vertices[0], body.faces)
    assert np.abs(np.abs(qw.distance[0].numpy()) - np.abs(ref.signed_distance)).max() < 1e-5
    # Pseudo-normal and winding-number signs agree on this body (no self-intersection in this pose).
    assert np.array_equal(qw.distance[0].numpy() < 0, ref.signed_distance < 0)
    assert (ref.signed_distance < 0).sum() >= 10

    fixed, moved = push_out(x, bv, CollisionSurface(body.faces, body.v_template))
    after = project_to_surface(fixed.numpy(), out.vertices[0], body.faces).signed_distance
    assert after.min() > 0.0 and moved.sum() >= (ref.signed_distance < 0).sum()


def test_a_spread_push_lifts_a_sheet_off_a_sphere_without_stretching_it():
    """A flat sheet (1 cm edges) cut 6 mm deep by a sphere's cap: both pushes leave every vertex at
    least the clearance outside, but one vertex at a time stretches the triangles at the cap's rim
    (their largest principal stretch against the flat sheet), while the push spread over the cloth
    (MeshSpread) lifts the sheet like a tent: a fraction of that stretch; cloth far from the cap
    does not move."""
    from simgen.dataset.quality import triangle_rest_inverse, triangle_strain
    from simgen.learn.collision import MeshSpread

    v, f = _sphere(radius=0.3)
    n = 41
    u = np.linspace(-0.2, 0.2, n)
    grid = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)
    sheet = np.column_stack([grid, np.full(len(grid), 0.294)])           # the cap above 0.294 m pokes through
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel(), k[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    surface = CollisionSurface(f, v)
    rest_inv = triangle_rest_inverse(sheet, faces)
    results = {}
    for name, spread in (("vertex", None), ("spread", MeshSpread(faces, len(sheet)))):
        out, moved = push_out(torch.tensor(sheet), torch.tensor(v), surface, clearance=CLEARANCE, spread=spread)
        out = out.numpy()
        sd = project_to_surface(out, v, f).signed_distance
        assert sd.min() > CLEARANCE - 1e-5, name
        results[name] = (out, moved.numpy(), triangle_strain(out, faces, rest_inv).max())
    (x1, moved, strain_vertex), (x2, moved2, strain_spread) = results["vertex"], results["spread"]
    assert np.array_equal(moved, moved2) and moved.sum() > 20
    assert strain_vertex > 0.05 and strain_spread < 0.3 * strain_vertex
    far = np.linalg.norm(grid, axis=1) > 0.18      # the cap's rim lies at 6 cm; 8 rings reach 11 cm beyond it
    assert np.array_equal(x2[far], sheet[far])
