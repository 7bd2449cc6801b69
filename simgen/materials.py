"""Cloth materials: named presets with their sources, overridable field by field.

A :class:`Material` holds what the energies need per garment instance: area density (mass),
Young's modulus, Poisson ratio and thickness (StVK membrane, plane stress), bending stiffness
(dihedral bending), the Coulomb friction coefficient against the body, and two Rayleigh-style
damping coefficients. The model (:mod:`simgen.sim.model`) turns them into per-element
coefficients, so every instance of a batched simulation can have its own material.

Damping model (see :mod:`simgen.sim.energies.damping`): an incremental dissipation potential,
added to the backward-Euler objective, whose force is Rayleigh damping ``-(alpha M + beta K) v``
in the small-deformation limit:

- ``damping_stiffness`` beta [s]: Kelvin-Voigt viscosity on the membrane's Green strain and on the
  dihedral angle, ``D = beta/h * (V Psi_StVK(G(x) - G(x_t)) + k (theta(x) - theta(x_t))^2 / 2)``.
  It damps deformation rates only, never rigid motion.
- ``damping_mass`` alpha [1/s]: drag against the world frame, ``D = alpha/(2h) (x - x_t)^T M (x - x_t)``.

Both default to 0 in the presets: backward Euler already dissipates the high-frequency membrane
modes at the solver's substeps (omega h > 1), and a measured damping for these fabrics is not
available here; set them explicitly where extra viscosity is wanted.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, fields, replace

from simgen.errors import InputError

__all__ = ["Material", "MATERIALS", "get_material", "DEFAULT_FRICTION"]

DEFAULT_FRICTION = 0.3  # ARCSim's default body-cloth friction coefficient ("friction": 0.3 in its conf files)

# Fields that must be finite and > 0, and those that may be 0 (an effect switched off).
_POSITIVE = ("area_density", "youngs_modulus", "thickness", "bending_stiffness")
_NON_NEGATIVE = ("friction_coefficient", "damping_stiffness", "damping_mass")


@dataclass(frozen=True)
class Material:
    """A cloth material (SI units).

    name: preset or user label.
    area_density [kg/m^2]: mass per unit area of the fabric.
    youngs_modulus [Pa], poisson_ratio [-]: isotropic in-plane elasticity, turned into the
      plane-stress Lame parameters (:attr:`lame_lambda`, :attr:`lame_mu`).
    thickness [m]: multiplies the Lame parameters (membrane energy = area x thickness x Psi).
    bending_stiffness [N m]: k_bend of the dihedral bending energy.
    friction_coefficient [-]: Coulomb coefficient against the body.
    damping_stiffness [s]: Rayleigh stiffness-proportional coefficient beta (see module doc).
    damping_mass [1/s]: Rayleigh mass-proportional coefficient alpha (see module doc).
    source: citation of where the numbers come from.

    Plane stress requires -1 < nu < 1; fabrics are accepted with 0 <= nu < 1 (knits measure above
    the 3D bound of 0.5).
    """

    name: str
    area_density: float
    youngs_modulus: float
    poisson_ratio: float
    thickness: float
    bending_stiffness: float
    friction_coefficient: float = DEFAULT_FRICTION
    damping_stiffness: float = 0.0
    damping_mass: float = 0.0
    source: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"material name must be a non-empty string, got {self.name!r}")
        if not isinstance(self.source, str):
            raise InputError(f"material {self.name!r}: source must be a string, got {self.source!r}")
        for f in fields(self):
            if f.name in ("name", "source"):
                continue
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                raise InputError(f"material {self.name!r}: {f.name} must be a finite number, got {value!r}")
            object.__setattr__(self, f.name, float(value))
            if f.name in _POSITIVE and value <= 0:
                raise InputError(f"material {self.name!r}: {f.name} must be > 0, got {value!r}")
            if f.name in _NON_NEGATIVE and value < 0:
                raise InputError(f"material {self.name!r}: {f.name} must be >= 0, got {value!r}")
        if not 0.0 <= self.poisson_ratio < 1.0:
            raise InputError(f"material {self.name!r}: poisson_ratio must be in [0, 1), got {self.poisson_ratio!r}")

    @property
    def lame_lambda(self) -> float:
        """Plane-stress first Lame parameter lambda = E nu / (1 - nu^2) [Pa]."""
        nu = self.poisson_ratio
        return self.youngs_modulus * nu / (1.0 - nu * nu)

    @property
    def lame_mu(self) -> float:
        """Shear modulus mu = E / (2 (1 + nu)) [Pa]."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def membrane_stiffness(self) -> tuple[float, float]:
        """(lambda * thickness, mu * thickness) [N/m]: the coefficients the membrane energy uses."""
        return self.lame_lambda * self.thickness, self.lame_mu * self.thickness

    @property
    def flexural_rigidity(self) -> float:
        """Continuum flexural rigidity B [N m] (bending moment per unit width per unit curvature).

        The dihedral energy sum_e k_bend l^2/(8 (a1 + a2)) theta^2 (ARCSim's form, which its measured
        tables are fitted with) equals the plate energy integral of B kappa^2 / 2 over a cylinder bent
        to curvature kappa when B = k_bend / 4, on regular and equilateral meshes alike (tested).
        The cantilever bending length is (B / (area_density g))^(1/3).
        """
        return self.bending_stiffness / 4.0

    @property
    def stretch_stiffness_2d(self) -> float:
        """Plane-stress 2D Young's modulus E_2D = E * thickness [N/m] (uniaxial tension, free sides).

        The hanging-strip elongation rho g L^2 / (2 E_2D) uses it.
        """
        return self.youngs_modulus * self.thickness

    def with_overrides(self, **overrides) -> Material:
        """A copy with some fields replaced, validated.

        Unknown field names and out-of-range values raise :class:`InputError` naming the field.
        Example: ``get_material("cotton").with_overrides(bending_stiffness=1e-5)``.
        """
        known = {f.name for f in fields(self)}
        for key in overrides:
            if key not in known:
                raise InputError(f"unknown material field {key!r}; fields are: {', '.join(sorted(known))}")
        return replace(self, **overrides)

    def to_dict(self) -> dict:
        """JSON-serialisable dict of the fields (for dataset attributes and configs)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> Material:
        """Inverse of :meth:`to_dict`; unknown keys raise :class:`InputError`."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise InputError(f"unknown material field {unknown[0]!r}; fields are: {', '.join(sorted(known))}")
        return cls(**data)


_SNUG = ("Santesteban, Otaduy, Casas, SNUG (CVPR 2022) / Santesteban PhD thesis (2022) sec. 5.3.1: "
         "100% cotton, thickness 0.47 mm and density 426 kg/m^3 (0.2 kg/m^2), Lame lambda = 4.44e4 Pa, "
         "mu = 2.36e4 Pa (E = 0.7e5 Pa, nu = 0.485, plane stress), k_bending = 3.96e-5")
_ARCSIM = ("Narain, Samii, O'Brien, ARCSim (2012) materials from Wang, O'Brien, Ramamoorthi, "
           "'Data-driven elastic models for cloth' (SIGGRAPH 2011)")

_WANG = "(Wang, O'Brien, Ramamoorthi 2011, as shipped with ARCSim)"


def _bending_fit(table_mean: float) -> str:
    return (f"bending {table_mean:.3g} N m is the mean of the measured bending table {_WANG} over its three "
            "directions (0, 45, 90 deg) and five curvatures (0-20 1/m), in ARCSim's hinge form, which ours is "
            "(flexural rigidity B = k / 4)")


MATERIALS: dict[str, Material] = {
    "cotton": Material(
        name="cotton",
        area_density=0.276,
        youngs_modulus=3.3e5,
        poisson_ratio=0.3,
        thickness=5.0e-4,
        bending_stiffness=4.6e-5,
        source=(_ARCSIM + ": the measured ivory-rib-knit (95% cotton, 5% spandex; the most cotton knit of the "
                "set), area density 0.276 kg/m^2. " + _bending_fit(4.63e-5) + ". Stretch: E h = 165 N/m, "
                "the interlock's 150 N/m scaled by the ratio of the two stretching tables (geometric mean of the "
                "direction-averaged (lambda + 2 mu) h at rest and at 17% strain: 162 against 148 N/m); "
                "thickness 0.5 mm and nu = 0.3 are assumptions"),
    ),
    "interlock": Material(
        name="interlock",
        area_density=0.187,
        youngs_modulus=3.0e5,
        poisson_ratio=0.3,
        thickness=5.0e-4,
        bending_stiffness=2.2e-5,
        source=(_ARCSIM + ": the measured gray-interlock (60% cotton, 40% polyester; the T-shirt fabric of the "
                "set and of the thesis's ch. 4 dataset), area density 0.187 kg/m^2. " + _bending_fit(2.18e-5)
                + ". Stretch is an isotropic StVK fit to its stretching table, which is nonlinear and anisotropic: "
                "(lambda + 2 mu) h of ~33 and ~69 N/m along its two fabric directions at rest, stiffening to ~90-280 "
                "and ~410-830 N/m at 17% strain; E h = 150 N/m ((lambda + 2 mu) h = 165 N/m) is their middle at "
                "~8% strain, where garments on a moving body work. A fit at rest (~15 N/m) lets the knit hang 6% "
                "on average and 28% in places under its own weight, and arms swung at the speed of the CMU hop "
                "stretch it to 3x. Thickness 0.5 mm (bulk density ~370 kg/m^3) is an assumption"),
    ),
    "snug_cotton": Material(
        name="snug_cotton",
        area_density=0.2,
        youngs_modulus=0.7e5,
        poisson_ratio=0.485,
        thickness=4.7e-4,
        bending_stiffness=3.96e-5,
        source=_SNUG + " (tuned there for the look of the fabric, not measured); friction 0.3 is ARCSim's default",
    ),
    "denim": Material(
        name="denim",
        area_density=0.324,
        youngs_modulus=2.5e5,
        poisson_ratio=0.3,
        thickness=8.0e-4,
        bending_stiffness=2.0e-4,
        source=(_ARCSIM + ": area density 0.324 kg/m^2 of the measured 11oz black denim. Stiffness chosen, "
                "not fitted: in-plane E h = 200 N/m (~6x SNUG cotton) for a tight twill weave; bending "
                "2.0e-4 N m, i.e. ~2 gf cm^2/cm, inside the KES-FB2 range reported for denims "
                "(~0.5-3 gf cm^2/cm; 1 gf cm^2/cm = 9.81e-5 N m); thickness 0.8 mm"),
    ),
    "silk": Material(
        name="silk",
        area_density=0.07,
        youngs_modulus=1.5e5,
        poisson_ratio=0.3,
        thickness=1.5e-4,
        bending_stiffness=2.0e-6,
        source=("Light silk charmeuse: 16 momme = 16 x 4.34 g/m^2 = 0.069 kg/m^2 (momme is the silk trade's "
                "weight unit); thickness 0.15 mm; bending 2.0e-6 N m (~0.02 gf cm^2/cm, the KES-FB2 range of "
                "light silks, ~0.01-0.05) and E h = 22 N/m are chosen values, not a fit to one fabric"),
    ),
}


def get_material(name: str | Material) -> Material:
    """The preset called ``name`` (cotton, interlock, snug_cotton, denim, silk); a Material passes through.

    Unknown names raise :class:`InputError` listing the presets.
    """
    if isinstance(name, Material):
        return name
    try:
        return MATERIALS[str(name).lower()]
    except KeyError:
        raise InputError(f"unknown material {name!r}; presets are: {', '.join(MATERIALS)}") from None
