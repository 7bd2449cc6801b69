"""The solver's and the simulation's settings: :class:`SolverConfig` (one implicit step) and
:class:`SimulationConfig` (a garment on a moving body: frame rate, substeps, the start protocol).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from simgen.errors import InputError
from simgen.materials import Material, get_material
from simgen.params import ContactParams, FrictionParams, GravityParams
from simgen.sim.energies.self_contact import SelfContactParams

__all__ = ["SolverConfig", "SimulationConfig"]


@dataclass(frozen=True)
class SolverConfig:
    """Options of :class:`ImplicitSolver` (SI units).

    newton_iterations: Newton iterations per (sub)step (ARCSim: 1).
    newton_tolerance [m]: if > 0, stop iterating once the largest vertex update is below it (costs a
      host read per iteration, so it is off by default and for graph capture).
    cg_iterations: PCG iterations launched per Newton iteration (work stops once converged).
    cg_tolerance: relative PCG tolerance on the preconditioned residual.
    line_search: backtrack alpha = 1, 1/2, ... (``line_search_steps`` trials, Armijo constant
      ``armijo``) on each instance's incremental potential.
    substeps: equal substeps per :meth:`ImplicitSolver.step` (the body moves linearly across them).
    gravity, contact, friction: the energy parameters; friction=None switches friction off.
    self_contact: cloth-cloth vertex-triangle repulsion (:class:`SelfContactParams`); None (default)
      switches it off.
    floor [m]: height of the ground plane y = floor (the body contact's penalty against it and,
      with ``project``, a projection onto it after each substep; :mod:`simgen.sim.energies.floor`);
      None: no floor.
    damping: include the material damping potential (only matters if the material has damping).
    strain_limit: if set, after each (sub)step no triangle stretches past 1 + strain_limit in any
      direction (:mod:`simgen.sim.strain_limit`, ``strain_limit_iterations`` Jacobi passes, before
      the body projection); None (default) leaves plain backward Euler.
    project: after each step push vertices found inside the body onto it (offset
      ``projection_offset`` [m] outside) and remove their inward normal velocity.
    constraint_rounds: how many times the strain limiter and the body projection alternate after
      each substep (both project onto a constraint set: each undoes part of the other, and
      alternating approaches a state that meets both; the body projection always comes last, so
      the output is never inside the body). 1 (default) runs each once.
    guard: check each step for divergence and retry it as two half steps, up to ``max_retries``
      levels. max_speed [m/s]: a vertex faster than this marks divergence. divergence_ratio: E may
      rise at most this many times the first Newton model's predicted decrease.
    guard_energy: the guard's energy test (True, default). False keeps only its non-finite and
      max_speed tests and skips the energy passes the test needs (the first assembly's energy and
      one energy evaluation after each step). With a stiff contact penalty E can rise within a step
      that stays finite and slow (the projection then resolves the contact), and the test redoes
      such steps at up to 2^max_retries finer ones: on the T-shirt every retry came from it, so the
      thesis presets turn it off (BENCHMARKS.md, 2026-11-25).
    """

    newton_iterations: int = 1
    newton_tolerance: float = 0.0
    cg_iterations: int = 50
    cg_tolerance: float = 1.0e-3
    line_search: bool = False
    line_search_steps: int = 8
    armijo: float = 1.0e-4
    substeps: int = 1
    gravity: GravityParams = field(default_factory=GravityParams)
    contact: ContactParams = field(default_factory=ContactParams)
    friction: FrictionParams | None = field(default_factory=FrictionParams)
    self_contact: SelfContactParams | None = None
    floor: float | None = 0.0
    damping: bool = True
    strain_limit: float | None = None
    strain_limit_iterations: int = 8
    project: bool = True
    projection_offset: float = 0.0
    constraint_rounds: int = 1
    guard: bool = True
    max_retries: int = 4
    max_speed: float = 50.0
    divergence_ratio: float = 10.0
    guard_energy: bool = True

    def __post_init__(self) -> None:
        if self.floor is not None and (isinstance(self.floor, bool) or not isinstance(self.floor, (int, float))
                                       or not math.isfinite(self.floor)):
            raise InputError(f"solver floor must be a finite number [m] or None, got {self.floor!r}")
        if self.strain_limit is not None and not (isinstance(self.strain_limit, (int, float))
                                                  and not isinstance(self.strain_limit, bool)
                                                  and math.isfinite(self.strain_limit) and self.strain_limit > 0):
            raise InputError(f"solver strain_limit must be a finite number > 0 or None, got {self.strain_limit!r}")
        for name in ("newton_iterations", "cg_iterations", "line_search_steps", "substeps", "strain_limit_iterations",
                     "constraint_rounds"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise InputError(f"solver {name} must be an integer >= 1, got {v!r}")
        if isinstance(self.max_retries, bool) or not isinstance(self.max_retries, int) or self.max_retries < 0:
            raise InputError(f"solver max_retries must be an integer >= 0, got {self.max_retries!r}")
        for name in ("newton_tolerance", "cg_tolerance", "projection_offset"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise InputError(f"solver {name} must be a finite number >= 0, got {v!r}")
        for name in ("armijo", "max_speed", "divergence_ratio"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"solver {name} must be a finite number > 0, got {v!r}")



@dataclass(frozen=True)
class SimulationConfig:
    """Options of :func:`simulate` (SI units).

    fps [1/s]: output frame rate; None takes the clip's. The frame time step is 1 / fps.
    substeps: solver steps per frame (10 at 30 fps: dt = 3.33 ms, the thesis's ARCSim step); the body
      is re-posed from slerped joint rotations before each.
    solver: the :class:`SolverConfig`; default: one Newton iteration, projection 0.2 mm outside the
      body so projected vertices count as outside.
    material: preset name or :class:`Material`; None takes the garment's default_material, else cotton.
    material_overrides: Material fields to replace, e.g. ``{"area_density": 0.25}``.
    relax_frames, ramp_frames (>= 1), rest_frames: the start protocol's frame counts (module doc).
    self_intersection_probe [m]: outward offset of the self-intersection test (module doc).
    query_distance [m]: deepest penetration the statistics can see.
    record_body: keep the posed body vertices of every output frame (SimulationResult.body_vertices).
    device: Warp device (None: Warp's default).
    cuda_graph: on CUDA, replay each frame's substeps as one captured CUDA graph (see
      :func:`simulate_batch`); the CPU always runs them eagerly.
    """

    fps: float | None = None
    substeps: int = 10
    solver: SolverConfig = field(default_factory=lambda: SolverConfig(projection_offset=2.0e-4))
    material: str | Material | None = None
    material_overrides: dict = field(default_factory=dict)
    relax_frames: int = 15
    ramp_frames: int = 30
    rest_frames: int = 15
    self_intersection_probe: float = 2.0e-3
    query_distance: float = 0.05
    record_body: bool = False
    device: str | None = None
    cuda_graph: bool = True

    def __post_init__(self) -> None:
        if self.fps is not None and not (isinstance(self.fps, (int, float)) and not isinstance(self.fps, bool)
                                         and math.isfinite(self.fps) and self.fps > 0):
            raise InputError(f"simulation fps must be a finite number > 0 or None, got {self.fps!r}")
        for name, low in (("substeps", 1), ("relax_frames", 0), ("ramp_frames", 1), ("rest_frames", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise InputError(f"simulation {name} must be an integer >= {low}, got {v!r}")
        if not isinstance(self.solver, SolverConfig):
            raise InputError(f"simulation solver must be a SolverConfig, got {type(self.solver).__name__}")
        for name in ("self_intersection_probe", "query_distance"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                raise InputError(f"simulation {name} must be a finite number > 0, got {v!r}")
        if not isinstance(self.material_overrides, dict):
            raise InputError("simulation material_overrides must be a dict of Material fields")

    def resolve_material(self, garment=None) -> Material:
        """The Material this config simulates (preset or given, defaults from the garment, overrides applied)."""
        name = self.material
        if name is None:
            name = ((getattr(garment, "metadata", None) or {}).get("default_material")) or "cotton"
        material = get_material(name)
        if self.material_overrides:
            known = set(Material.__dataclass_fields__)
            bad = sorted(set(self.material_overrides) - known)
            if bad:
                raise InputError(f"unknown material fields {bad}; fields are: {', '.join(sorted(known))}")
            material = replace(material, **self.material_overrides)
        return material
