"""The torch energies of simgen.physics equal the Warp solver's energies of the same name (float64).

For every garment template (full resolution), posed by LBS on the open body at a library motion
frame and deformed at random (a third of the vertices moved to a random signed distance in
[-4, 4] mm from the body along the solver's own contact normal: inside the margin and inside the
body; every vertex jittered), each torch term equals the Warp kernel at the same parameters to 1e-5
relative, and its autograd gradient equals the kernel's analytic gradient. The rest data (masses,
rest frames, hinge stiffness, rest angles) is computed independently in torch from the garment and
its Material.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from simgen.physics import (BodySurface, ClothRest, FrictionParams, LaggedContact, bending, contact, friction, gravity,
                            inertia, membrane)
from simgen.physics.surface_query import body_distance
from simgen.sim import BodyCollider, ClothModel
from simgen.sim.energies import (ContactFrame, ContactParams, GravityParams, eval_bending, eval_contact, eval_friction,
                                 eval_gravity, eval_inertia, eval_membrane, update_contact_frame)

wp.config.quiet = True

GARMENTS = ("tshirt", "tank_top", "dress", "skirt", "pants", "shorts")
REL = 1e-5


@pytest.fixture(scope="module")
def scene():
    from simgen.body import load
    from simgen.motion import load_motion

    body = load("open")
    clip = load_motion("walk")
    out = body.forward(np.zeros(body.num_betas), clip.poses[12], clip.trans[12])
    # The solver's warp.Mesh holds float32 points: give both sides the same rounded body.
    verts = out.vertices[0].astype(np.float32).astype(np.float64)
    return dict(body=body, transforms=out.transforms, vertices=verts, surface=BodySurface.from_body(body),
                collider=BodyCollider.from_static(verts, body.faces, device="cpu"))


def deformed(garment, scene, seed):
    """LBS-posed garment with a third of its vertices moved to -4..4 mm from the body, all jittered."""
    from simgen.garment import lbs

    x = lbs(garment.vertices, garment.skin_weights, scene["transforms"])[0]
    model = ClothModel.from_garment(garment, body=scene["body"], device="cpu", dtype=wp.float64)
    frame = ContactFrame(model)
    update_contact_frame(model, wp.array(x, dtype=wp.vec3d, device="cpu"), scene["collider"].mesh_ids,
                         ContactParams(query_distance=0.5), frame)
    d, n = frame.distance.numpy(), frame.normal.numpy()
    rng = np.random.default_rng(seed)
    pick = (rng.random(len(x)) < 1 / 3) & (frame.face.numpy() >= 0)
    target = rng.uniform(-4e-3, 4e-3, size=len(x))
    x = x + np.where(pick[:, None], (target - d)[:, None] * n, 0.0)
    return x + 5e-4 * rng.normal(size=x.shape), model


def warp_term(model, fn, x, *args, **kw):
    e, g = model.new_energy(), model.new_gradient()
    fn(model, wp.array(x, dtype=wp.vec3d, device="cpu"), *args, energy=e, gradient=g, **kw)
    return float(e.numpy().sum()), g.numpy().astype(np.float64)


def torch_term(fn, x, *args, **kw):
    xt = torch.tensor(x, dtype=torch.float64, requires_grad=True)
    e = fn(xt, *args, **kw)
    e.backward()
    return float(e.detach()), xt.grad.numpy()


def assert_parity(name, warp_out, torch_out, rel=REL, vertices=slice(None)):
    """Energies equal to ``rel``; gradients too, relative to their largest component (at ``vertices``)."""
    (ew, gw), (et, gt) = warp_out, torch_out
    assert abs(et - ew) <= rel * abs(ew), f"{name}: torch {et!r} vs warp {ew!r}"
    scale = np.abs(gw).max()
    assert scale > 0, f"{name}: zero gradient, the test configuration does not exercise the term"
    err = np.abs(gt - gw)[vertices].max() / scale
    assert err <= rel, f"{name}: gradient differs by {err:.2e} of its largest component"


@pytest.mark.parametrize("name", GARMENTS)
@pytest.mark.parametrize("bending_rest", ["template", "flat"])
def test_terms_equal_warp_energies(name, bending_rest, scene):
    from simgen.garment import load_garment

    garment = load_garment(name, body=scene["body"])
    x, _ = deformed(garment, scene, seed=GARMENTS.index(name))
    model = ClothModel.from_garment(garment, body=scene["body"], device="cpu", dtype=wp.float64,
                                   bending_rest=bending_rest)
    rest = ClothRest.from_garment(garment, bending_rest=bending_rest, dtype=torch.float64)
    # Independently computed rest data equals the model's.
    np.testing.assert_allclose(rest.vertex_mass.numpy(), model.host.vertex_mass, rtol=1e-12)
    np.testing.assert_allclose(rest.hinge_stiffness.numpy(), model.host.hinge_stiffness, rtol=1e-12)
    np.testing.assert_allclose(rest.hinge_rest_angle.numpy(), model.host.hinge_rest_angle, atol=1e-12)

    assert_parity("membrane", warp_term(model, eval_membrane, x), torch_term(membrane, x, rest))
    assert_parity("bending", warp_term(model, eval_bending, x), torch_term(bending, x, rest))
    g = GravityParams((0.3, -9.81, 0.1))
    assert_parity("gravity", warp_term(model, eval_gravity, x, g), torch_term(gravity, x, rest, g))
    if bending_rest == "template":
        rng = np.random.default_rng(1)
        x_hat = x + 0.01 * rng.normal(size=x.shape)
        dt = 1.0 / 30.0
        x_hat_t = torch.tensor(x_hat, dtype=torch.float64)
        assert_parity("inertia", warp_term(model, eval_inertia, x, wp.array(x_hat, dtype=wp.vec3d, device="cpu"), dt),
                      torch_term(inertia, x, x_hat_t, rest, dt))
        bv = torch.tensor(scene["vertices"])
        same = same_nearest_face(model, x, scene)
        for params in (ContactParams(), ContactParams.snug(), ContactParams(margin=3e-3, stiffness=5e3, power=2.5)):
            assert_parity(f"contact {params}", warp_term(model, eval_contact, x, scene["collider"].mesh_ids, params),
                          torch_term(contact, x, bv, scene["surface"], params), vertices=same)


def same_nearest_face(model, x, scene):
    """Vertices where the solver's query and the torch search agree on the nearest body triangle.

    The solver picks the face in float32 (``warp.mesh_query_point_sign_normal``) and then measures
    on it in float64; where two triangles are equally close to float32 resolution it may pick the
    farther. Such vertices must be true ties (distances within 1e-7 m); the gradient is compared at
    all the others (the energy everywhere). Faces sharing the closest edge or vertex give the same
    distance and normal and are not ties of this kind.
    """
    frame = ContactFrame(model)
    update_contact_frame(model, wp.array(x, dtype=wp.vec3d, device="cpu"), scene["collider"].mesh_ids,
                         ContactParams(), frame)
    dist = body_distance(torch.tensor(x), torch.tensor(scene["vertices"]), scene["surface"])
    found = frame.face.numpy() >= 0
    d_w, d_t = frame.distance.numpy(), dist.distance.numpy()
    # The configuration exercises the term: vertices inside the margin and inside the body.
    assert np.sum(found & (d_w > 0) & (d_w < 2e-3)) >= 20 and np.sum(found & (d_w < 0)) >= 20
    n_w, n_t = frame.normal.numpy(), dist.normal.numpy()
    same = ~found | (np.abs(d_w - d_t) < 1e-12) & (np.abs(n_w - n_t).max(axis=1) < 1e-9)
    assert np.all(np.abs(d_w - d_t)[found] < 1e-7), "the nearest triangles differ by more than a float32 tie"
    assert np.sum(~same) <= max(3, 0.002 * found.sum()), f"{np.sum(~same)} float32 ties: too many to be ties"
    return same


def test_contact_configuration_has_vertices_inside_margin_and_body(scene):
    from simgen.garment import load_garment

    garment = load_garment("tshirt", body=scene["body"])
    x, _ = deformed(garment, scene, seed=0)
    d = body_distance(torch.tensor(x), torch.tensor(scene["vertices"]), scene["surface"]).distance.numpy()
    assert np.sum((d > 0) & (d < 2e-3)) > 50 and np.sum(d < 0) > 50


@pytest.mark.parametrize("max_normal_load", [20.0, float("inf")])
def test_friction_equals_warp(scene, max_normal_load):
    """Lagged friction against a moving body: the torch lagged contact (normal, force, body
    displacement at the closest point) and the friction potential equal the solver's, with and
    without the solver's cap on the normal load.

    The solver interpolates the body velocity with float32 barycentric weights (~1e-7 relative),
    and a sticking vertex's gradient is 2 mu lambda / (eps_v dt) per metre of slip, so the gradient
    parity holds to 1e-5 for eps_v >= 1e-2 m/s (at IPC's 1e-3 m/s to ~6e-5, float32 round-off).
    """
    from simgen.garment import load_garment

    garment = load_garment("tshirt_1k", body=scene["body"])
    x_start, model = deformed(garment, scene, seed=7)
    dt = 1.0 / 300.0
    # [m/s] the body translates; float32 values (the solver's mesh velocities are float32).
    body_v = np.array([0.3, 0.05, -0.2], dtype=np.float32).astype(np.float64)
    params = ContactParams()
    verts = scene["vertices"]
    collider = BodyCollider.from_static(verts, scene["body"].faces, device="cpu")
    collider.update(verts, velocities=np.broadcast_to(body_v, verts.shape))
    collider.set_time(0.0)                                # contact set at the step's start
    frame = ContactFrame(model)
    update_contact_frame(model, wp.array(x_start, dtype=wp.vec3d, device="cpu"), collider.mesh_ids, params, frame)
    lag = LaggedContact.from_positions(torch.tensor(x_start), torch.tensor(verts),
                                       torch.tensor(verts + dt * body_v), scene["surface"], params)
    np.testing.assert_allclose(lag.force.numpy(), frame.force.numpy(), rtol=1e-9, atol=1e-9 * frame.force.numpy().max())
    assert np.sum(frame.force.numpy() > 0) > 20
    rng = np.random.default_rng(3)
    # Slips below and above the smoothing width eps_v dt, relative to the body.
    fp = FrictionParams(smoothing_velocity=1e-2, max_normal_load=max_normal_load)
    eps = fp.smoothing_velocity * dt
    x = x_start + dt * body_v + eps * rng.normal(size=x_start.shape) * rng.choice([0.1, 3.0], size=(len(x_start), 1))
    rest = ClothRest.from_garment(garment, dtype=torch.float64)
    xs = wp.array(x_start, dtype=wp.vec3d, device="cpu")
    assert_parity("friction", warp_term(model, eval_friction, x, xs, collider.mesh_ids, frame, dt, fp),
                  torch_term(friction, x, torch.tensor(x_start), lag, rest, dt, fp), rel=1e-5)
