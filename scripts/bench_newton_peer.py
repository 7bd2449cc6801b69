"""Peer benchmark: NVIDIA Newton 1.8's cloth solvers (SolverVBD, SolverStyle3D) on our garment and body.

What is measured, and how it maps to our own benchmark (scripts/bench_solver.py, mode "static"):

- Scene: the garment template (vertices [m] as given, modelled on the body in rest pose, lying just
  outside it) draping under gravity (-9.81 m/s^2 along -y, our up axis is +y) onto the body held in
  rest pose, a static triangle-mesh collider. Same garment, same body, no self-contact (ours has none).
- Instances: N copies of (cloth + body), one Newton world each (``ModelBuilder.replicate``), stepping
  together in one model; particles collide only with the shapes of their own world, so copies do
  not interact although they overlap in space.
- Time stepping: a 30 fps frame is ``substeps`` (10) solver steps of dt = 1 / (fps * substeps).
  Collision detection (particle vs. body mesh soft contacts) runs once per substep: SolverVBD owns
  the ``newton.CollisionPipeline`` and detects at the start of every step (its default schedule, as
  in Newton's cloth_bending example); for SolverStyle3D, which cannot own a pipeline, ``collide`` is
  called before every step (as in the cloth_hanging and cloth_h1 examples). SolverVBD runs
  ``iterations`` (10) VBD iterations per substep; SolverStyle3D runs ``iterations`` non-linear
  iterations per substep (10, its ``Config`` default) with its default 10 PCG iterations each.
- On CUDA one whole frame (all substeps, detection included) is captured once as a CUDA graph with
  ``wp.ScopedCapture`` and replayed, as the Newton examples do; on the CPU it runs eagerly.
- Timing: after ``warmup_frames`` frames, each of ``frames`` frames is timed with
  ``wp.synchronize_device`` before and after it (``time.perf_counter``); reported are the median and
  mean ms per frame and cloth-frames per second = instances * 1000 / median ms.
- Also reported: device memory taken by building (CUDA: total - free before building and after the
  capture), sizes, whether positions stayed finite, the final minimum y and vertical extent of the
  cloth against the initial ones, and the cloth vertices inside the body (winding-number test
  against the body mesh with Warp, on the model's device, untimed).

Material mapping (our StVK cloth: area density rho_A [kg/m^2], Young's modulus E [Pa], Poisson ratio
nu, thickness h [m], bending stiffness k_bend [N m]; plane-stress Lame parameters
lambda = E nu / (1 - nu^2), mu = E / (2 (1 + nu))):

- mass: ``density`` = rho_A (both solvers lump area * rho_A / 3 on each vertex, as ours).
- SolverVBD membrane: its triangle is a stable Neo-Hookean membrane whose ``tri_ke``/``tri_ka`` are
  the Lame parameters mu and lambda per unit area (energy = rest area * Psi): tri_ke = mu h,
  tri_ka = lambda h [N/m], the same coefficients our StVK membrane uses (both agree to first order
  in the strain). tri_kd = 0 (our presets have no damping).
- SolverVBD bending: Newton's hinge energy is edge_ke * l * (theta - theta_rest)^2 / 2, ours is
  k_bend * l^2 / (4 (a1 + a2)) * (theta - theta_rest)^2 / 2, so edge_ke = k_bend l / (4 (a1 + a2))
  [N], set per edge from the template (l the edge length, a1, a2 the adjacent triangle areas);
  theta_rest is the template's angle in both. edge_kd = 0.
- SolverStyle3D membrane: Baraff-Witkin stretch/shear with ``tri_aniso_ke`` = (weft, warp, shear)
  stiffness [N/m]: weft = warp = E h (the uniaxial tensile stiffness of our material, free sides),
  shear = mu h. Baraff-Witkin has no Poisson coupling between the two directions, so this is an
  approximation of our StVK membrane. Its rest shape comes from 2D panel coordinates: each triangle
  is laid flat isometrically (exact template rest shape), with the warp (v) axis along the world
  up axis projected onto the triangle (the front-back axis where the triangle is near horizontal).
- SolverStyle3D bending: the quadratic (Bergou et al. 2006) model, energy
  k * 3 / (a1 + a2) * |sum_i w_i x_i|^2 / 2 with |sum_i w_i x_i| = l theta for small angles, so
  k = k_bend / 12 gives our energy for small angles; its rest shape is flat (ours: the template's
  angles), a known difference.
- Body contact (both): particle radius = 2 mm (contact acts where the vertex-body distance is below
  it, like our 2 mm contact margin), body shape margin 0, detection-only gap 2 mm on top of that
  (``soft_contact_gap``); quadratic penalty with soft_contact_ke = shape ke = 1e3 N/m, damping
  kd = 0.1 N s/m (the pair of Newton's cloth_twist example), Coulomb friction 0.3 (ours).

The scene (:func:`build_newton_peer`, :class:`NewtonPeer`) and the material mapping are shared with
scripts/peer_drape.py, which drapes one instance on a body that moves from the rest pose to a
standing pose and moves the body mesh between substeps.

Run standalone (prints one JSON line per run):

    python scripts/bench_newton_peer.py --solver vbd --instances 1 16 --frames 20 --device cuda:0 \\
        [--garment tshirt] [--out file.json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import newton
import numpy as np
import warp as wp
from newton.solvers import SolverStyle3D, SolverVBD, style3d

CONTACT_RADIUS = 2.0e-3  # [m] particle radius: body contact acts below this distance (our margin)
CONTACT_GAP = 2.0e-3  # [m] detection-only slack added to the radius for the body-mesh query
CONTACT_KE = 1.0e3  # [N/m] normal penalty stiffness (particle side and body shape alike)
CONTACT_KD = 1.0e-1  # [N s/m] normal contact damping
FRICTION = 0.3  # [-] Coulomb coefficient against the body (our default)
GRAVITY = (0.0, -9.81, 0.0)  # [m/s^2], y up

SOLVERS = ("vbd", "style3d")


def material_mapping(area_density: float, youngs_modulus: float, poisson: float, thickness: float,
                     bend_stiffness: float) -> dict:
    """Newton coefficients for our StVK material (SI units; see the module docstring).

    Returns a JSON-serialisable dict: our parameters, the plane-stress Lame parameters times thickness,
    and the per-solver values (VBD's per-edge bending stiffness is computed per hinge, see
    :func:`vbd_edge_stiffness`).
    """
    lam = youngs_modulus * poisson / (1.0 - poisson * poisson)
    mu = youngs_modulus / (2.0 * (1.0 + poisson))
    return {
        "ours": {"area_density_kg_m2": area_density, "youngs_modulus_pa": youngs_modulus, "poisson": poisson,
                 "thickness_m": thickness, "bend_stiffness_nm": bend_stiffness,
                 "lambda_h_n_m": lam * thickness, "mu_h_n_m": mu * thickness},
        "vbd": {"density_kg_m2": area_density, "tri_ke_n_m": mu * thickness, "tri_ka_n_m": lam * thickness,
                "tri_kd": 0.0, "edge_ke_n": "k_bend * l / (4 (a1 + a2)) per edge", "edge_kd": 0.0,
                "bending_rest": "template"},
        "style3d": {"density_kg_m2": area_density,
                    "tri_aniso_ke_n_m": [youngs_modulus * thickness, youngs_modulus * thickness, mu * thickness],
                    "edge_ke_nm": bend_stiffness / 12.0, "edge_kd": 0.0, "bending_rest": "flat",
                    "panel": "each triangle flattened isometrically, warp axis = projected world up"},
    }


def vbd_edge_stiffness(x: np.ndarray, edges: np.ndarray, bend_stiffness: float) -> np.ndarray:
    """Per-edge ``edge_ke`` [N] for SolverVBD that reproduces our hinge energy on the rest shape.

    x [m], (V, 3): rest positions; edges, int (E, 4): Newton's edge rows (opposite vertex 1,
    opposite vertex 2, edge start, edge end; -1 where a boundary edge has no opposite vertex).
    Returns (E,): k_bend * l / (4 (a1 + a2)) on interior edges, 0 on boundary edges.
    """
    o1, o2, a, b = edges.T
    interior = (o1 >= 0) & (o2 >= 0)
    o1, o2, a, b = o1[interior], o2[interior], a[interior], b[interior]
    length = np.linalg.norm(x[b] - x[a], axis=1)
    area1 = 0.5 * np.linalg.norm(np.cross(x[a] - x[o1], x[b] - x[o1]), axis=1)
    area2 = 0.5 * np.linalg.norm(np.cross(x[a] - x[o2], x[b] - x[o2]), axis=1)
    ke = np.zeros(len(edges))
    ke[interior] = bend_stiffness * length / (4.0 * (area1 + area2))
    return ke


def panel_coordinates(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Style3D panel (2D rest) coordinates [m] laying each triangle flat, isometrically.

    x [m], (V, 3); faces, int (F, 3), counter-clockwise. Returns (F, 3, 2): the corners of triangle f
    in an orthonormal frame (u, v) of its plane, v along the world up axis (+y) projected onto the
    plane, or along the front-back axis (+z) where the triangle is within 30 degrees of horizontal,
    u = v x n; the 2D triangles keep their counter-clockwise orientation (positive area).
    """
    corners = x[faces]                                             # (F, 3, 3)
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)

    def in_plane(axis):
        return axis - (n @ axis)[:, None] * n

    v = in_plane(np.array([0.0, 1.0, 0.0]))
    near_horizontal = np.linalg.norm(v, axis=1) < 0.5
    v[near_horizontal] = in_plane(np.array([0.0, 0.0, 1.0]))[near_horizontal]
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    u = np.cross(v, n)
    rel = corners - corners[:, :1]
    return np.stack([np.einsum("fkd,fd->fk", rel, u), np.einsum("fkd,fd->fk", rel, v)], axis=-1)


def _world_builder(solver: str, garment_vertices: np.ndarray, garment_faces: np.ndarray, body_mesh,
                   material: dict, area_density: float, bend_stiffness: float):
    """One world: the static body mesh shape and the cloth, set up for ``solver``."""
    builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=GRAVITY)
    body_cfg = newton.ModelBuilder.ShapeConfig(ke=CONTACT_KE, kd=CONTACT_KD, mu=FRICTION, margin=0.0)
    builder.add_shape_mesh(body=-1, mesh=body_mesh, cfg=body_cfg, label="body")
    x = np.asarray(garment_vertices, dtype=np.float64)
    faces = np.asarray(garment_faces, dtype=np.int64)
    if solver == "vbd":
        builder.add_cloth_mesh(pos=wp.vec3(0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0),
                               vertices=x, indices=faces.reshape(-1), density=area_density,
                               tri_ke=material["vbd"]["tri_ke_n_m"], tri_ka=material["vbd"]["tri_ka_n_m"],
                               tri_kd=0.0, edge_ke=0.0, edge_kd=0.0, particle_radius=CONTACT_RADIUS,
                               label="garment")
        edge_ke = vbd_edge_stiffness(x, np.asarray(builder.edge_indices), bend_stiffness)
        builder.edge_bending_properties = [(float(k), 0.0) for k in edge_ke]
        builder.color(include_bending=True)
    else:
        SolverStyle3D.register_custom_attributes(builder)
        builder.default_edge_ke = material["style3d"]["edge_ke_nm"]  # edges take it without edge_aniso_ke
        style3d.add_cloth_mesh(builder, pos=wp.vec3(0.0), rot=wp.quat_identity(), vel=wp.vec3(0.0),
                               vertices=x, indices=faces.reshape(-1), density=area_density,
                               panel_verts=panel_coordinates(x, faces).reshape(-1, 2),
                               panel_indices=np.arange(3 * len(faces)),
                               tri_aniso_ke=wp.vec3(*material["style3d"]["tri_aniso_ke_n_m"]),
                               tri_kd=0.0, edge_kd=0.0, particle_radius=CONTACT_RADIUS, label="garment")
    return builder


def inside_depth(body_vertices: np.ndarray, body_faces: np.ndarray, points: np.ndarray, device) -> np.ndarray:
    """(P,) depth [m] of each point (P, 3) [m] inside the watertight body mesh (winding number), 0 outside."""
    from simgen.body.surface import project_to_surface

    sd = project_to_surface(points, body_vertices, body_faces, device=device).signed_distance
    return np.maximum(-sd, 0.0)


def _used_memory_mb(device) -> float | None:
    return (device.total_memory - device.free_memory) / 2**20 if device.is_cuda else None


def material_kwargs(material) -> dict:
    """The material keywords of :func:`build_newton_peer` / :func:`run_newton_peer` for one of our
    :class:`simgen.materials.Material` (area density [kg/m^2], Young's modulus [Pa], Poisson ratio,
    thickness [m], bending stiffness [N m]); damping and friction are not mapped (see the module doc)."""
    return {"area_density": material.area_density, "youngs_modulus": material.youngs_modulus,
            "poisson": material.poisson_ratio, "thickness": material.thickness,
            "bend_stiffness": material.bending_stiffness}


@dataclass
class NewtonPeer:
    """One Newton cloth scene, built and ready to step (:func:`build_newton_peer`).

    solver: "vbd" or "style3d"; model: the finalized ``newton.Model``; sim: the Newton solver;
    pipeline: the ``newton.CollisionPipeline``; contacts: the contact buffer passed to every step
    (None for SolverVBD, which detects into its own); states: the two ``newton.State`` buffers
    (a frame's result ends in ``states[0]``); control: ``model.control()``; substeps: solver steps
    per frame; dt [s]: one step; settings: the solver's JSON settings; material: the mapped
    coefficients (:func:`material_mapping`).
    """

    solver: str
    model: object
    sim: object
    pipeline: object
    contacts: object
    states: list
    control: object
    substeps: int
    dt: float
    settings: dict
    material: dict

    def frame(self, before_substep=None) -> None:
        """One frame of ``substeps`` solver steps; the result ends in ``states[0]``.

        before_substep: optional callable(i) run before substep i's collision detection (e.g. to
        move a collider); None in the timed benchmark (the frame is captured as one CUDA graph).
        """
        for i in range(self.substeps):
            state_in, state_out = self.states[i % 2], self.states[(i + 1) % 2]
            if before_substep is not None:
                before_substep(i)
            state_in.clear_forces()
            if self.contacts is not None:
                self.pipeline.collide(state_in, self.contacts)
            self.sim.step(state_in, state_out, self.control, self.contacts, self.dt)
        if self.substeps % 2:
            self.states[0].assign(self.states[1])

    def positions(self) -> np.ndarray:
        """The cloth positions [m] after the last frame, (instances * V, 3) float32 on the host."""
        return self.states[0].particle_q.numpy()


def build_newton_peer(solver: str, garment_vertices: np.ndarray, garment_faces: np.ndarray,
                      body_vertices: np.ndarray, body_faces: np.ndarray, *, instances: int = 1,
                      substeps: int = 10, fps: float = 30.0, iterations: int = 10, device=None,
                      area_density: float = 0.2, youngs_modulus: float = 0.7e5, poisson: float = 0.485,
                      thickness: float = 4.7e-4, bend_stiffness: float = 3.96e-5) -> NewtonPeer:
    """Build ``instances`` worlds of (cloth + static body mesh shape) and the Newton solver.

    Arguments as :func:`run_newton_peer` (garment and body vertices [m], y up; the body mesh starts
    at ``body_vertices``). Allocates on ``device`` (Warp's preferred one if None).
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
    dev = wp.get_device(device)
    material = material_mapping(area_density, youngs_modulus, poisson, thickness, bend_stiffness)
    with wp.ScopedDevice(dev):
        body_mesh = newton.Mesh(np.asarray(body_vertices, np.float32), np.asarray(body_faces, np.int32).reshape(-1),
                                compute_inertia=False)
        world = _world_builder(solver, garment_vertices, garment_faces, body_mesh, material, area_density,
                               bend_stiffness)
        scene = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=GRAVITY)
        if solver == "style3d":
            SolverStyle3D.register_custom_attributes(scene)
        scene.replicate(world, instances)
        model = scene.finalize(device=dev)
        model.soft_contact_ke = CONTACT_KE
        model.soft_contact_kd = CONTACT_KD
        model.soft_contact_mu = FRICTION

        pipeline = newton.CollisionPipeline(model, soft_contact_gap=CONTACT_GAP)
        if solver == "vbd":
            sim = SolverVBD(model, iterations=iterations, collision_pipeline=pipeline)
            contacts = None  # the solver detects into its own buffer at the start of every step
            settings = {"newton_solver": "SolverVBD", "iterations": iterations, "collide": "owned by the "
                        "solver, once per substep (PRE_INIT)"}
        else:
            config = SolverStyle3D.Config(iterations=iterations)
            with contextlib.redirect_stdout(sys.stderr):  # its precompute prints a timer line
                sim = SolverStyle3D(model, config=config)
            # No self-contact, as ours: zero the stiffness of its built-in cloth-cloth contacts (the body
            # contacts it evaluates from ``contacts`` stay on).
            sim.collision.stiff_vf = sim.collision.stiff_ee = sim.collision.stiff_ef = 0.0
            contacts = pipeline.contacts()
            settings = {"newton_solver": "SolverStyle3D", "iterations": iterations,
                        "linear_iterations": config.linear_iterations,
                        "collide": "CollisionPipeline.collide before every substep"}
        states = [model.state(), model.state()]
        control = model.control()
    return NewtonPeer(solver=solver, model=model, sim=sim, pipeline=pipeline, contacts=contacts, states=states,
                      control=control, substeps=substeps, dt=1.0 / (fps * substeps), settings=settings,
                      material=material)


def contact_settings() -> dict:
    """The body-contact settings both peers use (JSON)."""
    return {"particle_radius_m": CONTACT_RADIUS, "body_shape_margin_m": 0.0, "soft_contact_gap_m": CONTACT_GAP,
            "ke_n_m": CONTACT_KE, "kd_n_s_m": CONTACT_KD, "friction": FRICTION}


def run_newton_peer(solver: str, garment_vertices: np.ndarray, garment_faces: np.ndarray,
                    body_vertices: np.ndarray, body_faces: np.ndarray, *, instances: int, frames: int,
                    substeps: int = 10, fps: float = 30.0, iterations: int = 10, device: str | None = None,
                    warmup_frames: int = 2, area_density: float = 0.2, youngs_modulus: float = 0.7e5,
                    poisson: float = 0.485, thickness: float = 4.7e-4, bend_stiffness: float = 3.96e-5) -> dict:
    """Drape ``instances`` copies of the garment on the static body with a Newton solver and time it.

    Args:
        solver: "vbd" (SolverVBD, ``iterations`` iterations per substep) or "style3d" (SolverStyle3D,
            ``iterations`` non-linear iterations per substep, default 10 PCG iterations each).
        garment_vertices [m], (V, 3); garment_faces, int (F, 3): the garment on the body, y up.
        body_vertices [m], (B, 3); body_faces, int (G, 3): the watertight body mesh in rest pose, y up.
        instances: number of independent (cloth + body) copies, one Newton world each.
        frames: frames timed after ``warmup_frames`` untimed ones.
        substeps: solver steps per frame; fps: frames per second (dt = 1 / (fps * substeps) [s]).
        iterations: solver iterations per substep (see ``solver``).
        device: Warp device (default: Warp's preferred device).
        area_density [kg/m^2], youngs_modulus [Pa], poisson [-], thickness [m], bend_stiffness [N m]:
            our material, mapped to Newton's coefficients as the module docstring describes.

    Returns:
        A JSON-serialisable dict: timing (ms per frame median/mean, cloth-frames per second), device
        memory, sizes, the final cloth state (finite, y range, vertices inside the body) and the
        material and contact settings used.
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
    dev = wp.get_device(device)
    num_vertices = len(garment_vertices)

    with wp.ScopedDevice(dev):
        memory_before = _used_memory_mb(dev)
        t_build = time.perf_counter()
        peer = build_newton_peer(solver, garment_vertices, garment_faces, body_vertices, body_faces,
                                 instances=instances, substeps=substeps, fps=fps, iterations=iterations, device=dev,
                                 area_density=area_density, youngs_modulus=youngs_modulus, poisson=poisson,
                                 thickness=thickness, bend_stiffness=bend_stiffness)
        graph = None
        if dev.is_cuda:
            with wp.ScopedCapture(device=dev) as capture:
                peer.frame()
            graph = capture.graph

        def frame():
            if graph is not None:
                wp.capture_launch(graph)
            else:
                peer.frame()

        wp.synchronize_device(dev)
        build_s = time.perf_counter() - t_build
        memory_built = _used_memory_mb(dev)

        times = []
        for f in range(warmup_frames + frames):
            wp.synchronize_device(dev)
            t0 = time.perf_counter()
            frame()
            wp.synchronize_device(dev)
            if f >= warmup_frames:
                times.append(time.perf_counter() - t0)

        x = peer.positions().reshape(instances, num_vertices, 3)
        finite = bool(np.all(np.isfinite(x)))
        depth = inside_depth(body_vertices, body_faces, x.reshape(-1, 3), dev).reshape(instances, num_vertices)

    y0 = np.asarray(garment_vertices)[:, 1]
    y = x[..., 1]
    extent = y.max(axis=1) - y.min(axis=1)
    median = float(np.median(times)) * 1e3
    row = {
        "peer": f"newton-{solver}", "solver": solver, **peer.settings,
        "newton": newton.__version__, "warp": wp.__version__,
        "device": dev.name if dev.is_cuda else platform.processor() or "cpu", "device_alias": str(dev),
        "instances": instances, "worlds": "ModelBuilder.replicate: one world per instance, no cross-world contact",
        "vertices_per_instance": num_vertices, "triangles_per_instance": len(garment_faces),
        "frames": frames, "warmup_frames": warmup_frames, "substeps": substeps, "fps": fps, "dt_s": peer.dt,
        "cuda_graph": graph is not None, "graph_includes_collide": graph is not None,
        "self_contact": False,
        "ms_per_frame_median": median, "ms_per_frame_mean": float(np.mean(times)) * 1e3,
        "cloth_frames_per_s": instances * 1e3 / median,
        "build_s": build_s,
        "finite": finite,
        "y_min_initial": float(y0.min()), "y_min": float(np.nanmin(y)),
        "y_extent_initial": float(y0.max() - y0.min()),
        "y_extent_min": float(np.nanmin(extent)), "y_extent_max": float(np.nanmax(extent)),
        "mean_y_drop_mm": 1e3 * float(y0.mean() - np.nanmean(y)),
        "inside_count": int((depth > 0.0).sum()),
        "inside_count_max_per_instance": int((depth > 0.0).sum(axis=1).max()),
        "max_inside_depth_mm": 1e3 * float(depth.max()),
        "material": peer.material,
        "contact": {**contact_settings(), "body": "static mesh shape (body=-1) in every world"},
    }
    if memory_before is not None:
        row["gpu_memory_mb"] = memory_built - memory_before
        row["gpu_memory_mb_per_instance"] = row["gpu_memory_mb"] / instances
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--solver", choices=SOLVERS, default="vbd")
    parser.add_argument("--instances", type=int, nargs="+", default=[1])
    parser.add_argument("--frames", type=int, default=20, help="frames timed (after the warm-up frames)")
    parser.add_argument("--warmup-frames", type=int, default=2)
    parser.add_argument("--substeps", type=int, default=10)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--iterations", type=int, default=10, help="solver iterations per substep")
    parser.add_argument("--device", default=None)
    parser.add_argument("--garment", default="tshirt")
    parser.add_argument("--out", type=Path, default=None, help="also write all runs to this JSON file")
    args = parser.parse_args()

    from simgen.body import load
    from simgen._warp_log import quiet_warp
    from simgen.garment import load_garment

    quiet_warp()
    wp.init()
    body = load("open")
    garment = load_garment(args.garment, body=body)
    runs = []
    for n in args.instances:
        row = run_newton_peer(args.solver, garment.vertices, garment.faces, body.v_template, body.faces,
                              instances=n, frames=args.frames, substeps=args.substeps, fps=args.fps,
                              iterations=args.iterations, device=args.device, warmup_frames=args.warmup_frames)
        print(json.dumps(row), flush=True)
        runs.append(row)
    if args.out is not None:
        result = {"benchmark": "newton_peer", "garment": args.garment, "body_vertices": int(body.num_vertices),
                  "runs": runs}
        args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
