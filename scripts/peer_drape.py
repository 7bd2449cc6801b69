"""Drape test (issue 21, part 1): one T-shirt on one body brought into a relaxed standing pose, by
our solver and by NVIDIA Newton 1.8's SolverVBD and SolverStyle3D in the same run, so that what
the solver does can be told apart from what the garment template does.

Measured on every stepped frame against the posed body surface (scripts/fit_report.py's
``frame_metrics``: ``simgen.body.surface.SurfaceMesh(body, faces).project(cloth)``, winding-number
sign):

- hem_cling: share of the garment's lowest 10 cm (by the template's height) within 3 mm of the body;
- sleeve_gap [m]: the largest distance from the body of a sleeve vertex (a vertex whose dominant
  skinning joint is an SMPL shoulder, elbow or wrist, 16-21);
- hem_mean_distance [m]: mean distance of the hem vertices from the body; inside_share: share of
  all cloth vertices inside the body; y_min [m]: the lowest cloth vertex; finite: no NaN/inf;
  arm_angle [deg]: the larger angle of the upper arms from the downward vertical.

Each run reports them per frame (``per_frame``, in --out), at the end of the transition (the last
ramp frame: the body has just reached the standing pose) and at the end of the run, and the
largest hem_cling over the frames after the transition and the largest sleeve_gap over those
with the arms down (both upper arms within 45 deg of the vertical; fit_report.py).

Scene (one for all solvers):

- Body: the open body (13,348 vertices), beta = 0 (--betas to change), y up. It starts in its rest
  T-pose and follows our start protocol (simgen/sim/protocol.py, ``ProtocolSchedule``): relax
  (--relax-frames, 15: T-pose held), ramp (--ramp-frames, 30: joint rotations slerped from the rest
  pose to the target pose and betas 0 -> target, per substep), rest (--rest-frames, 15: target
  held), then --frames - 1 more frames held (our output frames are --frames; output frame 0 is the
  rest phase's end state and takes no step).
- Target pose: frame --pose-frame of the bundled motion ``idle_sway``, held still (a clip of that
  frame's joint rotations and root translation repeated at --fps). Default frame 81 (t = 2.7 s),
  not frame 0: every procedural clip starts at the exact rest pose and lowers the arms in its first
  ~0.9 s, so frame 0 is the T-pose itself (``--pose-frame 0`` reproduces that: nothing moves).
  Frame 81 is the sway's neutral point: arms hanging (collars ~14 deg and shoulders ~44 deg turned
  from the rest pose, elbows bent 12 deg), pelvis level (0.1 deg), root translation
  (-0.001, -0.016, 0) m, neck and head each turned ~12 deg.
- --motion NAME (e.g. ``walk``, the demo's) plays that clip instead of holding a pose, after the
  same protocol: the same comparison in motion, where our T-shirt's hem clings (issue 21).
- Garment: ``load_garment(--garment, body=body)``: template vertices on the T-pose body, moved with
  the body by the pose's root translation before the first frame, as ours does.
- One body trajectory: :class:`BodyTrajectory` poses the body at the end of every substep with the
  same ``ProtocolSchedule`` targets and ``WarpBody`` calls our FrameRunner makes; ours poses its own
  body (checked against these vertices on the output frames: ``body_match_max_m``), Newton's body
  mesh is set to them.

Solvers:

- ours: ``simulate_batch`` with one job on the held clip, the SimulationConfig of each --variants
  entry (scripts/fit_report.py's ``variants()``: "default", "preset", ...), record_body=True.
- vbd, style3d: scripts/bench_newton_peer.py's scene (``build_newton_peer``; its module docstring
  gives the material and contact mapping), one world, the material of our "default" variant (the
  garment's default, cotton for the T-shirts; --newton-material to change), 10 substeps per 30 fps
  frame, 10 VBD iterations / Style3D's defaults (10 non-linear iterations of 10 PCG iterations),
  gravity -9.81 m/s^2 along y, friction 0.3, contact radius 2 mm plus a 2 mm detection gap, no
  self-contact, no CUDA graph. The body is a static (body = -1) triangle-mesh shape whose Warp mesh
  is moved before every substep (:class:`MovingBodyMesh`): its points set to the body at the
  substep's end, its velocities to (new - old) / dt [m/s], then refit. Newton's particle-shape
  contact query reads both (``wp.mesh_eval_velocity`` -> ``Contacts.soft_contact_body_vel``), and
  both solvers take that velocity as the body's in their contact friction and damping.

Prints one JSON line per run (solver, or solver and variant) without the per-frame series; --out
writes all runs with their series and the settings (device, commit from SIMGEN_COMMIT or git,
garment, frames, pose, materials). --save-npz DIR writes <label>.npz per run: the cloth and the body
at the transition's end and at the end, with both face lists.

    python scripts/peer_drape.py --device cuda:0 --garment tshirt --frames 120 \\
        --solvers ours vbd style3d --variants default preset --out drape.json [--save-npz DIR]

    python scripts/peer_drape.py --device cuda:0 --motion walk --frames 91 --solvers ours vbd style3d

The Newton part needs ``import newton`` (1.8); ``--solvers ours`` runs without it (a CPU check:
``--device cpu --garment tshirt_1k --frames 12 --solvers ours``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fit_report  # noqa: E402

SOLVERS = ("ours", "vbd", "style3d")
MOTION = "idle_sway"
DEFAULT_POSE_FRAME = 81  # idle_sway at t = 2.7 s: arms down, pelvis level (module docstring)
# Per-frame metrics (fit_report.frame_metrics) and the unit suffix of their JSON keys.
METRICS = (("hem_cling", ""), ("sleeve_gap", "_m"), ("hem_mean_distance", "_m"), ("inside_share", ""),
           ("y_min", "_m"), ("arm_angle", "_deg"))


def newton_peer_module():
    """scripts/bench_newton_peer.py (it imports Newton); exits with one sentence where Newton is missing."""
    try:
        import bench_newton_peer
    except ImportError as exc:
        raise SystemExit(f"peer_drape.py: --solvers vbd/style3d need NVIDIA Newton (import newton, 1.8), which "
                         f"cannot be imported here ({exc}); run with --solvers ours or where Newton is "
                         f"installed.") from None
    return bench_newton_peer


def played_clip(name: str, frames: int, fps: float):
    """The bundled or AMASS motion ``name`` (resampled to ``fps`` [1/s] by the protocol's schedule,
    as the simulation does); it must last ``frames`` output frames."""
    from simgen.errors import InputError
    from simgen.motion import load_motion

    try:
        clip = load_motion(name)
    except InputError as exc:
        raise SystemExit(f"--motion: {exc}") from None
    if (clip.num_frames - 1) / clip.fps < (frames - 1) / fps:
        raise SystemExit(f"--motion {name} lasts {(clip.num_frames - 1) / clip.fps:.2f} s, shorter than --frames "
                         f"{frames} at {fps:g} fps")
    return clip


def held_clip(pose_frame: int, frames: int, fps: float):
    """A MotionClip holding frame ``pose_frame`` of MOTION (joint rotations [rad], root translation
    [m]) still for ``frames`` frames (at least 2) at ``fps`` [1/s]."""
    from simgen.motion import MotionClip, load_motion

    src = load_motion(MOTION)
    if not 0 <= pose_frame < src.num_frames:
        raise SystemExit(f"--pose-frame must be in [0, {src.num_frames - 1}] for {MOTION}, got {pose_frame}")
    n = max(int(frames), 2)
    one = slice(pose_frame, pose_frame + 1)
    return MotionClip(name=f"{MOTION}@{pose_frame}_held", fps=fps, poses=np.repeat(src.poses[one], n, axis=0),
                      trans=np.repeat(src.trans[one], n, axis=0),
                      meta={"source": MOTION, "frame": pose_frame, "time_s": pose_frame / src.fps})


class BodyTrajectory:
    """The body [m] at the end of every substep of every stepped frame, posed as ours poses it.

    One :class:`simgen.sim.protocol.ProtocolSchedule` (the targets) and one
    :class:`simgen.body.warp_lbs.WarpBody` (the skinning), called as
    :class:`simgen.sim.frame_runner.FrameRunner` calls them: start pose (rest pose at the clip's
    first root translation), then per substep re-shape while the betas change, and pose.

    body: BodyModel; clip: the MotionClip (held or played); betas: target shape (B',); config: the
    SimulationConfig giving fps, substeps and the protocol's frame counts; frames: our output frames.

    steps: the stepped frames [(phase, k)] in order; trans0 [m] (3,): the root translation;
    start (Vb, 3): the body before the first frame; ends (T, Vb, 3) float32: the body at the end of
    each stepped frame; faces (Fb, 3) int32; transition_end: index in ``steps`` of the last ramp frame.
    """

    def __init__(self, body, clip, betas, config, frames: int, device: str) -> None:
        from simgen.sim.protocol import ProtocolSchedule

        nb = max(body.num_betas, 1)
        b = np.zeros((1, nb))
        b[0, :len(betas)] = betas
        self.body, self.device, self.substeps = body, device, config.substeps
        self.schedule = ProtocolSchedule([clip], b, config.fps or clip.fps, config.substeps,
                                         relax_frames=config.relax_frames, ramp_frames=config.ramp_frames,
                                         rest_frames=config.rest_frames, animate_frames=frames)
        self.steps = [f for f in self.schedule.frames if self.schedule.steps(*f)]
        self.transition_end = config.relax_frames + config.ramp_frames - 1
        self.trans0 = self.schedule.trans0[0]
        self.faces = np.asarray(body.faces, dtype=np.int32)
        self.start = self._reset()
        self.ends = np.stack([sub[-1] for _, sub in self.frames()])

    def _pose(self, quats: np.ndarray, trans: np.ndarray) -> np.ndarray:
        """Pose from joint rotations xyzw (1, 24, 4) and root translation [m] (1, 3); (Vb, 3) float32."""
        import warp as wp

        q = wp.array(np.ascontiguousarray(quats, dtype=np.float32), dtype=wp.quat, device=self.device)
        t = wp.array(np.ascontiguousarray(trans, dtype=np.float32), dtype=wp.vec3, device=self.device)
        return self._wbody.pose_from_quats(q, t).numpy()[0].copy()

    def _reset(self) -> np.ndarray:
        """A fresh WarpBody in the start pose (as simgen.sim.batch.setup_batch); its vertices (Vb, 3)."""
        from simgen.body.warp_lbs import WarpBody

        self._wbody = WarpBody(self.body, max_batch=1, device=self.device)
        self._wbody.set_shape(np.zeros((1, self.body.num_betas)), num_instances=1)
        self._betas_now = np.zeros((1, self.schedule.betas.shape[1]))
        return self._pose(*self.schedule.start_pose())

    def frames(self):
        """Yield ((phase, k), (S, Vb, 3) float32: the body at each substep's end) per stepped frame."""
        import warp as wp

        self._reset()
        for phase, k in self.steps:
            q, tr, bt = self.schedule.body_targets(phase, k)
            reshape = self.body.num_betas > 0 and not np.all(bt == self._betas_now[None])
            out = []
            for s in range(self.substeps):
                if reshape:
                    self._wbody.set_shape(wp.array(np.ascontiguousarray(bt[s], dtype=np.float32), dtype=wp.float32,
                                                   device=self.device))
                out.append(self._pose(q[s], tr[s]))
            self._betas_now = np.array(bt[-1])
            yield (phase, k), np.stack(out)


class MovingBodyMesh:
    """The Warp mesh behind the Newton body shape, moved before every substep.

    Newton keeps a mesh shape's geometry as a ``wp.Mesh`` whose id is ``model.shape_source_ptr[shape]``
    (made by ``newton.Mesh.finalize`` in ``ModelBuilder.finalize``; the ``newton.Mesh`` stays in
    ``model.shape_source[shape]`` with that wp.Mesh as its ``mesh``). The particle-shape contact kernel
    (``create_soft_contacts``) queries it at every detection: the contact point from its ``points``,
    the body velocity from its ``velocities`` (``wp.mesh_eval_velocity``, into
    ``Contacts.soft_contact_body_vel``). :meth:`move` assigns both and refits the BVH.

    model: the finalized newton.Model with exactly one mesh shape (the body); start [m] (Vb, 3):
    the body the mesh was built on.
    """

    def __init__(self, model, start: np.ndarray) -> None:
        import newton

        types = model.shape_type.numpy()
        shapes = [i for i, t in enumerate(types) if int(t) == int(newton.GeoType.MESH)]
        if len(shapes) != 1:
            raise RuntimeError(f"expected one mesh shape (the body) in the Newton model, found {len(shapes)}")
        self.shape = shapes[0]
        ptr = int(model.shape_source_ptr.numpy()[self.shape])
        src = model.shape_source[self.shape]
        candidates = [getattr(src, "mesh", None), *getattr(src, "_finalized_meshes", {}).values(),
                      *getattr(model, "_mesh_keep_alive", [])]
        found = [m for m in candidates if m is not None and int(m.id) == ptr]
        if not found:
            raise RuntimeError("found no wp.Mesh with the body shape's id (model.shape_source_ptr) among "
                               "model.shape_source[shape].mesh and the model's kept meshes")
        self.mesh = found[0]
        self.has_velocities = self.mesh.velocities is not None
        sdf = getattr(model, "_shape_sdf_index", None)
        self.has_sdf = None if sdf is None else bool(sdf.numpy()[self.shape] >= 0)
        self._last = np.asarray(start, dtype=np.float32)

    def move(self, points: np.ndarray, dt: float) -> None:
        """Set the body to ``points`` [m] (Vb, 3), reached over ``dt`` [s] from the last ones."""
        p = np.ascontiguousarray(points, dtype=np.float32)
        if self.has_velocities:
            self.mesh.velocities.assign((p - self._last) / dt)
        self.mesh.points.assign(p)
        self.mesh.refit()
        self._last = p


def summarize(series: list[dict], transition_end: int, total: int) -> dict:
    """JSON fields of one run from its per-frame metrics (a diverged run's series stops early):
    each metric at the transition's end and at the end (None if not reached), the largest
    hem_cling after the transition and sleeve_gap there with the arms down (fit_report's
    ``arms_down_max``; None if they never are), and the per-frame lists."""
    row = {}
    for tag, t in (("transition_end", transition_end), ("end", total - 1)):
        for key, unit in METRICS:
            row[f"{key}_{tag}{unit}"] = series[t][key] if t < len(series) else None
    hold = series[transition_end + 1:]
    row["hem_cling_max_after_transition"] = max((m["hem_cling"] for m in hold), default=None)
    row["sleeve_gap_arms_down_max_after_transition_m"] = fit_report.arms_down_max(hold)
    row["per_frame"] = {key + unit: [m[key] for m in series] for key, unit in METRICS}
    return row


def _keep(x: np.ndarray, t: int, traj: BodyTrajectory, kept: dict) -> None:
    """Keep cloth positions x [m] of stepped frame t if it is the transition's end or the last."""
    for tag, at in (("transition_end", traj.transition_end), ("end", len(traj.steps) - 1)):
        if t == at:
            kept[f"positions_{tag}"] = np.asarray(x, dtype=np.float32).copy()
            kept[f"body_{tag}"] = traj.ends[t]


def run_ours(variant: str, garment, body, clip, traj: BodyTrajectory, args, parts) -> tuple[dict, dict]:
    """Our solver on the clip (held or played) with variant ``variant``; the JSON row and the arrays to save."""
    from simgen.sim import SimulationFailure, SimulationJob, simulate_batch

    cfg = fit_report.variant_config(variant, **protocol_settings(args), record_body=True, device=args.device)
    if any(getattr(cfg, k) != v for k, v in protocol_settings(args).items()):
        raise SystemExit(f"variant {variant!r} changes the protocol; the body trajectory would differ")
    t0 = time.perf_counter()
    (res,) = simulate_batch(garment, body, [SimulationJob(clip, betas=args.betas, frames=args.frames,
                                                          key=variant)], cfg)
    wall = time.perf_counter() - t0
    row = {"solver": "ours", "variant": variant, "label": f"ours-{variant}", "wall_s": wall,
           "material": cfg.resolve_material(garment).name}
    if isinstance(res, SimulationFailure):
        return {**row, "finite": False, "error": f"{res.phase} frame {res.frame}: {res.message}"}, {}
    xs = np.concatenate([res.protocol_positions, res.positions[1:]])
    P = len(res.protocol_positions)
    recorded = np.concatenate([traj.ends[P - 1:P], traj.ends[P:]])  # output frame 0 = the rest phase's end
    row["body_match_max_m"] = float(np.abs(res.body_vertices - recorded).max())
    row["body_faces_match"] = bool(np.array_equal(res.body_faces, traj.faces))
    row["initial_inside_count"] = int(res.metadata["initial_inside"])
    row["retries"] = int(res.metadata["retries"])
    series, kept = [], {}
    for t, x in enumerate(xs):
        series.append(fit_report.frame_metrics(x, traj.ends[t], traj.faces, *parts, args.device))
        _keep(x, t, traj, kept)
    row["finite"] = bool(np.all(np.isfinite(xs)))
    return {**row, **summarize(series, traj.transition_end, len(traj.steps))}, kept


def run_newton(solver: str, garment, material, traj: BodyTrajectory, args, parts) -> tuple[dict, dict]:
    """A Newton peer ("vbd" or "style3d") on the moving body; the JSON row and the arrays to save."""
    import warp as wp

    peer_mod = newton_peer_module()
    dev = wp.get_device(args.device)
    x0 = (np.asarray(garment.vertices, dtype=np.float64) + traj.trans0).astype(np.float32)
    t0 = time.perf_counter()
    with wp.ScopedDevice(dev):
        peer = peer_mod.build_newton_peer(solver, x0, garment.faces, traj.start, traj.faces, instances=1,
                                          substeps=args.substeps, fps=args.fps, iterations=args.iterations,
                                          device=dev, **peer_mod.material_kwargs(material))
        body = MovingBodyMesh(peer.model, traj.start)
        series, kept, diverged = [], {}, None
        for t, (_, sub) in enumerate(traj.frames()):
            peer.frame(before_substep=lambda i: body.move(sub[i], peer.dt))
            x = peer.positions()
            if not np.all(np.isfinite(x)):
                diverged = t
                break
            series.append(fit_report.frame_metrics(x, traj.ends[t], traj.faces, *parts, args.device))
            _keep(x, t, traj, kept)
    row = {"solver": solver, "variant": None, "label": f"newton-{solver}", "wall_s": time.perf_counter() - t0,
           **peer.settings, "newton": peer_mod.newton.__version__, "material": material.name,
           "material_mapping": peer.material, "contact": peer_mod.contact_settings(),
           "body_collider": {"shape": "static triangle mesh (body=-1), points and velocities set and refit "
                                      "before every substep", "mesh_velocities": body.has_velocities,
                             "shape_sdf": body.has_sdf},
           "finite": diverged is None, "diverged_at_frame": diverged}
    return {**row, **summarize(series, traj.transition_end, len(traj.steps))}, kept


def protocol_settings(args) -> dict:
    """The SimulationConfig fields that fix the body trajectory (frame rate [1/s], substeps, protocol)."""
    return {"fps": args.fps, "substeps": args.substeps, "relax_frames": args.relax_frames,
            "ramp_frames": args.ramp_frames, "rest_frames": args.rest_frames}


def parse_args(argv=None):
    from simgen.sim.config import SimulationConfig

    base = SimulationConfig()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--garment", default="tshirt")
    p.add_argument("--frames", type=int, default=120, help="our output frames after the protocol (held pose)")
    p.add_argument("--solvers", nargs="+", default=list(SOLVERS), choices=SOLVERS)
    p.add_argument("--variants", nargs="+", default=["default", "preset"], choices=list(fit_report.variants()),
                   help="our solver's variants (scripts/fit_report.py)")
    p.add_argument("--betas", type=float, nargs="+", default=None, help="body shape (default: zeros)")
    p.add_argument("--pose-frame", type=int, default=DEFAULT_POSE_FRAME, help=f"frame of {MOTION} to hold")
    p.add_argument("--motion", default=None, help="play this motion instead of holding a pose (e.g. walk)")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--substeps", type=int, default=base.substeps)
    p.add_argument("--relax-frames", type=int, default=base.relax_frames)
    p.add_argument("--ramp-frames", type=int, default=base.ramp_frames)
    p.add_argument("--rest-frames", type=int, default=base.rest_frames)
    p.add_argument("--iterations", type=int, default=10, help="Newton solver iterations per substep")
    p.add_argument("--newton-material", default=None, help="material preset for Newton (default: ours' default)")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--save-npz", type=Path, default=None, metavar="DIR")
    args = p.parse_args(argv)
    if args.frames < 1:
        p.error("--frames must be >= 1")
    return args


def setup(args):
    """Body, garment, hem/sleeve masks, the clip (held or played), body trajectory and the JSON header."""
    import warp as wp

    from simgen._warp_log import quiet_warp
    from simgen.body import load as load_body
    from simgen.garment import load_garment
    from simgen.sim import SimulationConfig

    quiet_warp()
    body = load_body("open")
    garment = load_garment(args.garment, body=body)
    parts = fit_report.garment_parts(garment)
    clip = (held_clip(args.pose_frame, args.frames, args.fps) if args.motion is None
            else played_clip(args.motion, args.frames, args.fps))
    traj = BodyTrajectory(body, clip, args.betas or [], SimulationConfig(**protocol_settings(args)), args.frames,
                          args.device)
    x0 = (np.asarray(garment.vertices, dtype=np.float64) + traj.trans0).astype(np.float32)
    pose = {**clip.meta} if args.motion is None else {"motion": args.motion, "fps": clip.fps}
    pose["root_translation_m"] = traj.trans0.tolist()
    header = {"benchmark": "peer_drape", "device": wp.get_device(args.device).name, "device_alias": args.device,
              "commit": fit_report.commit(), "warp": wp.__version__, "garment": args.garment,
              "garment_vertices": int(len(garment.vertices)), "hem_vertices": int(parts[0].sum()),
              "sleeve_vertices": int(parts[1].sum()), "body": "open", "body_vertices": int(body.num_vertices),
              "betas": args.betas or [], "pose": pose,
              "frames": args.frames, "stepped_frames": len(traj.steps), "transition_end_frame": traj.transition_end,
              **protocol_settings(args), "newton_iterations": args.iterations,
              "initial": fit_report.frame_metrics(x0, traj.start, traj.faces, *parts, args.device), "runs": []}
    return body, garment, parts, clip, traj, header


def main(argv=None) -> int:
    args = parse_args(argv)
    if set(args.solvers) - {"ours"}:
        newton_peer_module()  # fail before our runs, not after them
    body, garment, parts, clip, traj, info = setup(args)

    def emit(row: dict, kept: dict) -> None:
        print(json.dumps({k: v for k, v in row.items() if k != "per_frame"}), flush=True)
        info["runs"].append(row)
        if args.out is not None:  # after every run, so a cut run keeps what it measured
            args.out.write_text(json.dumps(info, indent=2) + "\n")
        if args.save_npz is not None and kept:
            args.save_npz.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(args.save_npz / f"{row['label']}.npz", faces=np.asarray(garment.faces, np.int32),
                                body_faces=traj.faces, **kept)

    for solver in args.solvers:
        if solver == "ours":
            for variant in args.variants:
                emit(*run_ours(variant, garment, body, clip, traj, args, parts))
        else:
            from simgen.materials import get_material
            from simgen.sim import SimulationConfig

            material = (SimulationConfig().resolve_material(garment) if args.newton_material is None
                        else get_material(args.newton_material))
            emit(*run_newton(solver, garment, material, traj, args, parts))
    return 0


if __name__ == "__main__":
    sys.exit(main())
