"""The solver's and the simulation's settings: :class:`SolverConfig` (one implicit step) and
:class:`SimulationConfig` (a garment on a moving body: frame rate, substeps, the start protocol).

Each field is declared once, with its type, bounds, default and a one-line doc with its unit
(:func:`simgen.settings.setting`); the classes' docstrings list them, the dataset spec's
``[solver]`` and ``[protocol]`` tables and the ``simgen simulate`` flags are derived from them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from simgen.errors import InputError
from simgen.materials import Material, get_material
from simgen.params import ContactParams, FrictionParams, GravityParams, SelfContactParams
from simgen.settings import documented, setting, validate

__all__ = ["SolverConfig", "SimulationConfig"]


@documented
@dataclass(frozen=True)
class SolverConfig:
    """Options of :class:`ImplicitSolver` (SI units).

    Newton iterations: three by default. One, the linearised step of Baraff and Witkin and of
    ARCSim, dissipates the cloth's swing (a sheet hinged along one edge and released from
    horizontal swings back 17% less high than converged backward Euler takes it; two and three
    iterations agree with it, tests/test_sim_solver.py), and in the demo's walk the T-shirt's hem
    then stays pressed onto the thighs: up to 79-83% of its lowest 10 cm within 3 mm of the body
    with one iteration, 63% with two, 40% with three (BENCHMARKS.md, 2026-11-29).

    The Newton tolerance costs a host read per iteration, so it is off by default and for graph
    capture. The floor acts through the body contact's penalty against it and, with ``project``, a
    projection onto it after each substep (:mod:`simgen.sim.energies.floor`). The strain limiter
    (:mod:`simgen.sim.strain_limit`) runs before the body projection; without it the step is plain
    backward Euler.

    Constraint rounds: the strain limiter and the body projection both project onto a constraint
    set, each undoes part of the other, and alternating approaches a state that meets both; the
    body projection always comes last, so the output is never inside the body.

    The guard checks each step for divergence (non-finite, a vertex faster than ``max_speed``, or
    with ``guard_energy`` an energy rise beyond ``divergence_ratio`` times the first Newton model's
    predicted decrease) and retries it as two half steps, up to ``max_retries`` levels. The energy
    test is off by default: it needs extra energy passes (the first assembly's energy and one
    evaluation after each step), and with a stiff contact penalty or a stiff measured knit E can
    rise within a step that stays finite and slow (the projection then resolves the contact); the
    test redoes such steps at up to 2^max_retries finer ones: on the T-shirt every retry came from
    it, on a quarter of the frames in interlock, with nothing deeper in the body without it
    (measurements: BENCHMARKS.md, docs/sim.md).
    """

    newton_iterations: int = setting(3, low=1, doc="Newton iterations per (sub)step (ARCSim: 1; see above)")
    newton_tolerance: float = setting(0.0, low=0.0, doc="[m] if > 0, stop iterating once the largest vertex "
                                                         "update is below it")
    cg_iterations: int = setting(50, low=1, doc="PCG iterations launched per Newton iteration (work stops "
                                                 "once converged)")
    cg_tolerance: float = setting(1.0e-3, low=0.0, doc="[-] relative PCG tolerance on the preconditioned residual")
    cg_warm_start: bool = setting(True, doc="start each Newton iteration's PCG from the same iteration's step of "
                                            "the previous substep (the tolerance stays relative to the right-hand "
                                            "side)")
    line_search: bool = setting(False, doc="backtrack alpha = 1, 1/2, ... on each instance's incremental potential")
    line_search_steps: int = setting(8, low=1, doc="trials of the line search")
    armijo: float = setting(1.0e-4, low=0.0, inclusive=False, doc="[-] the line search's Armijo constant")
    gravity: GravityParams = setting(default_factory=GravityParams, doc="the gravity term")
    contact: ContactParams = setting(default_factory=ContactParams, doc="the body contact penalty")
    friction: FrictionParams | None = setting(default_factory=FrictionParams,
                                              doc="lagged cloth-body friction; None: none")
    self_contact: SelfContactParams | None = setting(None, doc="cloth-cloth vertex-triangle repulsion; None: none")
    floor: float | None = setting(0.0, doc="[m] height of the ground plane y = floor; None: no floor")
    strain_limit: float | None = setting(None, low=0.0, inclusive=False,
                                         doc="[-] after each (sub)step no triangle stretches past 1 + strain_limit "
                                             "in any direction; None: no limit")
    strain_limit_iterations: int = setting(8, low=1, doc="Jacobi passes of the strain limiter")
    project: bool = setting(True, doc="after each substep push vertices found inside the body (or below the "
                                      "floor) out and remove their inward normal velocity")
    projection_offset: float = setting(2.0e-4, low=0.0, doc="[m] how far outside the body (above the floor) "
                                                            "projected vertices land, so they count as outside")
    constraint_rounds: int = setting(1, low=1, doc="how many times the strain limiter and the body projection "
                                                   "alternate after each substep")
    guard: bool = setting(True, doc="check each step for divergence and retry it as two half steps")
    max_retries: int = setting(4, low=0, doc="levels of halving the guard tries before it gives up")
    max_speed: float = setting(50.0, low=0.0, inclusive=False, doc="[m/s] a vertex faster than this marks "
                                                                     "divergence")
    divergence_ratio: float = setting(10.0, low=0.0, inclusive=False,
                                      doc="[-] E may rise at most this many times the first Newton model's "
                                          "predicted decrease")
    guard_energy: bool = setting(False, doc="the guard's energy test besides its non-finite and speed tests")

    def __post_init__(self) -> None:
        validate(self, "solver")


@documented
@dataclass(frozen=True)
class SimulationConfig:
    """Options of :func:`simulate` (SI units).

    The frame time step is 1 / fps; the body is re-posed from slerped joint rotations before each
    substep (10 at 30 fps: dt = 3.33 ms, the thesis's ARCSim step). The material is a preset name or
    a :class:`Material`; by default the garment's default_material, else cotton. The start
    protocol's phases (relax, ramp, rest) are described in :mod:`simgen.sim.driver`, the
    self-intersection test in :mod:`simgen.sim.frame_stats` (it sees as deep as the contact's
    ``query_distance``). The CPU ignores ``cuda_graph`` and runs the substeps eagerly (see
    :func:`simulate_batch`).
    """

    fps: float | None = setting(None, low=0.0, inclusive=False,
                                doc="[1/s] output frame rate; None takes the clip's")
    substeps: int = setting(10, low=1, doc="solver steps per frame")
    solver: SolverConfig = setting(default_factory=SolverConfig, doc="the solver's options")
    material: str | Material | None = setting(None, doc="preset name or Material; None: the garment's default")
    material_overrides: dict = setting(default_factory=dict, doc="Material fields to replace, e.g. "
                                                                 "{'area_density': 0.25}")
    relax_frames: int = setting(15, low=0, doc="frames of the start protocol's relax phase (template body, rest pose)")
    ramp_frames: int = setting(30, low=1, doc="frames of the start protocol's ramp to the target shape and first pose")
    rest_frames: int = setting(15, low=0, doc="frames of the start protocol's rest phase (the clip's first frame held)")
    record_body: bool = setting(False, doc="keep the posed body vertices of every output frame")
    device: str | None = setting(None, doc="Warp device; None: Warp's default")
    cuda_graph: bool = setting(True, doc="on CUDA, replay each frame's substeps as one captured CUDA graph")

    def __post_init__(self) -> None:
        validate(self, "simulation")

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
