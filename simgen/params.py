"""The parameters of the physical terms that the Warp solver (:mod:`simgen.sim.energies`) and the
torch losses (:mod:`simgen.physics`) share: one definition, validated once, with neither Warp nor
torch imported (``import simgen.physics`` does not load Warp).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from simgen.errors import InputError

__all__ = ["ContactParams", "GravityParams", "FrictionParams", "check_penalty_params"]


def check_penalty_params(params, label: str, positive: tuple[str, ...], *, above: tuple[str, str]) -> None:
    """Validate a frozen dataclass of a penalty k * max(margin - d, 0)^power in place: each field in
    ``positive`` a finite number > 0 (stored as float), power >= 2, and ``above`` = (a, b) with a > b.
    Raises InputError naming ``label`` and the field."""
    for name in positive:
        v = getattr(params, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise InputError(f"{label} {name} must be a finite number > 0, got {v!r}")
        object.__setattr__(params, name, float(v))
    if params.power < 2.0:
        raise InputError(f"{label} power must be >= 2 (C1 energy, bounded Hessian), got {params.power!r}")
    a, b = above
    if getattr(params, a) <= getattr(params, b):
        raise InputError(f"{label} {a} ({getattr(params, a)}) must exceed the {b} ({getattr(params, b)})")


@dataclass(frozen=True)
class ContactParams:
    """Body contact penalty k * max(margin - d, 0)^power.

    margin [m]: distance below which the penalty acts (SNUG: 2e-3).
    stiffness [J/m^power]: k (SNUG: 250 J/m^3; solver default 1e4 J/m^3, see simgen.sim.energies.contact).
    power [-]: p >= 2 so that the energy is C1 and its Hessian bounded (SNUG: 3).
    query_distance [m]: how far the closest-point query looks; a vertex deeper inside the body than
      this gets no contact force, so it must exceed the deepest expected penetration.
    pinch_distance [m]: a cloth vertex inside another body part and within this distance of its own
      part keeps to its own part (where the body intersects itself; see simgen.sim.energies.contact). Used only
      when body part labels are given; must exceed the margin.
    """

    margin: float = 2.0e-3
    stiffness: float = 1.0e4
    power: float = 3.0
    query_distance: float = 0.05
    pinch_distance: float = 5.0e-3

    def __post_init__(self) -> None:
        check_penalty_params(self, "contact", ("margin", "stiffness", "power", "query_distance", "pinch_distance"),
                             above=("query_distance", "margin"))
        if self.pinch_distance <= self.margin:
            raise InputError(f"contact pinch_distance ({self.pinch_distance}) must exceed the margin ({self.margin})")

    @classmethod
    def snug(cls) -> "ContactParams":
        """SNUG's training values: margin 2 mm, k = 250 J/m^3, p = 3."""
        return cls(margin=2.0e-3, stiffness=250.0, power=3.0)


@dataclass(frozen=True)
class GravityParams:
    """gravity [m/s^2]: the acceleration vector; the world is Y-up, (0, -9.81, 0)."""

    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)

    def __post_init__(self) -> None:
        g = tuple(float(c) for c in self.gravity)
        if len(g) != 3 or not all(math.isfinite(c) for c in g):
            raise InputError(f"gravity must be 3 finite numbers, got {self.gravity!r}")
        object.__setattr__(self, "gravity", g)


@dataclass(frozen=True)
class FrictionParams:
    """smoothing_velocity eps_v [m/s]: slip speeds below it are treated as (smoothed) sticking.

    IPC's default 1e-3 m/s: well below visible sliding speeds, and with h = 1/300 s the sticking
    zone (eps_v h = 3.3e-6 m) still spans ~30 float32 ulps of a 1 m coordinate.

    max_normal_load [-]: cap on the lagged normal force lambda, in multiples of the vertex's own
    weight m g (inf: no cap). The penalty's normal force is the real contact load in resting
    contact (a T-shirt on the open body: median 3x, 99th percentile 25x the vertex weight on the
    shoulders), but where cloth is pinched between body parts that the skinned body drives into
    each other (hem between swinging thighs, armpits) it reaches 100-15,000x; lagged into friction
    that glues the cloth to the moving limb, which drags it into the pinch, which raises lambda
    further, and the T-shirt was pulled off the body within a second of ``walk_fast``. 20 leaves
    resting contact nearly untouched and bounds the friction drag to 0.3 x 20 g = 59 m/s^2.
    """

    smoothing_velocity: float = 1.0e-3
    max_normal_load: float = 20.0

    def __post_init__(self) -> None:
        v = self.smoothing_velocity
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise InputError(f"friction smoothing_velocity must be a finite number > 0, got {v!r}")
        object.__setattr__(self, "smoothing_velocity", float(v))
        c = self.max_normal_load
        if isinstance(c, bool) or not isinstance(c, (int, float)) or math.isnan(c) or c <= 0:
            raise InputError(f"friction max_normal_load must be a number > 0 (inf: no cap), got {c!r}")
        object.__setattr__(self, "max_normal_load", float(c))
