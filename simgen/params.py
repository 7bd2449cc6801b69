"""The parameters of the physical terms that the Warp solver (:mod:`simgen.sim.energies`) and the
torch losses (:mod:`simgen.physics`) share: one definition, validated once, with neither Warp nor
torch imported (``import simgen.physics`` does not load Warp). Each field is declared once with
its bounds, default and unit (:func:`simgen.settings.setting`).
"""

from __future__ import annotations

from dataclasses import dataclass

from simgen.errors import InputError
from simgen.settings import documented, setting, validate

__all__ = ["ContactParams", "GravityParams", "FrictionParams", "SelfContactParams"]


def _check_above(params, label: str, a: str, b: str) -> None:
    """InputError unless field ``a`` of ``params`` exceeds field ``b``."""
    if getattr(params, a) <= getattr(params, b):
        raise InputError(f"{label} {a} ({getattr(params, a)}) must exceed the {b} ({getattr(params, b)})")


@documented
@dataclass(frozen=True)
class ContactParams:
    """Body contact penalty k * max(margin - d, 0)^power.

    SNUG trains with margin 2 mm, k = 250 J/m^3, p = 3 (:meth:`snug`); the solver's k is larger (see
    simgen.sim.energies.contact). The power is at least 2 so that the energy is C1 and its Hessian
    bounded. A vertex deeper inside the body than ``query_distance`` gets no contact force, so it must
    exceed the deepest expected penetration. ``pinch_distance`` is used only when body part labels
    are given (where the body intersects itself; the part rule of simgen.body.surface_query).
    """

    margin: float = setting(2.0e-3, low=0.0, inclusive=False,
                            doc="[m] distance below which the penalty acts")
    stiffness: float = setting(1.0e4, low=0.0, inclusive=False, doc="[J/m^power] the penalty's k")
    power: float = setting(3.0, low=2.0, doc="[-] the penalty's exponent p")
    query_distance: float = setting(0.05, low=0.0, inclusive=False,
                                    doc="[m] how far the closest-point query looks (must exceed the margin)")
    pinch_distance: float = setting(5.0e-3, low=0.0, inclusive=False,
                                    doc="[m] a cloth vertex inside another body part and within this distance of "
                                        "its own part keeps to its own part (must exceed the margin)")

    def __post_init__(self) -> None:
        validate(self, "contact")
        _check_above(self, "contact", "query_distance", "margin")
        _check_above(self, "contact", "pinch_distance", "margin")

    @classmethod
    def snug(cls) -> "ContactParams":
        """SNUG's training values: margin 2 mm, k = 250 J/m^3, p = 3."""
        return cls(margin=2.0e-3, stiffness=250.0, power=3.0)


@documented
@dataclass(frozen=True)
class GravityParams:
    """The gravity term; the world is Y-up."""

    gravity: tuple[float, float, float] = setting((0.0, -9.81, 0.0), doc="[m/s^2] the acceleration vector")

    def __post_init__(self) -> None:
        validate(self, "gravity")


@documented
@dataclass(frozen=True)
class FrictionParams:
    """Lagged cloth-body friction.

    Slip speeds below ``smoothing_velocity`` eps_v are treated as (smoothed) sticking. IPC's 1e-3 m/s
    is well below visible sliding speeds, and with h = 1/300 s the sticking zone (eps_v h = 3.3e-6 m)
    still spans ~30 float32 ulps of a 1 m coordinate.

    ``max_normal_load`` caps the lagged normal force lambda, in multiples of the vertex's own weight
    m g. The penalty's normal force is the real contact load in resting contact (a T-shirt on the
    open body: median 3x, 99th percentile 25x the vertex weight on the shoulders), but where cloth is
    pinched between body parts that the skinned body drives into each other (hem between swinging
    thighs, armpits) it reaches 100-15,000x; lagged into friction that glues the cloth to the moving
    limb, which drags it into the pinch, which raises lambda further, and the T-shirt was pulled off
    the body within a second of ``walk_fast``. A cap of 20 leaves resting contact nearly untouched
    and bounds the friction drag to 0.3 x 20 g = 59 m/s^2.
    """

    smoothing_velocity: float = setting(1.0e-3, low=0.0, inclusive=False,
                                        doc="[m/s] eps_v: slower slip counts as (smoothed) sticking")
    max_normal_load: float = setting(20.0, low=0.0, inclusive=False, finite=False,
                                     doc="[-] cap on the lagged normal force, in multiples of the vertex's "
                                         "weight m g (inf: no cap)")

    def __post_init__(self) -> None:
        validate(self, "friction")


@documented
@dataclass(frozen=True)
class SelfContactParams:
    """Cloth-cloth repulsion k * max(thickness - d, 0)^power between a vertex and a triangle and
    between two edges (:mod:`simgen.sim.energies.self_contact`).

    Two layers of cloth stay about ``thickness`` apart (the counterpart of the body contact's
    margin); stiffness and power read as the body contact penalty's (:class:`ContactParams`).
    Candidate triangles are gathered within ``search_radius`` at each substep's start, so it must
    exceed the thickness by a substep's travel (a 1 cm radius admits 2.4 m/s at 1/300 s).
    """

    thickness: float = setting(2.0e-3, low=0.0, inclusive=False,
                               doc="[m] distance below which the repulsion acts")
    stiffness: float = setting(1.0e4, low=0.0, inclusive=False, doc="[J/m^power] the penalty's k")
    power: float = setting(3.0, low=2.0, doc="[-] the penalty's exponent p")
    search_radius: float = setting(1.0e-2, low=0.0, inclusive=False,
                                   doc="[m] candidate triangles are gathered within it (must exceed the thickness)")
    max_candidates: int = setting(16, low=1, doc="triangles kept per vertex, and edges per edge (the first "
                                                 "found within the radius)")
    impact_rounds: int = setting(4, low=0, doc="detection passes of the impact filter per substep (0: no filter; "
                                               "a frame that ends through itself is untangled at its end either way)")

    def __post_init__(self) -> None:
        validate(self, "self-contact")
        _check_above(self, "self-contact", "search_radius", "thickness")
