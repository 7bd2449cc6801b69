"""The flesh's parameters, declared once (:mod:`simgen.settings`): material by region, the fat
layer, damping, and the integrator's rates.

Regions (:data:`REGIONS`) come from the skinning weights of the body (the joint that moves a
tetrahedron most) and, on the torso, from front and back. Belly, chest, buttocks, thighs and upper
arms are soft; head, hands, shins and feet stiff, with a thinner free layer.
"""

from __future__ import annotations

from dataclasses import dataclass

from simgen.settings import documented, setting, validate

__all__ = ["REGIONS", "SOFT_REGIONS", "FleshParams"]

#: Region names, in the order of the per-tetrahedron region ids.
REGIONS = ("belly", "chest", "buttocks", "back", "thigh", "upper_arm", "forearm", "shin", "foot", "hand", "head")
SOFT_REGIONS = ("belly", "chest", "buttocks", "thigh", "upper_arm")
_STIFF_REGIONS = ("shin", "foot", "hand", "head")


@documented
@dataclass(frozen=True)
class FleshParams:
    """Parameters of the soft-tissue simulation (SI units)."""

    density: float = setting(1000.0, low=0.0, inclusive=False, doc="[kg/m^3] flesh density (fat ~900, muscle ~1060)")
    poisson: float = setting(0.4, low=0.0, high=0.49, doc="[-] Poisson's ratio (linear tetrahedra lock near 0.5)")
    young_soft: float = setting(6.0e3, low=0.0, inclusive=False,
                                doc="[Pa] Young's modulus of belly, chest, buttocks (the layer's fat and muscle)")
    young_limb: float = setting(1.0e4, low=0.0, inclusive=False, doc="[Pa] thighs and upper arms")
    young_medium: float = setting(2.0e4, low=0.0, inclusive=False, doc="[Pa] back and forearms")
    young_stiff: float = setting(5.0e4, low=0.0, inclusive=False, doc="[Pa] head, hands, shins and feet")
    layer: float = setting(0.025, low=0.0, inclusive=False,
                           doc="[m] free (unpinned) layer under the skin on the template body's mass; deeper nodes "
                               "move with the skeleton")
    layer_exponent: float = setting(1.0, low=0.0,
                                    doc="[-] the layer scales with (body-mass proxy / the template's)^exponent")
    stiff_layer: float = setting(0.0, low=0.0, high=1.0,
                                 doc="[-] share of the layer free on head, hands, shins, feet (0: bone under the "
                                     "skin, they move with the skeleton; fingers are thinner than the mesh)")
    damping_mass: float = setting(0.0, low=0.0, doc="[1/s] Rayleigh damping C = a M + b K: a")
    damping_stiffness: float = setting(6.4e-3, low=0.0,
                                       doc="[s] Rayleigh b (6.4 ms: 10% of critical at 5 Hz, more above)")
    gravity: float = setting(9.81, low=0.0, doc="[m/s^2] gravity along -y (0: none)")
    rate: float = setting(240.0, low=1.0, doc="[1/s] integration steps per second")
    fps: float = setting(60.0, low=0.0, inclusive=False, doc="[1/s] output frames per second (rate a multiple of it)")
    lowpass: float = setting(12.0, low=0.0, inclusive=False,
                             doc="[Hz] cut-off of the zero-phase low-pass on the skeleton's motion before it is "
                                 "differenced")
    cg_tolerance: float = setting(1.0e-6, low=0.0, inclusive=False, doc="[-] relative PCG residual")
    cg_iterations: int = setting(400, low=1, doc="PCG iterations at most per solve")

    def __post_init__(self) -> None:
        validate(self, "soft-tissue")
        from simgen.errors import InputError

        steps = self.rate / self.fps
        if abs(steps - round(steps)) > 1e-9:
            raise InputError(f"soft-tissue rate ({self.rate:g}/s) must be a multiple of fps ({self.fps:g}/s)")
        if not self.lowpass < 0.5 * self.rate:
            raise InputError(f"soft-tissue lowpass ({self.lowpass:g} Hz) must be below half the rate "
                             f"({0.5 * self.rate:g} Hz)")

    def young(self, region: str) -> float:
        """Young's modulus [Pa] of a region of :data:`REGIONS`."""
        if region in ("belly", "chest", "buttocks"):
            return self.young_soft
        if region in ("thigh", "upper_arm"):
            return self.young_limb
        if region in _STIFF_REGIONS:
            return self.young_stiff
        return self.young_medium

    def layer_share(self, region: str) -> float:
        """Share of the free layer in a region (1, or ``stiff_layer`` on head, hands, shins, feet)."""
        return self.stiff_layer if region in _STIFF_REGIONS else 1.0
