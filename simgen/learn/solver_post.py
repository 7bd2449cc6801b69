"""The cloth solver as the post-process of learned garments: implicit steps from the prediction.

A learned garment model predicts every vertex on its own, so its triangles are strained by the
regression errors and some vertices lie inside the body; the thesis's push
(:func:`simgen.learn.collision.push_out`) moves them out and strains the cloth further, and the
metric post-process (:class:`simgen.learn.relax.MetricRelax`) keeps stretch where a prediction that
lay inside the torso is pushed out against the arm (BENCHMARKS.md). :class:`SolverPostProcess`
hands each predicted frame to the simulation's own solver (:class:`simgen.sim.ImplicitSolver`, with
the dataset's material and solver settings): the cloth starts at the prediction, at rest, on the
frame's posed body (held still), and steps ``substeps`` substeps of ``duration / substeps`` each
(by default 5 of 1/75 s).
The first substep, backward Euler from rest, minimises the cloth's energy plus the inertia term
sum_v m_v |x_v - p_v|^2 / (2 h^2): a metric relaxation tied to the prediction p, with the
membrane, bending and contact laws and the contact rules (penalty, projection, the body part rule,
friction) the ground truth was made with. The later substeps carry on from there as a short
simulation (their inertia term ties to x_k + h v_k), in which the strain the first one left
relaxes and the pushed-out vertices settle. Gravity acts on the way (over the default 1/15 s a free
hem would fall 2.6 cm; a supported one sags far less).

The substeps are longer than the dataset's (1/300 s): a longer step ties the cloth less to the
prediction and relaxes more strain per solve (every solve here runs to the PCG's cap whatever its
length), while the guard splits more of them. From fit-only predictions of the thesis-tshirt
model (the hop and dance against CPU-simulated ground truth) 20 substeps of 1/300 s left 1.7x the
simulation's strain energy, 5 of 1/75 s 2.8x for half the CG work (its guard's retries counted)
and 10 of 1/300 s 3.4x for about the same work, all at the same vertex error; a third Newton
iteration per substep relaxes more but moves the cloth off the prediction (BENCHMARKS.md), so the
post-process takes two (:data:`NEWTON_ITERATIONS`) whatever the store's solver took (three since
2026-11-29, two before).

Every frame is its own cloth instance on its own body; a call steps its frames ``chunk`` at a time,
each chunk from a clean solver (no friction contacts or CG guesses carried over). A frame fails
when its steps diverged (:class:`simgen.sim.SolverDivergedError`, or the guard still failing after
its retries, which the solver keeps as "unresolved"), or when they left a triangle stretched past
the dataset check's limit (:data:`simgen.dataset.quality.DEFAULT_MAX_STRAIN`) and further than the
prediction had it: on a held-out lunge of the thesis-tshirt model one frame of 17,615 came back
kilometres away with no error raised (BENCHMARKS.md). Failed frames are stepped once more with
twice the substeps of half the length (the same simulated time, as the generator's retries do);
those that fail again keep the raw prediction. :meth:`SolverPostProcess.report` counts both.
Waistband attachments are not modelled: they hold a garment over a whole sequence, and these steps
last two frames' time.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import torch

from simgen.dataset.quality import DEFAULT_MAX_STRAIN
from simgen.errors import InputError

__all__ = ["DEFAULT_DURATION", "DEFAULT_SUBSTEPS", "NEWTON_ITERATIONS", "SolverPostProcess",
           "solver_config_from_attrs"]

#: Substeps per frame and the simulated time they span [s] (module doc).
DEFAULT_SUBSTEPS = 5
DEFAULT_DURATION = 1.0 / 15.0
#: Newton iterations per substep of the post-process (module doc), in place of the store's.
NEWTON_ITERATIONS = 2


def solver_config_from_attrs(attrs: dict):
    """The :class:`simgen.sim.SolverConfig` of a store's root attributes (their ``solver`` entry, as
    :func:`simgen.dataset.generate_dataset` writes it, non-finite floats as null); InputError if
    absent."""
    import dataclasses

    from simgen.dataset.spec import solver_settings
    from simgen.sim.config import SolverConfig

    entry = (attrs or {}).get("solver") or {}
    if "config" not in entry:
        raise InputError("the dataset's attributes hold no solver settings ('solver' with 'config')")
    settings = solver_settings()
    kwargs = {}
    for key, value in entry["config"].items():
        if key not in settings:      # a setting this version no longer has
            continue
        nested = settings[key].nested
        if nested is not None and isinstance(value, dict):
            floats = {f.name for f in dataclasses.fields(nested) if isinstance(f.default, float)}
            value = nested(**{k: float("inf") if v is None and k in floats else tuple(v) if isinstance(v, list) else v
                              for k, v in value.items()})
        kwargs[key] = tuple(value) if isinstance(value, list) else value
    return SolverConfig(**kwargs)


class SolverPostProcess:
    """The solver post-process of one garment (module doc).

    rest_vertices [m] (V, 3): the solver's rest shape of the garment; faces (F, 3); home_parts (V,)
    int: each vertex's body part (:func:`simgen.body.parts.vertex_parts` of the garment's weights);
    material: a :class:`simgen.sim.Material` or preset name; config: the
    :class:`simgen.sim.SolverConfig`; dt [s]: the substep length; body_faces (Fb, 3) and
    body_part_masks (Fb,) (:func:`simgen.body.parts.face_part_masks`); substeps per frame; chunk:
    frames stepped together (a power of two); device: the Warp device ("cpu", "cuda:0").
    """

    def __init__(self, rest_vertices, faces, home_parts, material, config, dt: float, body_faces, body_part_masks,
                 *, substeps: int = DEFAULT_SUBSTEPS, chunk: int = 128, device: str = "cpu") -> None:
        if substeps < 1 or chunk < 8 or chunk & (chunk - 1) or not dt > 0:
            raise InputError(f"solver post-process: substeps ({substeps}) must be >= 1, chunk ({chunk}) a power "
                             f"of two >= 8 and dt ({dt}) > 0")
        self.rest = np.asarray(rest_vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.home = np.asarray(home_parts, dtype=np.int32)
        self.material, self.config, self.dt = material, config, float(dt)
        self.body_faces = np.asarray(body_faces, dtype=np.int64)
        self.body_part_masks = np.asarray(body_part_masks, dtype=np.int32)
        self.substeps, self.chunk, self.device = int(substeps), int(chunk), str(device)
        self._solvers: dict = {}     # instances -> (ClothModel, ImplicitSolver, _Stretch)
        # the solver's counters, and [s] spent in its steps
        self._counts = {"calls": 0, "substeps": 0, "retries": 0, "newton_iterations": 0, "cg_iterations": 0,
                        "step_seconds": 0.0}
        self.reset_counters()   # seconds [s] spent in calls; frames done, stepped again, left raw

    @classmethod
    def from_data(cls, data, body, *, substeps: int = DEFAULT_SUBSTEPS, duration: float = DEFAULT_DURATION,
                  **kw) -> SolverPostProcess:
        """The post-process of a :class:`simgen.learn.data.GarmentData` (its rest template,
        material and the store's solver settings, with :data:`NEWTON_ITERATIONS`) on ``body`` (a
        BodyModel), ``substeps`` substeps over ``duration`` [s] per frame; InputError when the data
        lacks them."""
        from simgen.body.parts import face_part_masks, face_parts, vertex_parts

        if data.rest_template is None or data.material is None:
            raise InputError("the dataset holds no solver rest template or material for the solver post-process")
        config = replace(solver_config_from_attrs(data.attrs), newton_iterations=NEWTON_ITERATIONS)
        faces = np.asarray(body.faces)
        masks = face_part_masks(np.asarray(body.v_template), faces, face_parts(np.asarray(body.weights), faces))
        return cls(data.rest_template, data.faces, vertex_parts(data.skin_weights), data.material, config,
                   duration / substeps, faces, masks, substeps=substeps, **kw)

    def __call__(self, points: torch.Tensor, body_vertices: torch.Tensor) -> torch.Tensor:
        """Predicted garments [m] (N, V, 3) on posed bodies [m] (N, Vb, 3) -> the garments after the
        solver's steps [m] (N, V, 3), in the input's dtype and device."""
        if points.ndim != 3 or points.shape[1:] != self.rest.shape:
            raise InputError(f"solver post-process: points must have shape (N, {len(self.rest)}, 3), "
                             f"got {tuple(points.shape)}")
        if body_vertices.ndim != 3 or body_vertices.shape[0] != points.shape[0]:
            raise InputError(f"solver post-process: body_vertices must have shape ({points.shape[0]}, Vb, 3), "
                             f"got {tuple(body_vertices.shape)}")
        t0 = time.perf_counter()
        x = points.detach().cpu().numpy().astype(np.float32)
        b = body_vertices.detach().cpu().numpy().astype(np.float32)
        out = np.empty_like(x)
        for s in range(0, len(x), self.chunk):
            out[s:s + self.chunk] = self._chunk(x[s:s + self.chunk], b[s:s + self.chunk])
        self.seconds += time.perf_counter() - t0
        self.frames += len(x)
        return torch.from_numpy(out).to(device=points.device, dtype=points.dtype)

    def reset_counters(self) -> None:
        """Zero what :meth:`report` counts (the solvers built so far stay)."""
        self.seconds, self.frames, self.retried, self.diverged = 0.0, 0, 0, 0
        self._counts = dict.fromkeys(self._counts, 0)

    def report(self) -> dict:
        """Its settings and cost so far: substeps, dt [s], chunk, seconds, frames, ms_per_frame
        (frames stepped ``chunk`` at a time, retries included), retried_frames (failed once, stepped
        again at half the substep), diverged_frames (left raw: failed twice, or a prediction that is
        not finite), and the solver's counters: solver_calls (batched steps of a chunk or its
        failed frames), substeps_attempted (guard retries included), newton_per_substep,
        cg_iterations (those of each solve's slowest instance, summed: the batched work),
        cg_per_substep, guard_retries (the half-step splits of whole chunks) and step_ms_per_frame
        (the solver's steps alone)."""
        c, n = self._counts, max(self._counts["substeps"], 1)
        return {"substeps": self.substeps, "dt": self.dt, "chunk": self.chunk, "seconds": round(self.seconds, 3),
                "frames": self.frames, "ms_per_frame": 1e3 * self.seconds / max(self.frames, 1),
                "retried_frames": self.retried, "diverged_frames": self.diverged,
                "solver_calls": c["calls"], "substeps_attempted": c["substeps"],
                "newton_per_substep": c["newton_iterations"] / n, "cg_iterations": c["cg_iterations"],
                "cg_per_substep": c["cg_iterations"] / n,
                "guard_retries": c["retries"], "step_ms_per_frame": 1e3 * c["step_seconds"] / max(self.frames, 1)}

    def _chunk(self, x: np.ndarray, body: np.ndarray) -> np.ndarray:
        """At most ``chunk`` frames [m] (n, V, 3) float32 on bodies (n, Vb, 3) -> (n, V, 3): stepped,
        the failed frames stepped again at half the substep, those failing again (and predictions
        that are not finite) left raw."""
        out = x.copy()
        finite = np.flatnonzero(np.isfinite(x).all(axis=(1, 2)))
        failed = self._run(x, body, finite, out, self.substeps, self.dt)
        self.retried += len(failed)
        still = self._run(x, body, failed, out, 2 * self.substeps, 0.5 * self.dt)
        out[still] = x[still]
        self.diverged += len(still) + len(x) - len(finite)
        return out

    def _run(self, x: np.ndarray, body: np.ndarray, frames: np.ndarray, out: np.ndarray, substeps: int,
             dt: float) -> np.ndarray:
        """Step ``frames`` (indices into x) and write those that pass into ``out``; return the indices
        of those that failed. A step that diverges names its instances: they fail, and the others
        are stepped again without them."""
        failed: list[int] = []
        while len(frames):
            stepped, bad, diverged = self._step(x[frames], body[frames], substeps, dt)
            if diverged is not None:
                failed += frames[diverged].tolist()
                frames = np.delete(frames, diverged)
                continue
            out[frames[~bad]] = stepped[~bad]
            failed += frames[bad].tolist()
            break
        return np.array(sorted(failed), dtype=np.int64)

    def _step(self, x: np.ndarray, body: np.ndarray, substeps: int, dt: float):
        """n frames [m] (n, V, 3) float32 on bodies (n, Vb, 3), ``substeps`` substeps of ``dt`` [s]
        -> (positions (n, V, 3), failed (n,) bool, None), or (None, None, the indices of the frames
        whose instances diverged). A frame fails when the guard left it unresolved, it is not finite,
        or its most stretched triangle passes both the check's limit and the prediction's own. The
        frames are padded with copies of the last to a power of two (at least 8), so that a few model
        sizes serve every sequence length."""
        from simgen.sim import BodyCollider, SolverDivergedError

        n = len(x)
        size = max(8, 1 << (n - 1).bit_length())
        pad = np.r_[np.arange(n), np.full(size - n, n - 1)]
        model, solver, stretch = self._solver(size)
        solver.reset_contacts()             # friction's lagged contacts were another chunk's
        solver.forget_steps(range(size))    # and so were the CG warm starts
        solver.reset_stats()
        state = model.state()
        state.positions.assign(x[pad].reshape(-1, 3))
        state.velocities.zero_()
        raw = stretch(state.positions)[:n]
        collider = BodyCollider(body[pad], self.body_faces, part_masks=self.body_part_masks, device=self.device)
        t0 = time.perf_counter()
        try:
            solver.step(state, state, collider, dt * substeps, substeps=substeps)
        except SolverDivergedError as err:
            hit = np.unique(np.minimum(np.asarray(err.instances, dtype=np.int64), n - 1))
            return None, None, hit if len(hit) else np.arange(n)
        finally:
            self._counts["calls"] += 1
            stats = solver.stats
            for key in ("substeps", "retries", "newton_iterations", "cg_iterations"):
                self._counts[key] += int(stats[key])
            self._counts["step_seconds"] += time.perf_counter() - t0
        out = state.positions.numpy().reshape((size,) + x.shape[1:])[:n]
        finite = np.isfinite(out).all(axis=(1, 2))
        over = stretch(state.positions)[:n] > np.maximum(DEFAULT_MAX_STRAIN, raw)
        return out, (solver.instance_stats["unresolved"][:n] > 0) | ~finite | over, None

    def _solver(self, n: int):
        """(ClothModel, ImplicitSolver, stretch) of n instances of the garment, built on first use;
        stretch(positions) -> (n,) each instance's largest triangle stretch - 1, on the device
        (:data:`simgen.sim.frame_stats.triangle_stretch_max`, the dataset check's measure)."""
        if n not in self._solvers:
            from simgen.sim import ClothModelBuilder, ImplicitSolver

            builder = ClothModelBuilder()
            for _ in range(n):
                builder.add_instance(self.rest, self.faces, self.material, body_part=self.home)
            model = builder.finalize(self.device)
            self._solvers[n] = (model, ImplicitSolver(model, self.config), _Stretch(model))
        return self._solvers[n]


class _Stretch:
    """Each instance's largest triangle stretch - 1 of a model's positions, on its device."""

    def __init__(self, model) -> None:
        import warp as wp

        self.model = model
        dev, n = model.device, model.num_instances
        self.measured = wp.ones(n, dtype=wp.int32, device=dev)
        self.self_hit = wp.zeros(model.num_vertices, dtype=wp.int32, device=dev)   # every triangle counts
        self.out = wp.zeros(n, dtype=wp.float32, device=dev)
        self.out_regular = wp.zeros(n, dtype=wp.float32, device=dev)

    def __call__(self, positions) -> np.ndarray:
        import warp as wp

        from simgen.sim.frame_stats import triangle_stretch_max

        m = self.model
        self.out.fill_(-1.0)
        self.out_regular.fill_(-1.0)
        wp.launch(triangle_stretch_max, dim=m.num_triangles, device=m.device,
                  inputs=[positions, m.triangles, m.tri_inv_rest, m.tri_instance, self.measured, self.self_hit],
                  outputs=[self.out, self.out_regular])
        return self.out.numpy().astype(np.float64)
