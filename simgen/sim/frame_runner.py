"""One frame of a batched simulation for every active slot: the substeps, their CUDA graphs, the
retry and freeze policy, and the slots that start and end jobs between frames.

A frame is ``substeps`` S solver steps. Each poses the body on the device from the frame's joint
rotations at the substep's end (:meth:`WarpBody.pose_from_quats`, the shape too while it changes),
refits the collider's meshes and takes one :meth:`ImplicitSolver.step` (:meth:`FrameRunner._substeps`).
On CUDA the whole frame replays as one captured graph, one per (reshape, retry level) for the
current set of refit bodies (:func:`refit_slots`); the CPU, and
the first frame (it loads every kernel and takes the first lagged contacts), run the same sequence
eagerly.

The solver's guard runs inside the graph and is read once per frame (:meth:`FrameRunner.run`): the
instances that failed it are redone from the frame's start with every substep split into 2, then
4, ... solver steps (``SolverConfig.max_retries`` levels, each its own graph) while the others are
held where they got (:meth:`FrameRunner._retry`), so no instance's result depends on its batch mates'
failures. An instance still not finite after the last level is frozen (:meth:`FrameRunner._freeze`:
back at the frame start, pinned, its body switched off) and recorded in ``failures``; one that is
finite but still fails the guard is kept and counted unresolved. With self-contact on, an instance
that ends the frame through itself is then untangled (:mod:`simgen.sim.tangle_repair`).

A slot is active (its job steps) or idle: pinned where it is, still and without a body, so it
takes no part in the physics (the membrane and bending kernels skip it, ``ClothModel.instance_active``;
the body's posing, contact and the solver's other launches still pass over it). The frame refits
the body BVHs of :func:`refit_slots` only: every active slot, and idle ones until enough are idle
to be worth capturing the frame's graphs again without them (an idle slot's refits were about two
fifths of its cost on an H200, BENCHMARKS.md). :meth:`FrameRunner.place`
starts a job in an idle slot before the next frame: its garment at its start positions, and the
body of every slot posed where it is, the new slot's at the job's start pose, with no velocity.
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from simgen.sim.batch import BatchSetup
from simgen.sim.tangle_repair import TangleRepair

__all__ = ["FrameRunner", "refit_slots"]


def refit_slots(active: np.ndarray, current: tuple) -> tuple:
    """The slots whose body BVHs a frame refits, given the slots ``active`` (bool (N,)) and the set
    the frames so far refit (each change captures the frame's graphs again): ``current`` with any
    active slot it lacks added, until N / 8 of its slots are idle; then exactly the active slots."""
    busy = {int(k) for k in np.flatnonzero(active)}
    grown = set(current) | busy
    if len(grown) - len(busy) < max(1, len(active) // 8):
        return current if grown == set(current) else tuple(sorted(grown))
    return tuple(sorted(busy))


@wp.kernel(enable_backward=False)
def _hold_instances(pinned_before: wp.array(dtype=wp.int32), vertex_instance: wp.array(dtype=wp.int32),
                    held: wp.array(dtype=wp.int32), pinned: wp.array(dtype=wp.int32), v: wp.array(dtype=wp.vec3)):
    # Held instances are pinned with zero velocity (kinematic and still); the others keep their pins.
    i = wp.tid()
    if held[vertex_instance[i]] != 0:
        pinned[i] = 1
        v[i] = wp.vec3(0.0)
    else:
        pinned[i] = pinned_before[i]


@wp.kernel(enable_backward=False)
def _select_instances(src_x: wp.array(dtype=wp.vec3), src_v: wp.array(dtype=wp.vec3),
                      vertex_instance: wp.array(dtype=wp.int32), chosen: wp.array(dtype=wp.int32),
                      x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    if chosen[vertex_instance[i]] != 0:
        x[i] = src_x[i]
        v[i] = src_v[i]


class FrameRunner:
    """Steps the active slots of a :class:`BatchSetup` one frame at a time.

    Every slot starts idle: pinned where it is, with no body (it takes no part in the physics).
    :meth:`place` starts a job in a slot at the next frame; :meth:`release` makes it idle again.
    ``failures``: slot -> (phase, frame, message) of the slots frozen (and so made idle) since the
    caller last took them (:meth:`take_failures`). ``step_time`` [s]: the last frame's stepping
    (posing, refits, solver, retries), synchronised.
    """

    def __init__(self, setup: BatchSetup) -> None:
        self.setup = setup
        cfg, dev = setup.config, setup.device
        S, N, nb = setup.substeps, setup.num_instances, max(setup.body.num_betas, 1)
        self.max_level = cfg.solver.max_retries if cfg.solver.guard else 0
        self.failures: dict[int, tuple[str, int, str]] = {}
        self.step_time = 0.0
        self._graphs: dict = {}
        self._frames_run = 0
        model = setup.model
        self._frame_start = model.state()
        self._accepted = model.state()
        self._body_start = wp.clone(setup.collider.points)
        self._held = wp.zeros(N, dtype=wp.int32, device=dev)
        # Per-frame body targets on the device; substep s poses from row s (views, no allocation later).
        self._quats = wp.zeros((S, N, 24), dtype=wp.quat, device=dev)
        self._trans = wp.zeros((S, N), dtype=wp.vec3, device=dev)
        self._betas = wp.zeros((S, N, nb), dtype=wp.float32, device=dev)
        self._rows = [(self._quats[s], self._trans[s], self._betas[s]) for s in range(S)]
        # Where each slot's body is now (host): joint rotations xyzw, root translation [m], shape.
        self._q_now = np.zeros((N, 24, 4), dtype=np.float32)
        self._q_now[..., 3] = 1.0
        self._tr_now = np.zeros((N, 3), dtype=np.float32)
        self._betas_now = np.zeros((N, nb))
        # The slots' own pins and bodies, restored when a job starts in one.
        self._pinned = model.vertex_pinned.numpy().copy()
        self._mesh_ids = setup.collider.mesh_ids.numpy().copy()
        self.active = np.zeros(N, dtype=bool)
        setup.collider.refit_slots = tuple(range(N))
        self._placed: dict[int, tuple] = {}
        # With self-contact on, cloth that ends a frame through itself is untangled before it is recorded.
        self.repair = (TangleRepair(setup.garment.faces, len(setup.start_positions), N, dev)
                       if cfg.solver.self_contact is not None else None)
        self._idle(range(N))

    @property
    def betas_now(self) -> np.ndarray:
        """Each slot's body shape at the end of the last frame, (N, nb)."""
        return self._betas_now

    @property
    def pose_now(self) -> tuple[np.ndarray, np.ndarray]:
        """Each slot's joint rotations xyzw (N, 24, 4) and root translation [m] (N, 3) now: the
        targets of an idle slot, which keep its body where it is."""
        return self._q_now, self._tr_now

    def place(self, slot: int, quats: np.ndarray, trans: np.ndarray, positions: np.ndarray,
              step_divisor: int = 1) -> None:
        """Start a job in idle ``slot`` at the next :meth:`run`: its body at rest shape in pose
        quats xyzw (24, 4) at root translation trans [m] (3,), its garment at positions [m] (V, 3)
        at rest, its pins and body back on; step_divisor: its solver steps take the batch's substep
        divided by this (1, 2, 4, ...: the job runs at that many times the substeps, each
        :meth:`run` then advancing it by that fraction of a frame)."""
        if self.active[slot]:
            raise ValueError(f"slot {slot} is busy")
        self._placed[slot] = (quats, trans, positions, int(step_divisor))
        self.active[slot] = True

    def release(self, slots) -> None:
        """Make ``slots`` idle: pinned where they are, still, with no body."""
        slots = list(slots)
        self.active[slots] = False
        for i in slots:
            self._placed.pop(i, None)   # placed but not started yet: it never starts
        self._idle(slots)

    def take_failures(self) -> dict:
        """The slots frozen since the last call: slot -> (phase, frame, message)."""
        out, self.failures = self.failures, {}
        return out

    def run(self, quats: np.ndarray, trans: np.ndarray, betas: np.ndarray, where: list) -> None:
        """Step one frame of every active slot (module doc: retries, freezing).

        quats xyzw (S, N, 24, 4), trans [m] (S, N, 3), betas (S, N, nb): the body targets at the
        substeps' ends (an idle slot's rows hold :attr:`pose_now` and :attr:`betas_now`); where:
        (phase, k) of each slot's frame (None for idle), what a failure records.
        """
        s = self.setup
        refit = refit_slots(self.active, s.collider.refit_slots)
        if refit != s.collider.refit_slots:
            s.collider.refit_slots = refit   # before the new jobs' bodies are placed (and refit)
            self._graphs.clear()             # captured with the old set
        self._start_placed()
        self._quats.assign(np.ascontiguousarray(quats, dtype=np.float32))
        self._trans.assign(np.ascontiguousarray(trans, dtype=np.float32))
        # Re-shape only while some shape changes (a ramp), never for a shapeless body model.
        reshape = s.body.num_betas > 0 and not np.all(betas == self._betas_now[None])
        if reshape:
            self._betas.assign(np.ascontiguousarray(betas, dtype=np.float32))
        wp.synchronize_device(s.device)
        t0 = time.perf_counter()
        self._frame(reshape, where, eager=self._frames_run == 0 or not s.use_graph)
        wp.synchronize_device(s.device)
        self.step_time = time.perf_counter() - t0
        self._frames_run += 1
        self._q_now = np.array(quats[-1], dtype=np.float32)
        self._tr_now = np.array(trans[-1], dtype=np.float32)
        self._betas_now = np.array(betas[-1])

    # -- slots --------------------------------------------------------------------------------------
    def _idle(self, slots) -> None:
        s = self.setup
        model, state, collider = s.model, s.state, s.collider
        starts = np.asarray(model.vertex_start)
        pinned, ids, vel = model.vertex_pinned.numpy(), collider.mesh_ids.numpy(), state.velocities.numpy()
        divisor, active = model.instance_step_divisor.numpy(), model.instance_active.numpy()
        for i in slots:
            pinned[starts[i]:starts[i + 1]] = 1
            vel[starts[i]:starts[i + 1]] = 0.0
            ids[i] = 0
            divisor[i] = 1
            active[i] = 0
        model.vertex_pinned.assign(pinned)
        model.instance_step_divisor.assign(divisor)
        model.instance_active.assign(active)
        collider.mesh_ids.assign(ids)
        state.velocities.assign(vel)

    def _start_placed(self) -> None:
        """Put the jobs placed since the last frame into their slots: garment, pins, body (moved
        there at rest, no velocity), no warm-start guesses, and friction's lagged contacts of every
        slot taken again."""
        if not self._placed:
            return
        s = self.setup
        model, state, collider = s.model, s.state, s.collider
        starts = np.asarray(model.vertex_start)
        x, v = state.positions.numpy(), state.velocities.numpy()
        pinned, ids = model.vertex_pinned.numpy(), collider.mesh_ids.numpy()
        divisor, active = model.instance_step_divisor.numpy(), model.instance_active.numpy()
        for i, (q, tr, pos, d) in self._placed.items():
            divisor[i] = d
            active[i] = 1
            a, b = starts[i], starts[i + 1]
            x[a:b] = pos
            v[a:b] = 0.0
            pinned[a:b] = self._pinned[a:b]
            ids[i] = self._mesh_ids[i]
            self._q_now[i], self._tr_now[i], self._betas_now[i] = q, tr, 0.0
        for arr, host in ((state.positions, x), (state.velocities, v), (model.vertex_pinned, pinned),
                          (collider.mesh_ids, ids), (model.instance_step_divisor, divisor),
                          (model.instance_active, active)):
            arr.assign(host)
        if s.body.num_betas > 0:
            s.wbody.set_shape(self._betas_now)
        dev = s.device
        s.wbody.pose_from_quats(wp.array(self._q_now, dtype=wp.quat, device=dev),
                                wp.array(self._tr_now, dtype=wp.vec3, device=dev))
        collider.update()                  # a teleport: the other slots' bodies are posed where they are
        s.solver.take_contacts(state, collider)
        s.solver.forget_steps(list(self._placed))
        self._placed = {}

    # -- the frame and its retries ------------------------------------------------------------------
    def _frame(self, reshape: bool, where: list, eager: bool) -> None:
        s = self.setup
        self._frame_start.assign(s.state)
        wp.copy(self._body_start, s.collider.points)
        bad = self._attempt(reshape, 0, eager)
        failing = [i for i in range(s.num_instances) if bad[i] and self.active[i]]
        level = 0
        while failing and level < self.max_level:
            level += 1
            s.solver.count_retries(failing)
            bad = self._retry(reshape, level, eager, failing)
            failing = [i for i in failing if bad[i]]
        if failing:
            diverged = [i for i in failing if bad[i] & 1]
            s.solver.count_unresolved([i for i in failing if not bad[i] & 1])
            if diverged:
                self._freeze(diverged, where, f"the cloth step still produced non-finite positions after "
                                              f"{self.max_level} retries at up to {2 ** self.max_level} solver "
                                              f"steps per substep")
        if level > 0:
            # Friction's lagged contacts at the frame's end for every instance (the retry took the
            # held instances' without their body).
            s.solver.take_contacts(s.state, s.collider)
        if self.repair is not None:
            self.repair(s.state, s.model.vertex_pinned, self.active, reference=self._frame_start.positions)

    def _substeps(self, reshape: bool, level: int) -> None:
        """The frame's S substeps (each split into 2^level solver steps), as launched or captured."""
        s = self.setup
        s.solver.clear_deferred_guard()
        if level > 0:
            # A retry starts from the restored frame start: friction's contacts are taken there
            # (at capture this puts their update into the retry's graph).
            s.solver.reset_contacts()
        for quats, trans, betas in self._rows:
            if reshape:
                s.wbody.set_shape(betas)
            s.wbody.pose_from_quats(quats, trans)
            s.collider.update(dt=s.dt, step_divisor=s.model.instance_step_divisor)
            s.solver.step(s.state, s.state, s.collider, s.dt, deferred_guard=True,
                          substeps=2 ** level)

    def _attempt(self, reshape: bool, level: int, eager: bool) -> np.ndarray:
        """Run the frame's substeps once; the guard's failure bits per instance, (N,) int."""
        solver = self.setup.solver
        if eager:
            self._substeps(reshape, level)
        else:
            key = (reshape, level)
            if key not in self._graphs:
                before = solver.host_counts()
                with wp.ScopedCapture(device=self.setup.device, force_module_load=False) as capture:
                    self._substeps(reshape, level)
                after = solver.host_counts()
                self._graphs[key] = (capture.graph, {c: after[c] - before[c] for c in after})
                solver.add_host_counts({c: -v for c, v in self._graphs[key][1].items()})
            graph, delta = self._graphs[key]
            wp.capture_launch(graph)
            solver.add_host_counts(delta)
        return solver.deferred_bad.numpy()

    def _retry(self, reshape: bool, level: int, eager: bool, failing: list) -> np.ndarray:
        """Redo the frame from its start for ``failing`` only, at 2^level solver steps per substep.

        The other instances are held: restored afterwards to the state (and the solver's warm-start
        guesses) they reached, and in between pinned at the frame start with zero velocity and no
        body, so they neither move nor change the retried ones.
        """
        s = self.setup
        model, state, collider = s.model, s.state, s.collider
        hold = np.ones(s.num_instances, dtype=np.int32)
        hold[failing] = 0
        self._accepted.assign(state)
        state.assign(self._frame_start)
        wp.copy(collider.points, self._body_start)
        pinned = wp.clone(model.vertex_pinned)
        ids = collider.mesh_ids.numpy().copy()  # .numpy() is a view of the array on the CPU
        collider.mesh_ids.assign(np.where(hold != 0, np.uint64(0), ids))
        self._held.assign(hold)
        wp.launch(_hold_instances, dim=model.num_vertices, device=s.device,
                  inputs=[pinned, model.vertex_instance, self._held, model.vertex_pinned, state.velocities])
        guesses = [wp.clone(g) for g in s.solver.step_guesses]
        bad = self._attempt(reshape, level, eager)
        collider.mesh_ids.assign(ids)
        wp.copy(model.vertex_pinned, pinned)
        wp.launch(_select_instances, dim=model.num_vertices, device=s.device,
                  inputs=[self._accepted.positions, self._accepted.velocities, model.vertex_instance, self._held,
                          state.positions, state.velocities])
        # The held instances keep their warm-start guesses too (pinned, the retry zeroed them).
        for saved, g in zip(guesses, s.solver.step_guesses):
            wp.launch(_select_instances, dim=model.num_vertices, device=s.device,
                      inputs=[saved, saved, model.vertex_instance, self._held, g, g])
        return bad

    def _freeze(self, instances: list, where: list, message: str) -> None:
        """Back to the frame start, then idle: the slots stop; their jobs fail."""
        s = self.setup
        model, state = s.model, s.state
        chosen = np.zeros(s.num_instances, dtype=np.int32)
        chosen[list(instances)] = 1
        self._held.assign(chosen)
        wp.launch(_select_instances, dim=model.num_vertices, device=s.device,
                  inputs=[self._frame_start.positions, self._frame_start.velocities, model.vertex_instance,
                          self._held, state.positions, state.velocities])
        for i in instances:
            phase, k = where[i]
            self.failures[i] = (phase, k, message)
        self.release(instances)
