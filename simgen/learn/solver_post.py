"""The cloth solver as the post-process of learned garments: implicit steps from the prediction.

A learned garment model predicts every vertex on its own, so its triangles are strained by the
regression errors and some vertices lie inside the body; the thesis's push
(:func:`simgen.learn.collision.push_out`) moves them out and strains the cloth further, and the
metric post-process (:class:`simgen.learn.relax.MetricRelax`) keeps stretch where a prediction that
lay inside the torso is pushed out against the arm (BENCHMARKS.md). :class:`SolverPostProcess`
hands each predicted frame to the simulation's own solver (:class:`simgen.sim.ImplicitSolver`, with
the dataset's material and solver settings): the cloth starts at the prediction, at rest, on the
frame's posed body (held still), and steps ``substeps`` substeps of the dataset's substep length.
The first substep, backward Euler from rest, minimises the cloth's energy plus the inertia term
sum_v m_v |x_v - p_v|^2 / (2 h^2): a metric relaxation tied to the prediction p, with the
membrane, bending and contact laws and the contact rules (penalty, projection, the body part rule,
friction) the ground truth was made with. The later substeps carry on from there as a short
simulation (their inertia term ties to x_k + h v_k), in which the strain the first one left
relaxes and the pushed-out vertices settle. Gravity acts on the way (for 20 substeps of 1/300 s,
1/15 s: a free hem would fall 2.3 cm; a supported one sags far less).

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

import numpy as np
import torch

from simgen.dataset.quality import DEFAULT_MAX_STRAIN, triangle_rest_inverse, triangle_strain
from simgen.errors import InputError

__all__ = ["DEFAULT_SUBSTEPS", "SolverPostProcess", "solver_config_from_attrs"]

#: Substeps per frame: on a held-out hop of the thesis-tshirt model (fit-only predictions) 3, 5, 10
#: and 20 substeps of 1/300 s left 21x, 11x, 5x and about 2x the simulation's strain energy
#: (BENCHMARKS.md).
DEFAULT_SUBSTEPS = 20


def solver_config_from_attrs(attrs: dict):
    """(:class:`simgen.sim.SolverConfig`, substep length [s]) of a store's root attributes (its
    ``solver`` entry, as :func:`simgen.dataset.generate_dataset` writes it); InputError if absent."""
    from simgen.dataset.spec import solver_settings
    from simgen.sim.config import SolverConfig

    entry = (attrs or {}).get("solver") or {}
    if "config" not in entry or "dt" not in entry:
        raise InputError("the dataset's attributes hold no solver settings ('solver' with 'config' and 'dt')")
    settings = solver_settings()
    kwargs = {}
    for key, value in entry["config"].items():
        if key not in settings:      # a setting this version no longer has
            continue
        nested = settings[key].nested
        if nested is not None and isinstance(value, dict):
            value = nested(**{k: tuple(v) if isinstance(v, list) else v for k, v in value.items()})
        kwargs[key] = tuple(value) if isinstance(value, list) else value
    return SolverConfig(**kwargs), float(entry["dt"])


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
        self._solvers: dict = {}     # instances -> (ClothModel, ImplicitSolver)
        self._rest_inverse = triangle_rest_inverse(self.rest, self.faces)
        # the solver's counters, and [s] spent in its steps
        self._counts = {"substeps": 0, "retries": 0, "newton_iterations": 0, "cg_iterations": 0, "step_seconds": 0.0}
        self.reset_counters()   # seconds [s] spent in calls; frames done, stepped again, left raw

    @classmethod
    def from_data(cls, data, body, **kw) -> SolverPostProcess:
        """The post-process of a :class:`simgen.learn.data.GarmentData` (its rest template,
        material and the store's solver settings) on ``body`` (a BodyModel); InputError when the
        data lacks them."""
        from simgen.body.parts import face_part_masks, face_parts, vertex_parts

        if data.rest_template is None or data.material is None:
            raise InputError("the dataset holds no solver rest template or material for the solver post-process")
        config, dt = solver_config_from_attrs(data.attrs)
        faces = np.asarray(body.faces)
        masks = face_part_masks(np.asarray(body.v_template), faces, face_parts(np.asarray(body.weights), faces))
        return cls(data.rest_template, data.faces, vertex_parts(data.skin_weights), data.material, config, dt,
                   faces, masks, **kw)

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
        again at half the substep), diverged_frames (failed twice, left raw), and the solver's
        counters over its batched substeps: newton_per_substep, cg_per_substep (PCG iterations of
        the chunk's slowest instance, summed over its Newton iterations), guard_retries (the
        half-step splits of whole chunks) and step_ms_per_frame (the solver's steps alone)."""
        c, n = self._counts, max(self._counts["substeps"], 1)
        return {"substeps": self.substeps, "dt": self.dt, "chunk": self.chunk, "seconds": round(self.seconds, 3),
                "frames": self.frames, "ms_per_frame": 1e3 * self.seconds / max(self.frames, 1),
                "retried_frames": self.retried, "diverged_frames": self.diverged,
                "newton_per_substep": c["newton_iterations"] / n, "cg_per_substep": c["cg_iterations"] / n,
                "guard_retries": c["retries"], "step_ms_per_frame": 1e3 * c["step_seconds"] / max(self.frames, 1)}

    def _chunk(self, x: np.ndarray, body: np.ndarray) -> np.ndarray:
        """At most ``chunk`` frames [m] (n, V, 3) float32 on bodies (n, Vb, 3) -> (n, V, 3): stepped,
        the failed frames stepped again at half the substep, those failing again left raw."""
        out, failed = self._step(x, body, self.substeps, self.dt)
        if failed.any():
            self.retried += int(failed.sum())
            again, still = self._step(x[failed], body[failed], 2 * self.substeps, 0.5 * self.dt)
            again[still] = x[failed][still]
            out[failed] = again
            self.diverged += int(still.sum())
        return out

    def _failed(self, x: np.ndarray, out: np.ndarray, unresolved: np.ndarray) -> np.ndarray:
        """(n,) bool: frames whose steps the guard left unresolved, that are not finite, or whose
        largest triangle stretch passes both the check's limit and the prediction's own."""
        finite = np.isfinite(out).all(axis=(1, 2))
        over = np.zeros(len(out), dtype=bool)
        strain = triangle_strain(np.where(finite[:, None, None], out, 0.0), self.faces, self._rest_inverse).max(1)
        raw = triangle_strain(x, self.faces, self._rest_inverse).max(1)
        over[finite] = (strain > np.maximum(DEFAULT_MAX_STRAIN, raw))[finite]
        return unresolved | ~finite | over

    def _step(self, x: np.ndarray, body: np.ndarray, substeps: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """n frames [m] (n, V, 3) float32 on bodies (n, Vb, 3), ``substeps`` substeps of ``dt`` [s]
        -> (positions (n, V, 3), failed (n,) bool). The frames are padded with copies of the last to
        a power of two (at least 8), so that a few model sizes serve every sequence length."""
        from simgen.sim import BodyCollider, SolverDivergedError

        n = len(x)
        size = max(8, 1 << (n - 1).bit_length())
        pad = np.r_[np.arange(n), np.full(size - n, n - 1)]
        model, solver = self._solver(size)
        solver.reset_contacts()             # friction's lagged contacts were another chunk's
        solver.forget_steps(range(size))    # and so were the CG warm starts
        solver.reset_stats()
        state = model.state()
        state.positions.assign(x[pad].reshape(-1, 3))
        state.velocities.zero_()
        collider = BodyCollider(body[pad], self.body_faces, part_masks=self.body_part_masks, device=self.device)
        t0 = time.perf_counter()
        try:
            solver.step(state, state, collider, dt * substeps, substeps=substeps)
        except SolverDivergedError:
            return x.copy(), np.ones(n, dtype=bool)
        finally:
            stats = solver.stats
            for key in ("substeps", "retries", "newton_iterations", "cg_iterations"):
                self._counts[key] += int(stats[key])
        out = state.positions.numpy().reshape((size,) + x.shape[1:])[:n]
        self._counts["step_seconds"] += time.perf_counter() - t0
        return out, self._failed(x, out, solver.instance_stats["unresolved"][:n] > 0)

    def _solver(self, n: int):
        """The (ClothModel, ImplicitSolver) of n instances of the garment, built on first use."""
        if n not in self._solvers:
            from simgen.sim import ClothModelBuilder, ImplicitSolver

            builder = ClothModelBuilder()
            for _ in range(n):
                builder.add_instance(self.rest, self.faces, self.material, body_part=self.home)
            model = builder.finalize(self.device)
            self._solvers[n] = (model, ImplicitSolver(model, self.config))
        return self._solvers[n]
