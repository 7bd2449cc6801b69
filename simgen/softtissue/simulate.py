"""simulate_softtissue(): the flesh of N body shapes doing one motion, as SoftSMPL's ground truth.

The flesh's nodes live in the unposed frame: node i at rest X_i (the shaped template) goes to
x_i = M_i (X_i + u_i) + t_i in the world, with (M_i, t_i) = sum_j w_ij A_j the body's blended
skinning transform (the same linear blend skinning as the skin's), so u is what the rig does not
explain and nothing is counted twice. Newton's law in the world, m x'' = R_i f_int(u) + m g, seen
from the node's moving frame (R_i: the rotation of M_i, its polar factor) and linearised in u, is

    m u'' + C u' + K u = m R_i^T (g - a_i),   a_i = sum_j w_ij A_j''(X_i)

with a_i the rig's acceleration of the node: the skeleton drives the flesh through its
acceleration and its orientation against gravity. Left out are the frame's inertial forces on u
itself (centrifugal, Coriolis, Euler: of order omega^2 |u| and 2 omega |u'|), a few per cent of
gravity on the torso for |u| of centimetres, and M_i's departure from a rotation near bent joints
(the linear blend's shrinkage), which u does not see.

The skeleton's transforms A_j(t) are the clip resampled at ``params.rate`` (240 Hz), low-passed
with a zero-phase 4th-order Butterworth at ``params.lowpass`` (12 Hz) entry by entry (on what a
straight line between the clip's ends leaves, so uniform motion stays uniform, and continued past
the ends by cubics so that the filter's start-up stays outside the clip: :func:`_lowpass`), and
differenced twice (central differences). The simulation starts at the static equilibrium of its
first step and outputs u at the body's vertices (the mesh's embedding) at ``params.fps`` (60):
SoftSMPL's Delta, the displacement in the unposed frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from simgen.errors import InputError
from simgen.softtissue.model import FleshModel
from simgen.softtissue.params import FleshParams
from simgen.softtissue.solver import FleshSolver

__all__ = ["simulate_softtissue", "simulate_softtissue_jobs", "skeleton_tracks", "rig_forces", "SoftTissueResult",
           "mean_speed"]


@dataclass
class SoftTissueResult:
    """One shape's simulated soft tissue (the fields of SoftSMPL's
    :class:`simgen.learn.softtissue.SoftTissueSequence`, which ``SoftTissueSequence.from_result`` makes).

    name: "<subject>_<motion>"; subject; motion; betas (B,); poses (T, 72) [rad] axis-angle; trans
    (T, 3) [m]; fps [1/s]; displacements (T, V, 3) [m]: Delta at the body's vertices in the unposed
    frame; meta: the parameters and the run's numbers (see :func:`simulate_softtissue`).
    """

    name: str
    subject: str
    motion: str
    betas: np.ndarray
    poses: np.ndarray
    trans: np.ndarray
    fps: float
    displacements: np.ndarray
    meta: dict = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return len(self.poses)


def mean_speed(displacements, fps: float) -> float:
    """[m/s] Mean vertex speed of displacements (T, V, 3) [m] at ``fps`` [1/s]: |Delta_t - Delta_{t-1}|
    x fps over frames and vertices (the thesis's Fig. 3.7 measure; 0 for one frame)."""
    d = np.asarray(displacements, dtype=np.float64)
    return float(np.linalg.norm(np.diff(d, axis=0), axis=-1).mean() * fps) if len(d) > 1 else 0.0


@wp.kernel(enable_backward=False)
def _rig_force(rest: wp.array(dtype=wp.vec3), weights: wp.array(dtype=wp.float32), nodes: int,
               node_instance: wp.array(dtype=wp.int32), transforms: wp.array(dtype=wp.mat44),
               accelerations: wp.array(dtype=wp.mat44), offset: int, mass: wp.array(dtype=wp.float32),
               pinned: wp.array(dtype=wp.int32), gravity: float, f: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    if pinned[i] != 0:
        f[i] = wp.vec3(0.0)
        return
    k = node_instance[i]
    n = i - k * nodes
    x = rest[i]
    frame = wp.mat33(0.0)
    acc = wp.vec3(0.0)
    for j in range(24):
        w = weights[n * 24 + j]
        if w > 0.0:
            a = transforms[offset + k * 24 + j]
            d = accelerations[offset + k * 24 + j]
            frame += w * wp.mat33(a[0, 0], a[0, 1], a[0, 2], a[1, 0], a[1, 1], a[1, 2], a[2, 0], a[2, 1], a[2, 2])
            acc += w * wp.vec3(d[0, 0] * x[0] + d[0, 1] * x[1] + d[0, 2] * x[2] + d[0, 3],
                               d[1, 0] * x[0] + d[1, 1] * x[1] + d[1, 2] * x[2] + d[1, 3],
                               d[2, 0] * x[0] + d[2, 1] * x[1] + d[2, 2] * x[2] + d[2, 3])
    # The rotation of the blended transform (its polar factor): near a bent joint the blend is no
    # rotation, and its inverse would scale the load by 1 / sigma_min.
    U = wp.mat33()
    sigma = wp.vec3()
    V = wp.mat33()
    wp.svd3(frame, U, sigma, V)
    rot = U * wp.transpose(V)
    f[i] = mass[i] * (wp.transpose(rot) * (wp.vec3(0.0, -gravity, 0.0) - acc))


def skeleton_tracks(body, clip, betas: np.ndarray, params: FleshParams) -> tuple[np.ndarray, np.ndarray, object]:
    """The joint transforms A (S, N, 24, 4, 4) and their second time derivative [1/s^2] at
    ``params.rate``, low-passed before differencing (module doc), for each shape of betas (N, B);
    and the clip at that rate."""
    from simgen.body.model import skinning_transforms
    from simgen.motion.ops import resample

    fine = resample(clip, params.rate)
    S = fine.num_frames
    if S < 3:
        raise InputError(f"motion {clip.name!r} is too short for the soft-tissue simulation ({clip.num_frames} frames)")
    A = np.stack([skinning_transforms(body, b, fine.poses, fine.trans) for b in np.atleast_2d(betas)], axis=1)
    A = _lowpass(A, params.lowpass, params.rate)
    h = 1.0 / params.rate
    dd = np.zeros_like(A)
    dd[1:-1] = (A[2:] - 2.0 * A[1:-1] + A[:-2]) / (h * h)
    dd[0], dd[-1] = dd[1], dd[-2]
    return A, dd, fine


def _lowpass(A: np.ndarray, cutoff: float, rate: float) -> np.ndarray:
    """A (S, ...) sampled at ``rate`` [1/s], low-passed along time at ``cutoff`` [Hz]: a zero-phase
    4th-order Butterworth on what the straight line between the ends leaves (a uniform motion stays
    exactly uniform), continued past each end by the cubic of its first (last) 0.1 s, so that the
    filter's start-up falls outside the clip and the ends keep their velocity, acceleration and jerk."""
    from scipy.signal import butter, filtfilt

    S = len(A)
    ramp = np.linspace(0.0, 1.0, S).reshape((S,) + (1,) * (A.ndim - 1))
    line = A[:1] + ramp * (A[-1:] - A[:1])
    r = (A - line).reshape(S, -1)
    pad = int(round(3.0 * rate / cutoff))
    n = min(S, max(3, int(round(0.1 * rate))))
    t = np.arange(n) / rate
    V = np.stack([np.ones(n), t, t * t, t ** 3], axis=1)
    head = np.linalg.lstsq(V, r[:n], rcond=None)[0]
    tail = np.linalg.lstsq(V, r[::-1][:n], rcond=None)[0]
    ext = -np.arange(pad, 0, -1) / rate                                   # times before the first sample
    W = np.stack([np.ones(pad), ext, ext ** 2, ext ** 3], axis=1)
    padded = np.concatenate([W @ head, r, (W @ tail)[::-1]])
    bb, aa = butter(4, cutoff / (0.5 * rate))
    out = filtfilt(bb, aa, padded, axis=0, padtype=None)[pad:pad + S]
    return line + out.reshape(A.shape)


def rig_forces(model: FleshModel, weights: wp.array, A: wp.array, dd: wp.array, step: int, out: wp.array) -> wp.array:
    """out = m R^T (g - a) per node (module doc) at step ``step`` of the uploaded tracks."""
    N = model.num_instances
    wp.launch(_rig_force, dim=model.total_nodes, device=model.device,
              inputs=[model.rest_positions, weights, model.num_nodes, model.node_instance, A, dd, step * N * 24,
                      model.node_mass, model.node_pinned, float(model.params.gravity)], outputs=[out])
    return out


@wp.kernel
def _tet_min_det(u: wp.array(dtype=wp.vec3), tets: wp.array(dtype=wp.vec4i), inv_rest: wp.array(dtype=wp.mat33),
                 tets_per_instance: int, out: wp.array(dtype=wp.float32)):
    """out[instance] = min(out[instance], det(I + grad u)) of each tetrahedron (> 0: not inverted; a
    non-finite u gives -1e30)."""
    t = wp.tid()
    k = tets[t]
    u0 = u[k[0]]
    a = u[k[1]] - u0
    b = u[k[2]] - u0
    c = u[k[3]] - u0
    ds = wp.mat33(a[0], b[0], c[0], a[1], b[1], c[1], a[2], b[2], c[2])     # columns: the edge vectors
    d = wp.determinant(wp.identity(n=3, dtype=float) + ds * inv_rest[t])
    if not wp.isfinite(d):
        d = -1.0e30
    wp.atomic_min(out, t // tets_per_instance, d)


def simulate_softtissue(body, clip, betas=None, params: FleshParams | None = None, *, mesh=None, device=None,
                        subjects=None, progress=None) -> list:
    """Simulate the flesh of each shape in ``betas`` (N, B') doing ``clip``; one
    :class:`SoftTissueResult` per shape, at ``params.fps``.

    body: :class:`BodyModel` or a body name; clip: :class:`MotionClip` or a library name; betas:
    None (the template) or (N, B'); mesh: a :class:`FleshMesh` or its file (None: the body's
    bundled one); subjects: N names (default "shape<k>"); progress(done, total) after each output
    frame. Each sequence's ``meta`` holds the parameters, the free layer [m], the pins added to
    floating free sets, the PCG iterations (largest), and ``min_det``, the smallest
    det(I + grad u) over every tetrahedron and frame (> 0: none inverted).
    """
    from simgen import body as body_pkg
    from simgen.body.model import BodyModel
    from simgen.motion.clip import MotionClip
    from simgen.motion.library import load_motion

    body = body if isinstance(body, BodyModel) else body_pkg.load(body)
    clip = clip if isinstance(clip, MotionClip) else load_motion(clip)
    b = body.check_betas(np.zeros((1, body.num_betas)) if betas is None else np.atleast_2d(betas))
    names = list(subjects) if subjects is not None else [f"shape{k}" for k in range(len(b))]
    return simulate_softtissue_jobs(body, [(clip, b[k], names[k]) for k in range(len(b))], params, mesh=mesh,
                                    device=device, progress=progress)


def simulate_softtissue_jobs(body, jobs, params: FleshParams | None = None, *, mesh=None, device=None,
                             progress=None) -> list:
    """One batched simulation of several (clip, betas (B',), subject) jobs, clips and shapes mixed (the
    dataset generator's unit); one :class:`SoftTissueResult` per job, in order, as
    :func:`simulate_softtissue` gives them. A clip shorter than the longest holds its last pose
    until the batch ends; only its own frames are returned, but its ``min_det`` covers the held
    frames too, and the PCG counts in ``meta`` are the whole batch's."""
    from dataclasses import asdict

    from simgen.motion.ops import resample
    from simgen.softtissue.mesh import FleshMesh, flesh_mesh

    p = params if params is not None else FleshParams()
    if mesh is None or not isinstance(mesh, FleshMesh):
        mesh = flesh_mesh(body, mesh)
    if not jobs:
        raise InputError("simulate_softtissue_jobs needs at least one (clip, betas, subject) job")
    b = np.concatenate([body.check_betas(np.atleast_2d(np.asarray(j[1], dtype=np.float64))) for j in jobs])
    N = len(jobs)
    model = FleshModel.for_body(mesh, body, b, p, device=device)
    solver = FleshSolver(model)
    A, dd, steps = _batched_tracks(body, [j[0] for j in jobs], b, p)
    dev = model.device
    As = wp.array(A.reshape(-1, 4, 4).astype(np.float32), dtype=wp.mat44, device=dev)
    dds = wp.array(dd.reshape(-1, 4, 4).astype(np.float32), dtype=wp.mat44, device=dev)
    weights = wp.array(np.tile(mesh.weights.astype(np.float32), (N, 1)).reshape(-1), device=dev)
    f = wp.zeros(model.total_nodes, dtype=wp.vec3, device=dev)
    every = int(round(p.rate / p.fps))
    out_clips = [resample(j[0], p.fps) for j in jobs]
    counts = [min(c.num_frames, (S - 1) // every + 1) for c, S in zip(out_clips, steps)]
    frames = max(counts)
    h = 1.0 / p.rate
    min_det = wp.full(N, 1e30, dtype=wp.float32, device=dev)

    def record(u_dev) -> np.ndarray:
        wp.launch(_tet_min_det, dim=model.num_tets_total, device=dev,
                  inputs=[u_dev, model.tets, model.inv_rest, mesh.num_tets], outputs=[min_det])
        return mesh.skin(u_dev.numpy().reshape(N, -1, 3)).astype(np.float32)

    solver.static(rig_forces(model, weights, As, dds, 0, f))
    deltas, cg = [], 0
    for k in range(frames):
        if k > 0:
            for s in range((k - 1) * every + 1, k * every + 1):
                solver.step(rig_forces(model, weights, As, dds, s, f), h)
                cg = max(cg, solver.cg_iterations)
        deltas.append(record(solver.u))
        if progress is not None:
            progress(k + 1, frames)
    disp = np.stack(deltas, axis=1)                                                         # (N, T, V, 3)
    dets = min_det.numpy()
    out = []
    for k, (clip, _, name) in enumerate(jobs):
        T = counts[k]
        meta = {"source": "simgen.softtissue simulation", "params": asdict(p), "layer_m": model.layer[k],
                "extra_pins": int(model.extra_pins[k]), "cg_iterations_max": int(cg),
                "cg_capped": int(solver.cg_capped), "min_det": float(dets[k]),
                "mesh": {"nodes": mesh.num_nodes, "tets": mesh.num_tets, "pinned": int(model.pinned[k].sum())}}
        out.append(SoftTissueResult(name=f"{name}_{clip.name}", subject=name, motion=clip.name, betas=b[k],
                                    poses=out_clips[k].poses[:T].reshape(T, -1), trans=out_clips[k].trans[:T],
                                    fps=p.fps, displacements=disp[k, :T], meta=meta))
    return out


def _batched_tracks(body, clips: list, betas: np.ndarray, params: FleshParams) -> tuple[np.ndarray, np.ndarray, list]:
    """:func:`skeleton_tracks` of each (clip, shape) job side by side, (S, N, 24, 4, 4) each, and each
    job's own steps: a clip of fewer steps than the longest holds its last transforms (zero
    acceleration) to the end."""
    by_clip: dict[int, list[int]] = {}            # one skeleton_tracks call per clip, for all its shapes
    for k, clip in enumerate(clips):
        by_clip.setdefault(id(clip), []).append(k)
    tracks: list = [None] * len(clips)
    for ks in by_clip.values():
        a, d, _ = skeleton_tracks(body, clips[ks[0]], betas[ks], params)
        for j, k in enumerate(ks):
            tracks[k] = (a[:, j:j + 1], d[:, j:j + 1])
    S = max(len(a) for a, _ in tracks)
    A = np.empty((S, len(clips), 24, 4, 4))
    dd = np.zeros_like(A)
    for k, (a, d) in enumerate(tracks):
        A[:len(a), k], A[len(a):, k] = a[:, 0], a[-1, 0]
        dd[:len(d), k] = d[:, 0]
    return A, dd, [len(a) for a, _ in tracks]
