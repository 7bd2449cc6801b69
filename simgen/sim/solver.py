"""Implicit cloth solver: backward Euler as minimisation (SNUG eq. 5.4), Newton + block-Jacobi PCG.

One step of length h from (x_t, v_t) solves

    x_{t+1} = argmin_x  E(x) = 1/(2 h^2) (x - x_hat)^T M (x - x_hat) + Phi(x),   x_hat = x_t + h v_t,
    v_{t+1} = (x_{t+1} - x_t) / h,

with Phi = StVK membrane + dihedral bending + gravity + body contact penalty + lagged friction +
damping dissipation + the floor's penalty + the springs of vertices attached to the body (a
waistband) (+ optional cloth self-contact repulsion, candidates gathered at each step's start) (the terms of :mod:`simgen.sim.energies`). Its stationarity condition is
exactly backward Euler, M (v_{t+1} - v_t) / h = f(x_{t+1}). Each Newton iteration assembles the
gradient g and the PSD-projected Hessian H (values refilled in place in the model's fixed BSR
pattern), solves H d = g with :class:`~simgen.sim.linear.BlockJacobiPCG` and sets x <- x - alpha d,
alpha = 1 or chosen by a backtracking (Armijo) line search on each instance's own E, run for a
fixed number of trials on the device. The iteration starts from x_t (ARCSim's single linearised
step when ``newton_iterations`` = 1); pinned vertices are kinematic: they move to x_hat (their
own velocity) and are removed from the linear system.

Guard: after each step the solver checks (one host read) for non-finite positions, a vertex speed
above ``max_speed`` or (``guard_energy``, off by default) an increase of E beyond ``divergence_ratio`` times the
decrease the first Newton model predicted (plus a round-off allowance). A failed step is redone as
two half steps, recursively, up to ``max_retries`` levels; retries are counted in
:attr:`ImplicitSolver.stats`.

After each substep, an optional projection (:meth:`BodyCollider.project`) moves any vertex found
inside its body onto the surface and removes its inward normal velocity, so no output vertex is
inside; vertices below the floor are put back on it the same way. Friction's contact set (normal force, normal, closest body point) is lagged: taken at the
end of the previous substep (after the projection), where cloth and body are at the same time.

Host synchronisation: the Newton/PCG/line-search sequence reads nothing back inside a CUDA graph
(PCG's loop is a conditional graph node there; run eagerly it reads its on-device "running" flag
once per CG iteration). The guard (one int per substep),
``newton_tolerance`` > 0 (one float per Newton iteration) and :attr:`ImplicitSolver.stats` read
from the device. For capture, ``step(..., deferred_guard=True)`` runs the guard's checks without
reading them: each instance's failure bits accumulate in :attr:`ImplicitSolver.deferred_bad`
(cleared by :meth:`ImplicitSolver.clear_deferred_guard`), and the caller reads them once after a
whole captured frame and redoes the failed instances at a finer step (``step(..., substeps=n)``;
:func:`simgen.sim.simulate_batch` holds the others meanwhile), counting it with
:meth:`ImplicitSolver.count_retries`.
"""


import functools
import math
from types import SimpleNamespace

import numpy as np
import warp as wp

from simgen.errors import InputError
from simgen.sim.collider import BodyCollider
from simgen.sim.energies import (ContactFrame, SelfContactSet, eval_bending, eval_contact, eval_attachment, eval_damping, eval_floor, eval_friction,
                                 eval_gravity, eval_inertia, eval_membrane, eval_self_contact, load_kernels,
                                 project_floor, update_contact_frame)
from simgen.sim.warp_toolkit import module_name, scalar_types
from simgen.sim.impact_filter import ImpactFilter, impact_kernels
from simgen.sim.linear import BlockJacobiPCG
from simgen.sim.model import ClothModel, ClothState
from simgen.sim.config import SolverConfig
from simgen.sim.strain_limit import StrainLimiter, strain_limit_kernels

__all__ = ["SolverConfig", "ImplicitSolver", "SolverDivergedError", "solver_kernels"]


class SolverDivergedError(RuntimeError):
    """A step still produced non-finite positions after every allowed retry.

    instances: indices of the model instances whose positions were non-finite (the others were
    fine; a batched caller can freeze the failed ones and redo the step for the rest).
    """

    def __init__(self, message: str, instances=()) -> None:
        super().__init__(message)
        self.instances = [int(i) for i in instances]


@functools.cache
def solver_kernels(scalar) -> SimpleNamespace:
    """Per-vertex and per-instance kernels of the integrator for one scalar type."""
    T = scalar_types(scalar)
    vec3 = T.vec3
    mod = module_name(__name__, scalar)
    zero = scalar(0.0)

    @wp.kernel(enable_backward=False, module=mod)
    def predict(x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), pinned: wp.array(dtype=wp.int32),
                vertex_instance: wp.array(dtype=wp.int32), step_divisor: wp.array(dtype=wp.int32), h: scalar,
                x_start: wp.array(dtype=vec3), x_hat: wp.array(dtype=vec3)):
        # Newton starts at x_t; pinned vertices follow their own velocity (kinematic) at once.
        i = wp.tid()
        xs = x[i]
        x_start[i] = xs
        xh = xs + (h / scalar(step_divisor[vertex_instance[i]])) * v[i]
        x_hat[i] = xh
        if pinned[i] != 0:
            x[i] = xh

    @wp.kernel(enable_backward=False, module=mod)
    def instance_dot(a: wp.array(dtype=vec3), b: wp.array(dtype=vec3), vertex_instance: wp.array(dtype=wp.int32),
                     out: wp.array(dtype=scalar)):
        i = wp.tid()
        wp.atomic_add(out, vertex_instance[i], wp.dot(a[i], b[i]))

    @wp.kernel(enable_backward=False, module=mod)
    def ls_init(alpha: wp.array(dtype=scalar), accepted: wp.array(dtype=wp.int32)):
        k = wp.tid()
        alpha[k] = scalar(1.0)
        accepted[k] = 0

    @wp.kernel(enable_backward=False, module=mod)
    def ls_trial(x: wp.array(dtype=vec3), d: wp.array(dtype=vec3), vertex_instance: wp.array(dtype=wp.int32),
                 alpha: wp.array(dtype=scalar), x_trial: wp.array(dtype=vec3)):
        i = wp.tid()
        x_trial[i] = x[i] - alpha[vertex_instance[i]] * d[i]

    @wp.kernel(enable_backward=False, module=mod)
    def ls_check(e0: wp.array(dtype=scalar), e_trial: wp.array(dtype=scalar), gd: wp.array(dtype=scalar),
                 armijo: scalar, rel_tol: scalar, alpha: wp.array(dtype=scalar), accepted: wp.array(dtype=wp.int32)):
        # Armijo on E(x - alpha d) with slope -g.d; rel_tol |E0| absorbs the round-off of E itself.
        k = wp.tid()
        if accepted[k] != 0:
            return
        a = alpha[k]
        if e_trial[k] <= e0[k] - armijo * a * gd[k] + rel_tol * wp.abs(e0[k]):
            accepted[k] = 1
        else:
            alpha[k] = a * scalar(0.5)

    @wp.kernel(enable_backward=False, module=mod)
    def ls_finalize(alpha: wp.array(dtype=scalar), accepted: wp.array(dtype=wp.int32), bad: wp.array(dtype=wp.int32)):
        # No trial passed: take no step rather than an unverified one, and flag it (bit 8) so the
        # guard retries the step at half dt.
        k = wp.tid()
        if accepted[k] == 0:
            alpha[k] = zero
            wp.atomic_or(bad, k, 8)

    @wp.kernel(enable_backward=False, module=mod)
    def apply_step(x: wp.array(dtype=vec3), d: wp.array(dtype=vec3), vertex_instance: wp.array(dtype=wp.int32),
                   alpha: wp.array(dtype=scalar)):
        i = wp.tid()
        x[i] = x[i] - alpha[vertex_instance[i]] * d[i]

    @wp.kernel(enable_backward=False, module=mod)
    def velocity(x: wp.array(dtype=vec3), x_start: wp.array(dtype=vec3), vertex_instance: wp.array(dtype=wp.int32),
                 step_divisor: wp.array(dtype=wp.int32), inv_h: scalar, v: wp.array(dtype=vec3)):
        i = wp.tid()
        v[i] = (x[i] - x_start[i]) * (inv_h * scalar(step_divisor[vertex_instance[i]]))

    @wp.kernel(enable_backward=False, module=mod)
    def max_abs(d: wp.array(dtype=vec3), out: wp.array(dtype=scalar)):
        i = wp.tid()
        di = d[i]
        wp.atomic_max(out, 0, wp.max(wp.abs(di[0]), wp.max(wp.abs(di[1]), wp.abs(di[2]))))

    @wp.kernel(enable_backward=False, module=mod)
    def check_vertices(x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), vertex_instance: wp.array(dtype=wp.int32),
                       max_speed2: scalar, bad: wp.array(dtype=wp.int32)):
        # bad bit 1: non-finite position or velocity; bit 2: a vertex faster than max_speed.
        i = wp.tid()
        xi = x[i]
        vi = v[i]
        s = xi[0] + xi[1] + xi[2] + vi[0] + vi[1] + vi[2]
        if not wp.isfinite(s):
            wp.atomic_or(bad, vertex_instance[i], 1)
        elif wp.dot(vi, vi) > max_speed2:
            wp.atomic_or(bad, vertex_instance[i], 2)

    @wp.kernel(enable_backward=False, module=mod)
    def check_energy(e_start: wp.array(dtype=scalar), e_end: wp.array(dtype=scalar),
                     predicted: wp.array(dtype=scalar), ratio: scalar, rel_tol: scalar,
                     bad: wp.array(dtype=wp.int32)):
        # bad bit 4: E rose by more than ratio x the first Newton model's predicted decrease.
        k = wp.tid()
        allowed = ratio * wp.abs(predicted[k]) + rel_tol * wp.abs(e_start[k])
        if not (e_end[k] - e_start[k] <= allowed):
            wp.atomic_or(bad, k, 4)

    @wp.kernel(enable_backward=False, module=mod)
    def accumulate(counter: wp.array(dtype=wp.int32), total: wp.array(dtype=wp.int64)):
        total[0] = total[0] + wp.int64(counter[0])

    @wp.kernel(enable_backward=False, module=mod)
    def accumulate_bad(bad: wp.array(dtype=wp.int32), total: wp.array(dtype=wp.int32)):
        k = wp.tid()
        total[k] = total[k] | bad[k]

    @wp.kernel(enable_backward=False, module=mod)
    def keep_max(value: wp.array(dtype=scalar), running: wp.array(dtype=scalar)):
        k = wp.tid()
        running[k] = wp.max(running[k], value[k])

    return SimpleNamespace(predict=predict, instance_dot=instance_dot, ls_init=ls_init, ls_trial=ls_trial,
                           ls_check=ls_check, ls_finalize=ls_finalize, apply_step=apply_step, velocity=velocity,
                           max_abs=max_abs, check_vertices=check_vertices, check_energy=check_energy, accumulate=accumulate,
                           accumulate_bad=accumulate_bad, keep_max=keep_max)


class ImplicitSolver:
    """Backward-Euler Newton/PCG cloth solver for one :class:`ClothModel` (see the module doc).

    >>> solver = ImplicitSolver(model, SolverConfig(newton_iterations=1))
    >>> s0, s1 = model.state(), model.state()
    >>> solver.step(s0, s1, body, dt=1 / 300); s0, s1 = s1, s0

    Every buffer is allocated here. ``stats`` (a dict, read with a host sync) counts steps,
    Newton and CG iterations, retries, unresolved (guard still failing after max_retries, but
    finite) and the maximum body penetration [m] seen before projection.
    """

    def __init__(self, model: ClothModel, config: SolverConfig | None = None) -> None:
        self.model = model
        self.config = config if config is not None else SolverConfig()
        cfg = self.config
        m = model
        T = scalar_types(m.scalar)
        dev, ni = m.device, m.num_instances
        self.kernels = solver_kernels(m.scalar)
        self.pcg = BlockJacobiPCG(m, max_iterations=cfg.cg_iterations, tolerance=cfg.cg_tolerance)
        self.hessian = m.new_hessian()
        self.gradient = m.new_gradient()
        self.step_dir = m.new_gradient()
        self.x_start = m.new_gradient()
        self.x_hat = m.new_gradient()
        self.x_trial = m.new_gradient()
        self.energy = m.new_energy()
        self.energy_start = m.new_energy()
        self.energy_trial = m.new_energy()
        self.grad_dot_step = m.new_energy()
        self.predicted = m.new_energy()
        self.alpha = wp.ones(ni, dtype=T.scalar, device=dev)
        self.accepted = wp.zeros(ni, dtype=wp.int32, device=dev)
        self.bad = wp.zeros(ni, dtype=wp.int32, device=dev)
        self.update_norm = wp.zeros(1, dtype=T.scalar, device=dev)
        self.contact_frame = ContactFrame(m)
        # The contact's body part rule, decided per vertex at each step's start and held through it.
        self.part_choice = wp.zeros(m.num_vertices, dtype=wp.int32, device=dev)
        self.self_contact = SelfContactSet(m, cfg.self_contact) if cfg.self_contact is not None else None
        self.impact_filter = (ImpactFilter(m, cfg.self_contact.impact_rounds)
                              if cfg.self_contact is not None and cfg.self_contact.impact_rounds > 0 else None)
        self._substep_start = m.new_gradient() if self.impact_filter is not None else None
        self.strain_limiter = (StrainLimiter(m, cfg.strain_limit, cfg.strain_limit_iterations)
                               if cfg.strain_limit is not None else None)
        self._frame_valid = False
        self.no_body = wp.zeros(ni, dtype=wp.uint64, device=dev)
        # Round-off allowance on energies that include the arbitrary offset of the gravity potential.
        self.energy_rel_tol = 1.0e-5 if m.scalar is wp.float32 else 1.0e-10
        self.has_damping = bool(np.any(m.host.tri_damping) or np.any(m.host.hinge_damping)
                                or np.any(m.host.vertex_damping_mass))
        self._backups = [m.state() for _ in range(cfg.max_retries + 1)] if cfg.guard else []
        self._work = m.state()
        # The last substep's step of each Newton iteration: the next substep's first guesses.
        self.step_guesses = [m.new_gradient() for _ in range(cfg.newton_iterations)] if cfg.cg_warm_start else []
        self._cg_total = wp.zeros(1, dtype=wp.int64, device=dev)
        self._depth = wp.zeros(ni, dtype=T.scalar, device=dev)
        self._depth_max = wp.zeros(ni, dtype=T.scalar, device=dev)
        self._inside = wp.zeros(ni, dtype=wp.int32, device=dev)
        self._counts = dict(steps=0, substeps=0, newton_iterations=0, retries=0, unresolved=0)
        # Per instance: substeps it failed (retried) and steps left unresolved, since reset_stats.
        self._instance_retries = np.zeros(ni, dtype=np.int64)
        self._instance_unresolved = np.zeros(ni, dtype=np.int64)
        self.deferred_bad = wp.zeros(ni, dtype=wp.int32, device=dev)

    # -- public -------------------------------------------------------------------------------

    def load(self) -> None:
        """Compile every kernel the solver launches (before capturing a CUDA graph)."""
        dev = self.model.device
        load_kernels(self.model.scalar, device=dev)
        self.pcg.load()
        wp.load_module(module_name(__name__, self.model.scalar), device=dev)
        if self.strain_limiter is not None:
            strain_limit_kernels(self.model.scalar)
            wp.load_module(module_name("simgen.sim.strain_limit", self.model.scalar), device=dev)
        if self.impact_filter is not None:
            impact_kernels(self.model.scalar)
            wp.load_module(module_name("simgen.sim.impact_filter", self.model.scalar), device=dev)

    @property
    def stats(self) -> dict:
        """Counters since construction or :meth:`reset_stats` (host sync):

        steps, substeps (attempted, retries included), newton_iterations, cg_iterations (total),
        cg_per_newton (mean), retries (half-step splits), unresolved, max_penetration [m]
        (deepest vertex inside its body before projection, over all steps and instances),
        last_inside (vertices found inside before the last projection, all instances).
        """
        s = dict(self._counts)
        s["cg_iterations"] = int(self._cg_total.numpy()[0])
        s["cg_per_newton"] = s["cg_iterations"] / max(s["newton_iterations"], 1)
        s["max_penetration"] = float(self._depth_max.numpy().max())
        s["last_inside"] = int(self._inside.numpy().sum())
        return s

    @property
    def instance_stats(self) -> dict:
        """Per-instance counters since :meth:`reset_stats` (host sync), each an (I,) array:
        max_penetration [m] before projection, retries (failed steps of that instance: step()'s own
        guard redoes the whole batch, so every instance takes its half steps; a caller's
        :meth:`count_retries` counts the instances it redoes), unresolved."""
        return dict(max_penetration=self._depth_max.numpy().astype(np.float64),
                    retries=self._instance_retries.copy(), unresolved=self._instance_unresolved.copy())

    def host_counts(self) -> dict:
        """The host-side step counters (steps, substeps, newton_iterations, retries, unresolved)."""
        return dict(self._counts)

    def add_host_counts(self, delta: dict) -> None:
        """Add counter increments, e.g. those of a captured frame each time its CUDA graph replays
        (the Python that counts them runs only at capture)."""
        for k, v in delta.items():
            self._counts[k] += int(v)

    def count_retries(self, instances) -> None:
        """Count a caller's retry of a deferred-guard step (or frame) for these instance indices."""
        self._counts["retries"] += 1
        self._instance_retries[list(instances)] += 1

    def count_unresolved(self, instances) -> None:
        """Count instances a caller kept although they still failed the guard after its last retry."""
        if len(instances):
            self._counts["unresolved"] += 1
            self._instance_unresolved[list(instances)] += 1

    def take_contacts(self, state: ClothState, body: BodyCollider | None) -> None:
        """Take friction's lagged contacts from ``state`` against the body where it is now, as a
        step does at its end (e.g. after a caller restored or replaced some instances' states)."""
        self._lag_contacts(state, body)

    def clear_deferred_guard(self) -> None:
        """Zero :attr:`deferred_bad` (a memset, graph-capture safe)."""
        self.deferred_bad.zero_()

    def reset_stats(self) -> None:
        """Zero every counter of :attr:`stats` and :attr:`instance_stats`."""
        for k in self._counts:
            self._counts[k] = 0
        self._instance_retries[:] = 0
        self._instance_unresolved[:] = 0
        self._cg_total.zero_()
        self._depth_max.zero_()
        self._inside.zero_()

    def step(self, state_in: ClothState, state_out: ClothState, body: BodyCollider | None, dt: float, *,
             deferred_guard: bool = False, substeps: int | None = None) -> None:
        """Advance ``state_in`` by dt [s] into ``state_out`` (they may be the same object); instance
        k advances by dt / ``model.instance_step_divisor[k]``.

        body: the :class:`BodyCollider` (one body per instance, already :meth:`~BodyCollider.update`d
        to the end of this step; with substeps it is interpolated from its previous position), or
        None for no body. Raises SolverDivergedError if a step stays non-finite after every retry.
        deferred_guard: run the guard's checks but only OR their bits into :attr:`deferred_bad`,
        with no host read and no retry (for CUDA graph capture; see the module doc).
        substeps: split this step into that many equal substeps (None: one), e.g. a caller's retry
        of a failed step at a finer time step.
        """
        try:
            dt = float(dt)
        except (TypeError, ValueError):
            raise InputError(f"time step must be a number, got {dt!r}") from None
        if not (math.isfinite(dt) and dt > 0):
            raise InputError(f"time step must be a finite number > 0, got {dt!r}")
        if body is not None:
            body.check_model(self.model)
        cfg = self.config
        work = self._work
        work.assign(state_in)
        n = 1 if substeps is None else int(substeps)
        if n < 1:
            raise InputError(f"substeps must be an integer >= 1, got {substeps!r}")
        for s in range(n):
            if self.impact_filter is not None:
                wp.copy(self._substep_start, work.positions)
                self.impact_filter.touching.zero_()  # marked afresh by this substep's projection
            if deferred_guard:
                self._deferred_step(work, body, dt / n, s / n, (s + 1) / n)
            else:
                self._guarded_step(work, body, dt / n, s / n, (s + 1) / n, 0)
            projecting = body is not None and cfg.project
            # Only the limiter and the projection alternate: a round without both is the same again.
            rounds = cfg.constraint_rounds if projecting and self.strain_limiter is not None else 1
            for _ in range(rounds):
                if self.strain_limiter is not None:
                    self.strain_limiter.apply(work, dt / n)
                if projecting:
                    self._inside.zero_()
                    self._depth.zero_()
                    f = self.impact_filter
                    body.project(self.model, work, offset=cfg.projection_offset,
                                 query_distance=cfg.contact.query_distance,
                                 pinch_distance=cfg.contact.pinch_distance, depth=self._depth, count=self._inside,
                                 touch_distance=cfg.contact.margin, **({} if f is None else f.touch_outputs()))
                    wp.launch(self.kernels.keep_max, dim=self.model.num_instances, device=self.model.device,
                              inputs=[self._depth, self._depth_max])
            if cfg.floor is not None and cfg.project:
                project_floor(self.model, work, cfg.floor, cfg.projection_offset)
            if self.impact_filter is not None:
                # Last: whatever moved the cloth in this substep (solve, limiter, projections).
                self.impact_filter.apply(self._substep_start, work)
            if projecting:
                self._lag_contacts(work, body)
        state_out.assign(work)
        self._counts["steps"] += 1

    # -- internals ----------------------------------------------------------------------------

    def _place_body(self, state: ClothState, body, t0: float, t1: float) -> None:
        cfg = self.config
        if body is not None and cfg.friction is not None and not self._frame_valid:
            # No lagged contacts yet: take them at this step's start, cloth and body both at t0.
            body.set_time(t0)
            update_contact_frame(self.model, state.positions, body.mesh_ids, cfg.contact, self.contact_frame,
                                 part_masks=body.part_masks)
            self._frame_valid = True
            body.set_time(t1)
        elif body is not None and not (t0 == 0.0 and t1 == 1.0):
            body.set_time(t1)

    def _lag_after_projection(self, body) -> bool:
        # When step() projects after the (whole) substep, it takes the lagged contacts there; an
        # unsplit substep need not take them before the projection as well.
        return body is not None and self.config.project

    def _deferred_step(self, state: ClothState, body, h: float, t0: float, t1: float) -> None:
        self._place_body(state, body, t0, t1)
        self._advance(state, body, h, deferred=True, lag=not self._lag_after_projection(body))

    def _guarded_step(self, state: ClothState, body, h: float, t0: float, t1: float, level: int) -> None:
        cfg = self.config
        self._place_body(state, body, t0, t1)
        # Half steps of a retry need the contacts of the first half for the second.
        lag = level > 0 or not self._lag_after_projection(body)
        if not cfg.guard:
            self._advance(state, body, h, lag=lag)
            return
        backup = self._backups[level]
        backup.assign(state)
        bad_vec = self._advance(state, body, h, lag=lag)
        bad = int(np.bitwise_or.reduce(bad_vec))
        if bad == 0:
            return
        if level >= cfg.max_retries:
            if bad & 1:
                raise SolverDivergedError(
                    f"the cloth step still produced non-finite positions at dt = {h:.3g} s after "
                    f"{cfg.max_retries} half-step retries", instances=np.nonzero(bad_vec & 1)[0])
            self._counts["unresolved"] += 1
            self._instance_unresolved[bad_vec != 0] += 1
            return
        state.assign(backup)
        self._counts["retries"] += 1
        self._instance_retries[bad_vec != 0] += 1
        tm = 0.5 * (t0 + t1)
        self._guarded_step(state, body, 0.5 * h, t0, tm, level + 1)
        self._guarded_step(state, body, 0.5 * h, tm, t1, level + 1)

    def _eval(self, x, h: float, mesh_ids, body, *, energy=None, gradient=None, hessian=None,
              decide_parts: bool = False) -> None:
        m, cfg = self.model, self.config
        eval_inertia(m, x, self.x_hat, h, energy=energy, gradient=gradient, hessian=hessian)
        eval_membrane(m, x, energy=energy, gradient=gradient, hessian=hessian)
        eval_bending(m, x, energy=energy, gradient=gradient, hessian=hessian)
        eval_gravity(m, x, cfg.gravity, energy=energy, gradient=gradient)
        if body is not None:
            eval_contact(m, x, mesh_ids, cfg.contact, part_masks=body.part_masks, part_choice=self.part_choice,
                         decide_parts=decide_parts, energy=energy, gradient=gradient, hessian=hessian)
            if cfg.friction is not None:
                eval_friction(m, x, self.x_start, mesh_ids, self.contact_frame, h, cfg.friction,
                              energy=energy, gradient=gradient, hessian=hessian)
            eval_attachment(m, x, mesh_ids, energy=energy, gradient=gradient, hessian=hessian)
        if self.self_contact is not None:
            eval_self_contact(m, x, self.self_contact, energy=energy, gradient=gradient, hessian=hessian)
        if cfg.floor is not None:
            eval_floor(m, x, cfg.floor, cfg.contact, energy=energy, gradient=gradient, hessian=hessian)
        if self.has_damping:
            eval_damping(m, x, self.x_start, h, energy=energy, gradient=gradient, hessian=hessian)

    def _advance(self, state: ClothState, body, h: float, *, deferred: bool = False, lag: bool = True):
        """One backward-Euler step of length h in place; returns the guard's bad bits per instance,
        (I,) int (0 = fine), or None without the guard or when ``deferred`` (bits OR-ed into
        :attr:`deferred_bad` on the device instead). lag: take friction's lagged contacts at the
        end (a successful step only)."""
        m, cfg, k = self.model, self.config, self.kernels
        dev, n, ni = m.device, m.num_vertices, m.num_instances
        x, v = state.positions, state.velocities
        mesh_ids = body.mesh_ids if body is not None else self.no_body
        self._counts["substeps"] += 1
        energy_test = cfg.guard and cfg.guard_energy
        self.bad.zero_()
        wp.launch(k.predict, dim=n, device=dev, inputs=[x, v, m.vertex_pinned, m.vertex_instance,
                                                        m.instance_step_divisor, h, self.x_start, self.x_hat])
        if self.self_contact is not None:
            self.self_contact.update(self.x_start)
        for it in range(cfg.newton_iterations):
            self.gradient.zero_()
            self.hessian.values.zero_()
            # The guard's E(x_start) is the first assembly's energy (Newton starts there), so no
            # separate energy pass is needed for it.
            want_energy = cfg.line_search or (energy_test and it == 0)
            if want_energy:
                self.energy.zero_()
            self._eval(x, h, mesh_ids, body, energy=self.energy if want_energy else None,
                       gradient=self.gradient, hessian=self.hessian, decide_parts=(it == 0))
            if energy_test and it == 0:
                wp.copy(self.energy_start, self.energy)
            self.pcg.apply_constraints(self.hessian)
            # H d = g; the Newton update is x - d (pinned entries of d are exactly 0).
            guess = self.step_guesses[it] if self.step_guesses else None
            self.pcg.solve(self.hessian, self.gradient, self.step_dir, guess=guess)
            if guess is not None:
                wp.copy(guess, self.step_dir)
            wp.launch(k.accumulate, dim=1, device=dev, inputs=[self.pcg.iteration_counter, self._cg_total])
            self._counts["newton_iterations"] += 1
            if cfg.line_search or (energy_test and it == 0):
                self.grad_dot_step.zero_()
                wp.launch(k.instance_dot, dim=n, device=dev,
                          inputs=[self.gradient, self.step_dir, m.vertex_instance, self.grad_dot_step])
            if energy_test and it == 0:
                # The quadratic model predicts a decrease of g.d / 2 for the full step.
                wp.copy(self.predicted, self.grad_dot_step)
            wp.launch(k.ls_init, dim=ni, device=dev, inputs=[self.alpha, self.accepted])
            if cfg.line_search:
                for _ in range(cfg.line_search_steps):
                    wp.launch(k.ls_trial, dim=n, device=dev,
                              inputs=[x, self.step_dir, m.vertex_instance, self.alpha, self.x_trial])
                    self.energy_trial.zero_()
                    self._eval(self.x_trial, h, mesh_ids, body, energy=self.energy_trial)
                    wp.launch(k.ls_check, dim=ni, device=dev, inputs=[
                        self.energy, self.energy_trial, self.grad_dot_step, cfg.armijo, self.energy_rel_tol,
                        self.alpha, self.accepted])
                wp.launch(k.ls_finalize, dim=ni, device=dev, inputs=[self.alpha, self.accepted, self.bad])
            wp.launch(k.apply_step, dim=n, device=dev, inputs=[x, self.step_dir, m.vertex_instance, self.alpha])
            if cfg.newton_tolerance > 0:
                self.update_norm.zero_()
                wp.launch(k.max_abs, dim=n, device=dev, inputs=[self.step_dir, self.update_norm])
                if float(self.update_norm.numpy()[0]) < cfg.newton_tolerance:
                    break
        wp.launch(k.velocity, dim=n, device=dev,
                  inputs=[x, self.x_start, m.vertex_instance, m.instance_step_divisor, 1.0 / h, v])
        if not cfg.guard:
            if lag:
                self._lag_contacts(state, body)
            return None
        # bad: 1 non-finite, 2 too fast, 4 energy rose, 8 line search found no decrease.
        wp.launch(k.check_vertices, dim=n, device=dev,
                  inputs=[x, v, m.vertex_instance, cfg.max_speed * cfg.max_speed, self.bad])
        if energy_test:
            self.energy.zero_()
            self._eval(x, h, mesh_ids, body, energy=self.energy)
            wp.launch(k.check_energy, dim=ni, device=dev, inputs=[
                self.energy_start, self.energy, self.predicted, cfg.divergence_ratio * 0.5, self.energy_rel_tol,
                self.bad])
        if deferred:
            wp.launch(k.accumulate_bad, dim=ni, device=dev, inputs=[self.bad, self.deferred_bad])
            if lag:
                self._lag_contacts(state, body)
            return None
        bad = self.bad.numpy()
        if lag and not bad.any():
            self._lag_contacts(state, body)
        return bad

    def _lag_contacts(self, state: ClothState, body) -> None:
        # Friction's normal forces and contact points for the next step come from the end of this
        # one (cloth and body both at t + h), where the penalty balances the actual contact load.
        # Taking them at the next step's start against the already moved body would see x_t inside
        # it and overestimate the normal force by orders of magnitude.
        if body is None or self.config.friction is None:
            return
        update_contact_frame(self.model, state.positions, body.mesh_ids, self.config.contact, self.contact_frame,
                             part_masks=body.part_masks)
        self._frame_valid = True

    def forget_steps(self, instances) -> None:
        """Zero the warm-start guesses of ``instances`` (a slot that starts a new job)."""
        starts = np.asarray(self.model.vertex_start)
        for g in self.step_guesses:
            a = g.numpy()
            for i in instances:
                a[starts[i]:starts[i + 1]] = 0.0
            g.assign(a)

    def reset_contacts(self) -> None:
        """Forget the lagged friction contacts, e.g. before stepping a state that is not the output
        of this solver's previous step (the next step then takes them at its own start)."""
        self._frame_valid = False
