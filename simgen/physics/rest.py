"""Rest data of a garment for the torch energies: the same quantities the Warp solver's ClothModel holds.

:class:`ClothRest` is computed here in torch from the garment template (the 3D rest mesh) and a
:class:`simgen.sim.Material`, independently of :class:`simgen.sim.ClothModel`'s numpy code (a test
holds the two equal), or copied from a ClothModel with :meth:`ClothRest.from_model`:

- triangles (F, 3); per triangle the inverse rest shape Dm^-1 (F, 2, 2) in the triangle's own 2D
  frame (t1 along the first edge, t2 in the triangle's plane; no UVs), the rest area A [m^2] (F,) and
  the plane-stress Lame parameters times thickness, lambda h and mu h [N/m];
- lumped vertex masses [kg] (V,): a third of each adjacent triangle's area times the area density;
- hinges (E, 4) (interior edges x0-x1 with wings x2, x3, the solver's
  :func:`simgen.topology.extract_hinges`), the hinge stiffness k_bend l^2 / (4 (a1 + a2)) [J] with
  the REST edge length l and rest areas a1, a2 (SNUG eq. 5.10's k_scale), and the rest angle [rad]:
  the template's dihedral angle ("template", the solver's default) or 0 ("flat", SNUG);
- the Coulomb friction coefficient of the material (friction term).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from simgen.errors import InputError

__all__ = ["ClothRest", "BENDING_REST_MODES", "dihedral_angles", "triangle_rest_frames"]

BENDING_REST_MODES = ("template", "flat")


def triangle_rest_frames(rest: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse rest shape matrices Dm^-1, (F, 2, 2), and rest areas [m^2], (F,), of a 3D template.

    rest [m] (V, 3); faces (F, 3) long. Each triangle is laid out in its own orthonormal 2D frame:
    t1 = e1 / |e1|, t2 = n x t1, so Dm = [[|e1|, e2.t1], [0, e2.t2]] (upper triangular).
    """
    x0, x1, x2 = rest[faces[:, 0]], rest[faces[:, 1]], rest[faces[:, 2]]
    e1, e2 = x1 - x0, x2 - x0
    len1 = e1.norm(dim=1)
    n = torch.cross(e1, e2, dim=1)
    twice_area = n.norm(dim=1)
    longest = torch.stack([len1, e2.norm(dim=1), (x2 - x1).norm(dim=1)]).amax(dim=0)
    bad = twice_area <= 1e-6 * longest**2
    if bool(bad.any()):
        t = int(torch.nonzero(bad)[0])
        raise InputError(f"triangle {t} (vertices {faces[t].tolist()}) is degenerate in the rest shape")
    t1 = e1 / len1[:, None]
    t2 = torch.cross(n / twice_area[:, None], t1, dim=1)
    a = len1
    b = (e2 * t1).sum(dim=1)
    d = (e2 * t2).sum(dim=1)
    # Inverse of the upper-triangular [[a, b], [0, d]] in closed form.
    inv = torch.zeros((len(faces), 2, 2), dtype=rest.dtype, device=rest.device)
    inv[:, 0, 0] = 1.0 / a
    inv[:, 0, 1] = -b / (a * d)
    inv[:, 1, 1] = 1.0 / d
    return inv, 0.5 * twice_area


def dihedral_angles(x: torch.Tensor, hinges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed bending angle [rad] of each hinge, (..., E), and a mask of degenerate hinges (..., E).

    x [m] (..., V, 3); hinges (E, 4) long rows (x0, x1, x2, x3). theta = atan2(((N_A x N_B) . e)/|e|,
    N_A . N_B) with e = x1 - x0, N_A = e x (x2 - x0), N_B = (x3 - x0) x e: 0 when flat, in (-pi, pi].
    A hinge whose wing normal is below 1e-12 |e|^2 (squared: 1e-24 |e|^4) is degenerate; its angle is
    0, as in the solver's kernel (no angle, no force).
    """
    x0, x1, x2, x3 = (x[..., hinges[:, k], :] for k in range(4))
    e = x1 - x0
    na = torch.cross(e, x2 - x0, dim=-1)
    nb = torch.cross(x3 - x0, e, dim=-1)
    l2 = (e * e).sum(-1)
    degenerate = ((na * na).sum(-1) <= 1e-24 * l2 * l2) | ((nb * nb).sum(-1) <= 1e-24 * l2 * l2)
    l_safe = torch.where(l2 > 0, l2, torch.ones_like(l2)).sqrt()
    sin = (torch.cross(na, nb, dim=-1) * e).sum(-1) / l_safe
    cos = (na * nb).sum(-1)
    # atan2(0, 0) has an undefined gradient: feed degenerate hinges a harmless (0, 1).
    sin = torch.where(degenerate, torch.zeros_like(sin), sin)
    cos = torch.where(degenerate, torch.ones_like(cos), cos)
    return torch.atan2(sin, cos), degenerate


@dataclass
class ClothRest:
    """Rest state and per-element material coefficients of one garment (torch tensors, one device/dtype).

    Fields (V vertices, F triangles, E hinges):
      rest_positions [m] (V, 3); faces (F, 3) long; tri_inv_rest [1/m] (F, 2, 2); tri_area [m^2] (F,);
      lam_h, mu_h [N/m] (scalars as 0-d tensors): plane-stress Lame parameters times thickness;
      vertex_mass [kg] (V,); hinges (E, 4) long; hinge_faces (E, 2) long; hinge_stiffness [J] (E,);
      hinge_rest_angle [rad] (E,); friction_coefficient [-] (0-d); material: the Material;
      bending_rest: "template" or "flat".
    """

    rest_positions: torch.Tensor
    faces: torch.Tensor
    tri_inv_rest: torch.Tensor
    tri_area: torch.Tensor
    lam_h: torch.Tensor
    mu_h: torch.Tensor
    vertex_mass: torch.Tensor
    hinges: torch.Tensor
    hinge_faces: torch.Tensor
    hinge_stiffness: torch.Tensor
    hinge_rest_angle: torch.Tensor
    friction_coefficient: torch.Tensor
    material: object
    bending_rest: str

    # -- construction ---------------------------------------------------------------------------

    @classmethod
    def from_mesh(cls, vertices, faces, material="cotton", *, bending_rest: str = "template",
                  dtype: torch.dtype = torch.float32, device=None) -> "ClothRest":
        """Rest data of a triangle mesh.

        vertices [m] (V, 3): the 3D template (rest shape); faces (F, 3) int; material: a
        :class:`simgen.sim.Material` or a preset name; bending_rest: "template" (the solver's
        default) or "flat" (SNUG). Geometry is computed in float64 and stored in ``dtype``.
        """
        from simgen.materials import get_material
        from simgen.topology import extract_hinges

        material = get_material(material)
        if bending_rest not in BENDING_REST_MODES:
            raise InputError(f"bending_rest must be one of {BENDING_REST_MODES}, got {bending_rest!r}")
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
            raise InputError(f"garment vertices must have shape (V, 3) with V >= 3, got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise InputError("garment vertices contain NaN or inf")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
            raise InputError(f"garment faces must be integers of shape (F, 3), got {f.dtype} {f.shape}")
        if f.min() < 0 or f.max() >= len(v):
            raise InputError(f"garment faces index vertex {int(f.max())} of {len(v)}")
        used = np.zeros(len(v), dtype=bool)
        used[f.reshape(-1)] = True
        if not used.all():
            raise InputError(f"garment vertex {int(np.flatnonzero(~used)[0])} belongs to no triangle (no mass)")
        hinges, hinge_faces = extract_hinges(f)

        f64 = torch.float64
        rest = torch.as_tensor(v, dtype=f64)
        ft = torch.as_tensor(f.astype(np.int64))
        ht = torch.as_tensor(hinges.astype(np.int64)).reshape(-1, 4)
        hft = torch.as_tensor(hinge_faces.astype(np.int64)).reshape(-1, 2)
        inv_rest, area = triangle_rest_frames(rest, ft)
        mass = torch.zeros(len(v), dtype=f64).index_add_(
            0, ft.reshape(-1), (area * material.area_density / 3.0).repeat_interleave(3))
        edge_len2 = ((rest[ht[:, 1]] - rest[ht[:, 0]]) ** 2).sum(1)
        stiffness = material.bending_stiffness * edge_len2 / (4.0 * (area[hft[:, 0]] + area[hft[:, 1]]))
        if bending_rest == "template":
            rest_angle = dihedral_angles(rest, ht)[0]
        else:
            rest_angle = torch.zeros(len(ht), dtype=f64)
        lam_h, mu_h = material.membrane_stiffness
        out = cls(rest_positions=rest, faces=ft, tri_inv_rest=inv_rest, tri_area=area,
                  lam_h=torch.tensor(lam_h, dtype=f64), mu_h=torch.tensor(mu_h, dtype=f64), vertex_mass=mass,
                  hinges=ht, hinge_faces=hft, hinge_stiffness=stiffness, hinge_rest_angle=rest_angle,
                  friction_coefficient=torch.tensor(material.friction_coefficient, dtype=f64),
                  material=material, bending_rest=bending_rest)
        return out.to(dtype=dtype, device=device)

    @classmethod
    def from_garment(cls, garment, material=None, *, bending_rest: str = "template",
                     dtype: torch.dtype = torch.float32, device=None) -> "ClothRest":
        """Rest data of a :class:`simgen.garment.Garment` (its template is the rest shape).

        material: default the garment's ``default_material``, else cotton (as the solver).
        """
        if material is None:
            material = (getattr(garment, "metadata", None) or {}).get("default_material") or "cotton"
        return cls.from_mesh(garment.vertices, garment.faces, material, bending_rest=bending_rest,
                             dtype=dtype, device=device)

    @classmethod
    def from_model(cls, model, instance: int = 0, *, dtype: torch.dtype = torch.float32,
                   device=None) -> "ClothRest":
        """Copy one instance's rest data from a :class:`simgen.sim.ClothModel` (its float64 host copies)."""
        if not 0 <= instance < model.num_instances:
            raise InputError(f"instance {instance} out of range for a model of {model.num_instances}")
        h = model.host
        spec = model.instances[instance]
        vs = slice(int(model.vertex_start[instance]), int(model.vertex_start[instance + 1]))
        ts = slice(int(model.triangle_start[instance]), int(model.triangle_start[instance + 1]))
        hs = slice(int(model.hinge_start[instance]), int(model.hinge_start[instance + 1]))
        v0, t0 = vs.start, ts.start
        f64 = torch.float64
        lam = h.tri_lambda[ts]
        mu = h.tri_mu[ts]
        out = cls(
            rest_positions=torch.as_tensor(h.rest_positions[vs], dtype=f64),
            faces=torch.as_tensor(h.triangles[ts] - v0, dtype=torch.int64),
            tri_inv_rest=torch.as_tensor(h.tri_inv_rest[ts], dtype=f64),
            tri_area=torch.as_tensor(h.tri_rest_area[ts], dtype=f64),
            lam_h=torch.tensor(float(lam[0]) if len(lam) else 0.0, dtype=f64),
            mu_h=torch.tensor(float(mu[0]) if len(mu) else 0.0, dtype=f64),
            vertex_mass=torch.as_tensor(h.vertex_mass[vs], dtype=f64),
            hinges=torch.as_tensor(h.hinges[hs] - v0, dtype=torch.int64).reshape(-1, 4),
            hinge_faces=torch.as_tensor(h.hinge_faces[hs] - t0, dtype=torch.int64).reshape(-1, 2),
            hinge_stiffness=torch.as_tensor(h.hinge_stiffness[hs], dtype=f64),
            hinge_rest_angle=torch.as_tensor(h.hinge_rest_angle[hs], dtype=f64),
            friction_coefficient=torch.tensor(float(h.vertex_friction[vs][0]), dtype=f64),
            material=spec.material, bending_rest=spec.bending_rest)
        return out.to(dtype=dtype, device=device)

    # -- use ------------------------------------------------------------------------------------

    @property
    def num_vertices(self) -> int:
        return int(self.rest_positions.shape[0])

    @property
    def num_triangles(self) -> int:
        return int(self.faces.shape[0])

    @property
    def num_hinges(self) -> int:
        return int(self.hinges.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        return self.rest_positions.dtype

    @property
    def device(self) -> torch.device:
        return self.rest_positions.device

    @property
    def total_mass(self) -> float:
        """Garment mass [kg]."""
        return float(self.vertex_mass.sum())

    @property
    def total_area(self) -> float:
        """Garment rest area [m^2]."""
        return float(self.tri_area.sum())

    def to(self, dtype: torch.dtype | None = None, device=None) -> "ClothRest":
        """A copy with floating tensors in ``dtype`` and every tensor on ``device`` (None: unchanged)."""
        kw = {}
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if isinstance(value, torch.Tensor):
                if value.is_floating_point():
                    value = value.to(device=device if device is not None else value.device,
                                     dtype=dtype if dtype is not None else value.dtype)
                elif device is not None:
                    value = value.to(device)
            kw[name] = value
        return ClothRest(**kw)

    def check_positions(self, x: torch.Tensor, what: str = "positions") -> None:
        """Raise InputError unless x is a floating tensor of shape (..., V, 3) on this rest's device."""
        if not isinstance(x, torch.Tensor) or not x.is_floating_point():
            raise InputError(f"{what} must be a floating-point torch tensor of shape (..., V, 3)")
        if x.ndim < 2 or x.shape[-2:] != (self.num_vertices, 3):
            raise InputError(f"{what} must have shape (..., {self.num_vertices}, 3), got {tuple(x.shape)}")
        if x.device != self.device:
            raise InputError(f"{what} is on {x.device} but the garment's rest data is on {self.device}")
