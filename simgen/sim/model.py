"""Static cloth model (topology, rest state, per-element materials) and its time-varying state.

Newton's split: a :class:`ClothModel` holds everything that does not change during a simulation,
a :class:`ClothState` the positions and velocities (two states are swapped each step). Many
independent instances (garment copy x body x motion) are simulated as one concatenated system: the
vertices of all instances live in one array (total V), triangles (total F) and hinges (total E)
index into it, and per-vertex / per-element ``*_instance`` arrays say which instance owns what.
Material parameters are stored per element (per-triangle membrane coefficients, per-hinge bending
coefficient and rest angle, per-vertex lumped mass, friction and damping), so every instance may
use its own material.

Build with :class:`ClothModelBuilder` (``add_instance`` once per instance, then ``finalize``), or
with the shortcuts :meth:`ClothModel.from_mesh`, :meth:`ClothModel.from_garment` and
:meth:`ClothModel.concatenate`.

The Hessian of the total energy is a 3x3-block BSR matrix with a fixed pattern
(:mod:`simgen.topology`); :meth:`ClothModel.new_hessian` allocates one, and the energy kernels
accumulate into its ``values`` through the model's slot maps (``tri_slots``, ``hinge_slots``,
``diag_slots``).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from simgen.errors import InputError
from simgen.sim.warp_toolkit import check_scalar, scalar_types
from simgen.materials import Material, get_material
from simgen.topology import BsrPattern, build_bsr_pattern, extract_hinges, stack_bsr_patterns

if TYPE_CHECKING:
    from simgen.garment.waistband import Attachment

__all__ = ["ClothModel", "ClothModelBuilder", "ClothState", "InstanceSpec", "BENDING_REST_MODES"]

BENDING_REST_MODES = ("template", "flat")


def _triangle_rest_frames(rest: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-triangle inverse rest shape matrix Dm^-1, shape (F, 2, 2), and rest area [m^2], (F,).

    Each rest triangle is laid out in its own orthonormal 2D frame (t1 along the first edge, t2 in
    the triangle's plane), so no UVs are needed: Dm = [[|e1|, e2.t1], [0, e2.t2]], F = Ds Dm^-1.
    """
    x0, x1, x2 = rest[faces[:, 0]], rest[faces[:, 1]], rest[faces[:, 2]]
    e1, e2 = x1 - x0, x2 - x0
    len1 = np.linalg.norm(e1, axis=1)
    n = np.cross(e1, e2)
    twice_area = np.linalg.norm(n, axis=1)
    longest = np.max(np.stack([len1, np.linalg.norm(e2, axis=1), np.linalg.norm(x2 - x1, axis=1)]), axis=0)
    # A sliver whose height is below 1e-6 of its longest edge has an ill-defined rest shape.
    bad = twice_area <= 1e-6 * longest**2
    if np.any(bad):
        t = int(np.flatnonzero(bad)[0])
        raise InputError(f"triangle {t} (vertices {faces[t].tolist()}) is degenerate in the rest shape")
    t1 = e1 / len1[:, None]
    t2 = np.cross(n / twice_area[:, None], t1)
    dm = np.zeros((len(faces), 2, 2))
    dm[:, 0, 0] = len1
    dm[:, 0, 1] = np.einsum("ij,ij->i", e2, t1)
    dm[:, 1, 1] = np.einsum("ij,ij->i", e2, t2)
    return np.linalg.inv(dm), 0.5 * twice_area


@dataclass
class InstanceSpec:
    """One instance as given to the builder (host, float64); kept so models can be concatenated.

    vertices [m], shape (V, 3): rest (template) positions, also the initial state.
    faces, int shape (F, 3); hinges, int shape (E, 4), hinge_faces, int shape (E, 2) (see
    :func:`simgen.topology.extract_hinges`).
    material: its :class:`Material`. pinned, bool shape (V,). bending_rest: "template" or "flat".
    body_part: int shape (V,), each vertex's home body part (index into
    :data:`simgen.body.parts.BODY_PARTS`), or None (the body contact's part rule stays off).
    attachment: vertices tied to the body surface (:class:`simgen.garment.waistband.Attachment`), or None.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    hinges: np.ndarray
    hinge_faces: np.ndarray
    material: Material
    pinned: np.ndarray
    bending_rest: str
    body_part: np.ndarray | None = None
    attachment: Attachment | None = None


@dataclass
class ClothState:
    """Time-varying state: positions [m] and velocities [m/s], each (V,) vec3 warp arrays."""

    positions: wp.array
    velocities: wp.array

    def clone(self) -> ClothState:
        """A deep copy on the same device."""
        return ClothState(wp.clone(self.positions), wp.clone(self.velocities))

    def assign(self, other: ClothState) -> None:
        """Copy other's values into this state's arrays (no allocation; graph-capture safe)."""
        wp.copy(self.positions, other.positions)
        wp.copy(self.velocities, other.velocities)


class ClothModelBuilder:
    """Collects instances (garment copies) and builds one concatenated :class:`ClothModel`.

    >>> b = ClothModelBuilder()
    >>> b.add_instance(vertices, faces, "cotton")           # returns the instance index
    >>> model = b.finalize("cuda:0")
    """

    def __init__(self) -> None:
        self.instances: list[InstanceSpec] = []

    @property
    def num_instances(self) -> int:
        return len(self.instances)

    def add_instance(self, vertices, faces, material: Material | str = "cotton", *, pinned=None,
                     bending_rest: str = "template", body_part=None, attachment: Attachment | None = None,
                     name: str | None = None) -> int:
        """Add one cloth instance; returns its index.

        vertices [m], shape (V, 3): rest shape (the 3D template; its triangles define the rest
          metric and, with bending_rest="template", the rest dihedral angles), also the initial state.
        faces, int shape (F, 3): triangles, counter-clockwise seen from the outside.
        material: a :class:`Material` or a preset name.
        pinned: optional bool mask shape (V,) or integer vertex indices; pinned vertices are left to
          the integrator (kinematic), the energies ignore the flag.
        bending_rest: "template" (rest angle = the template's dihedral angle) or "flat" (0, as SNUG).
        body_part: optional int shape (V,), each vertex's home body part for contact where the body
          intersects itself (:func:`simgen.body.parts.vertex_parts` of the garment's skinning
          weights; the part rule of :mod:`simgen.body.surface_query`); None leaves that rule off.
        attachment: optional :class:`~simgen.garment.waistband.Attachment`: vertices tied to points
          of the body surface by springs (:mod:`simgen.sim.energies.attachment`).
        name: label for reports (default "instance<k>").
        """
        k = len(self.instances)
        where = f"cloth instance {name or k!r}"
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3:
            raise InputError(f"{where}: vertices must have shape (V, 3) with V >= 3, got {vertices.shape}")
        if not np.all(np.isfinite(vertices)):
            raise InputError(f"{where}: vertices contain NaN or inf")
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise InputError(f"{where}: faces must have shape (F, 3), got {faces.shape}")
        if not np.issubdtype(faces.dtype, np.integer):
            raise InputError(f"{where}: faces must be integers, got {faces.dtype}")
        faces = faces.astype(np.int64)
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise InputError(f"{where}: faces index vertex {int(faces.max())} of {len(vertices)}")
        if np.any((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])):
            raise InputError(f"{where}: a triangle repeats a vertex")
        used = np.zeros(len(vertices), dtype=bool)
        used[faces.reshape(-1)] = True
        if not used.all():
            raise InputError(f"{where}: vertex {int(np.flatnonzero(~used)[0])} belongs to no triangle "
                             "(it would have no mass)")
        if bending_rest not in BENDING_REST_MODES:
            raise InputError(f"{where}: bending_rest must be one of {BENDING_REST_MODES}, got {bending_rest!r}")
        material = get_material(material)
        mask = np.zeros(len(vertices), dtype=bool)
        if pinned is not None:
            pinned = np.asarray(pinned)
            if pinned.dtype == bool:
                if pinned.shape != (len(vertices),):
                    raise InputError(f"{where}: pinned mask must have shape ({len(vertices)},), got {pinned.shape}")
                mask = pinned.copy()
            elif np.issubdtype(pinned.dtype, np.integer):
                if pinned.size and (pinned.min() < 0 or pinned.max() >= len(vertices)):
                    raise InputError(f"{where}: pinned index {int(pinned.max())} out of range "
                                     f"for {len(vertices)} vertices")
                mask[pinned.reshape(-1)] = True
            else:
                raise InputError(f"{where}: pinned must be a bool mask or integer indices, got {pinned.dtype}")
        if body_part is not None:
            from simgen.body.parts import BODY_PARTS

            body_part = np.asarray(body_part)
            if (body_part.shape != (len(vertices),) or not np.issubdtype(body_part.dtype, np.integer)
                    or body_part.min() < 0 or body_part.max() >= len(BODY_PARTS)):
                raise InputError(f"{where}: body_part must be {len(vertices)} integers in [0, {len(BODY_PARTS)})")
            body_part = body_part.astype(np.int32)
        _triangle_rest_frames(vertices, faces)  # validates the rest shape now, naming the instance
        if attachment is not None:
            outside = attachment.vertices[(attachment.vertices < 0) | (attachment.vertices >= len(vertices))]
            if len(outside):
                raise InputError(f"{where}: attachment vertex {int(outside[0])} out of range for {len(vertices)} vertices")
        hinges, hinge_faces = extract_hinges(faces)
        self.instances.append(InstanceSpec(
            name=name or f"instance{k}", vertices=vertices.copy(), faces=faces, hinges=hinges,
            hinge_faces=hinge_faces, material=material, pinned=mask, bending_rest=bending_rest, body_part=body_part,
            attachment=attachment))
        return k

    def add_spec(self, spec: InstanceSpec) -> int:
        """Add an instance described by an :class:`InstanceSpec` (e.g. taken from another model)."""
        return self.add_instance(spec.vertices, spec.faces, spec.material, pinned=spec.pinned,
                                 bending_rest=spec.bending_rest, body_part=spec.body_part,
                                 attachment=spec.attachment, name=spec.name)

    def finalize(self, device=None, *, dtype=wp.float32) -> ClothModel:
        """Build the concatenated model on ``device`` (default: Warp's default device).

        dtype: scalar type of every float array, wp.float32 (the solver) or wp.float64 (tests).
        """
        if not self.instances:
            raise InputError("the cloth model has no instance; call add_instance first")
        return ClothModel._build(self.instances, device, dtype)


def _rest_geometry(instances: list[InstanceSpec]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The instances' rest geometry, concatenated: each triangle's inverse rest shape matrix (F, 2, 2)
    and rest area [m^2] (F,), and each hinge's dihedral angle [rad] in the rest shape (E,); computed
    once per instance object (the slots of a pool share one)."""
    from simgen.sim.energies.reference import dihedral_angles  # numpy, float64

    built: dict = {}
    for s in instances:
        if id(s) not in built:
            built[id(s)] = (*_triangle_rest_frames(s.vertices, s.faces), dihedral_angles(s.vertices, s.hinges))
    return tuple(np.concatenate([built[id(s)][k] for s in instances]) for k in range(3))


def _instance_patterns(instances: list[InstanceSpec]) -> BsrPattern:
    """The model's Hessian pattern: each instance's, stacked; instances of one mesh (a pool's
    slots) share one build."""
    built: dict = {}
    parts = []
    for s in instances:
        key = (len(s.vertices), hashlib.sha1(np.ascontiguousarray(s.faces, dtype=np.int64).tobytes()).digest())
        if key not in built:
            built[key] = build_bsr_pattern(len(s.vertices), s.faces, s.hinges)
        parts.append(built[key])
    return stack_bsr_patterns(parts)


class ClothModel:
    """Static part of a batched cloth simulation (see the module docstring).

    Counts: num_instances (I), num_vertices (V), num_triangles (F), num_hinges (E).
    Warp arrays (device ``device``, floats of scalar type ``scalar``: wp.float32 or wp.float64):

    - rest_positions [m], (V,) vec3: template positions.
    - vertex_mass [kg], (V,): lumped mass, a third of each adjacent triangle's area x area density.
    - vertex_instance, int32 (V,); vertex_pinned, int32 (V,) (1 = pinned, for the integrator).
    - instance_step_divisor, int32 (I,): each instance's solver step is the step asked for divided
      by this, 1 at first (2 or 4: a pool slot that runs its job at twice or four times the
      substeps, :class:`simgen.sim.SimulationPool`); a power of two keeps the step's arithmetic exact.
    - instance_active, int32 (I,): 1 at first; 0 for an idle pool slot (all pinned, no body), whose
      membrane and bending elements the kernels then skip (its energy reads 0).
    - vertex_friction [-], (V,): Coulomb coefficient of the vertex's material.
    - vertex_damping_mass [1/s], (V,): Rayleigh alpha of the vertex's material.
    - vertex_body_part, int32 (V,): home body part for contact (-1: none); ``has_body_parts`` says
      whether any instance has them.
    - triangles, int32 (F, 3); tri_inv_rest, (F,) mat22: Dm^-1 in the triangle's 2D rest frame
      [1/m]; tri_rest_area [m^2], (F,); tri_lambda, tri_mu [N/m], (F,): plane-stress Lame
      parameters times thickness; tri_damping [s], (F,): Rayleigh beta; tri_instance, int32 (F,).
    - hinges, int32 (E, 4): (x0, x1, x2, x3), edge x0-x1, wings x2 (face A) and x3 (face B);
      hinge_stiffness [J], (E,): k_bend * l^2 / (4 (a1 + a2)) with rest edge length l and rest
      areas a1, a2; hinge_rest_angle [rad], (E,); hinge_damping [s], (E,); hinge_instance, int32 (E,).
    - attach_vertex, attach_face, int32 (A,); attach_bary (A,) vec3; attach_offset [m] (A,) vec3;
      attach_stiffness [N/m] (A,): the attached vertices (num_attachments, A) and their points on
      the body (:mod:`simgen.sim.energies.attachment`).
    - Hessian pattern (3x3 blocks, see :class:`simgen.topology.BsrPattern`): bsr_offsets (V+1,),
      bsr_columns (nnz,), bsr_rows (nnz,), diag_slots (V,), tri_slots (F, 9), hinge_slots (E, 16),
      all int32.

    Host data: ``instances`` (the :class:`InstanceSpec` list), ``pattern`` (numpy BsrPattern),
    ``vertex_start``/``triangle_start``/``hinge_start`` (I+1,) int64 offsets of each instance's
    range, and ``host``: numpy copies of the arrays above (same names; floats in float64, plus
    ``hinge_faces`` (E, 2)) for references and the torch losses.
    """

    def __init__(self) -> None:
        raise TypeError("build a ClothModel with ClothModelBuilder, ClothModel.from_mesh or ClothModel.from_garment")

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def from_mesh(cls, vertices, faces, material: Material | str, *, pinned=None, bending_rest: str = "template",
                  body_part=None, attachment: Attachment | None = None, device=None, dtype=wp.float32,
                  name: str | None = None) -> ClothModel:
        """A one-instance model from a triangle mesh (arguments as in :meth:`ClothModelBuilder.add_instance`)."""
        builder = ClothModelBuilder()
        builder.add_instance(vertices, faces, material, pinned=pinned, bending_rest=bending_rest,
                             body_part=body_part, attachment=attachment, name=name)
        return builder.finalize(device, dtype=dtype)

    @classmethod
    def from_garment(cls, garment, material: Material | str | None = None, *, body=None, pinned=None,
                     bending_rest: str = "template", device=None, dtype=wp.float32) -> ClothModel:
        """A one-instance model from a :class:`simgen.garment.Garment` (its template is the rest shape).

        material: default ``garment.metadata['default_material']``, else cotton. Each vertex's home
        body part comes from the garment's skinning weights. body: the body model the garment was
        made on, needed when the garment has a waistband (tied to that body's surface,
        :mod:`simgen.garment.waistband`).
        """
        from simgen.body.parts import vertex_parts
        from simgen.garment.waistband import waistband_attachment

        if material is None:
            material = (garment.metadata or {}).get("default_material") or "cotton"
        material = get_material(material)
        attachment = None
        if (garment.metadata or {}).get("waistband") is not None:
            if body is None:
                raise InputError(f"garment {garment.name!r} has a waistband: building its model needs the body "
                                 "it is tied to")
            _, area = _triangle_rest_frames(np.asarray(garment.vertices, dtype=np.float64), garment.faces)
            attachment = waistband_attachment(garment, body, float(area.sum()) * material.area_density)
        return cls.from_mesh(garment.vertices, garment.faces, material, pinned=pinned,
                             bending_rest=bending_rest, body_part=vertex_parts(garment.skin_weights),
                             attachment=attachment, device=device, dtype=dtype, name=garment.name)

    @classmethod
    def concatenate(cls, models, *, device=None, dtype=None) -> ClothModel:
        """One model holding every instance of ``models``, in order (device/dtype default: the first's)."""
        models = list(models)
        if not models:
            raise InputError("concatenate needs at least one ClothModel")
        # Their instances were checked when those models were built; a model repeated (a pool's
        # slots) shares its instances' objects, whose rest geometry _build computes once.
        return cls._build([spec for m in models for spec in m.instances],
                          device if device is not None else models[0].device,
                          dtype if dtype is not None else models[0].scalar)

    @classmethod
    def _build(cls, instances: list[InstanceSpec], device, scalar) -> ClothModel:
        check_scalar(scalar)
        self = object.__new__(cls)
        self.instances = list(instances)
        self.scalar = scalar
        self.device = wp.get_device(device)
        types = scalar_types(scalar)

        nverts = np.array([len(s.vertices) for s in instances])
        ntris = np.array([len(s.faces) for s in instances])
        nhinges = np.array([len(s.hinges) for s in instances])
        self.vertex_start = np.r_[0, np.cumsum(nverts)].astype(np.int64)
        self.triangle_start = np.r_[0, np.cumsum(ntris)].astype(np.int64)
        self.hinge_start = np.r_[0, np.cumsum(nhinges)].astype(np.int64)
        self.num_instances = len(instances)
        self.num_vertices = int(self.vertex_start[-1])
        self.num_triangles = int(self.triangle_start[-1])
        self.num_hinges = int(self.hinge_start[-1])

        rest = np.concatenate([s.vertices for s in instances])
        faces = np.concatenate([s.faces + off for s, off in zip(instances, self.vertex_start)])
        hinges = np.concatenate([s.hinges + off for s, off in zip(instances, self.vertex_start)]).reshape(-1, 4)
        tri_instance = np.repeat(np.arange(len(instances)), ntris)
        hinge_instance = np.repeat(np.arange(len(instances)), nhinges)
        vertex_instance = np.repeat(np.arange(len(instances)), nverts)

        inv_rest, area, template_angle = _rest_geometry(instances)
        mats = [s.material for s in instances]
        lam_h = np.array([m.membrane_stiffness[0] for m in mats])[tri_instance]
        mu_h = np.array([m.membrane_stiffness[1] for m in mats])[tri_instance]
        tri_damping = np.array([m.damping_stiffness for m in mats])[tri_instance]
        density = np.array([m.area_density for m in mats])[tri_instance]
        mass = np.zeros(len(rest))
        np.add.at(mass, faces.reshape(-1), np.repeat(area * density / 3.0, 3))

        # Bending: k_bend * l^2 / (4 (a1 + a2)) on the rest geometry (SNUG eq. 5.10's k_scale).
        hinge_faces = np.concatenate(
            [s.hinge_faces + off for s, off in zip(instances, self.triangle_start)]).reshape(-1, 2)
        edge_len2 = np.sum((rest[hinges[:, 1]] - rest[hinges[:, 0]]) ** 2, axis=1)
        area_sum = area[hinge_faces[:, 0]] + area[hinge_faces[:, 1]]
        k_bend = np.array([m.bending_stiffness for m in mats])[hinge_instance]
        hinge_stiffness = k_bend * edge_len2 / (4.0 * area_sum)
        template_rest = np.array([s.bending_rest == "template" for s in instances])[hinge_instance]
        rest_angle = np.where(template_rest, template_angle, 0.0)
        hinge_damping = np.array([m.damping_stiffness for m in mats])[hinge_instance]

        vertex_friction = np.array([m.friction_coefficient for m in mats])[vertex_instance]
        vertex_damping_mass = np.array([m.damping_mass for m in mats])[vertex_instance]
        pinned = np.concatenate([s.pinned for s in instances])
        body_part = np.concatenate([s.body_part if s.body_part is not None else np.full(len(s.vertices), -1, np.int32)
                                    for s in instances])
        self.has_body_parts = any(s.body_part is not None for s in instances)
        attached = [(s.attachment, off) for s, off in zip(instances, self.vertex_start) if s.attachment is not None]
        attach = SimpleNamespace(
            vertex=np.concatenate([a.vertices + off for a, off in attached] + [np.zeros(0, np.int64)]),
            face=np.concatenate([a.body_faces for a, _ in attached] + [np.zeros(0, np.int64)]),
            bary=np.concatenate([a.bary for a, _ in attached] + [np.zeros((0, 3))]),
            offset=np.concatenate([a.offset for a, _ in attached] + [np.zeros((0, 3))]),
            stiffness=np.concatenate([a.stiffness for a, _ in attached] + [np.zeros(0)]))
        self.num_attachments = len(attach.vertex)

        self.pattern: BsrPattern = _instance_patterns(instances)
        self.host = SimpleNamespace(
            rest_positions=rest, vertex_mass=mass, vertex_instance=vertex_instance, vertex_pinned=pinned,
            vertex_friction=vertex_friction, vertex_damping_mass=vertex_damping_mass, vertex_body_part=body_part,
            triangles=faces, tri_inv_rest=inv_rest, tri_rest_area=area, tri_lambda=lam_h, tri_mu=mu_h,
            tri_damping=tri_damping, tri_instance=tri_instance,
            hinges=hinges, hinge_faces=hinge_faces, hinge_stiffness=hinge_stiffness,
            hinge_rest_angle=rest_angle, hinge_damping=hinge_damping, hinge_instance=hinge_instance,
            attach_vertex=attach.vertex, attach_face=attach.face, attach_bary=attach.bary,
            attach_offset=attach.offset, attach_stiffness=attach.stiffness,
        )

        dev = self.device
        f = types.scalar

        def farr(a, dtype=f):
            return wp.array(np.ascontiguousarray(a), dtype=dtype, device=dev)

        def iarr(a):
            return wp.array(np.ascontiguousarray(a, dtype=np.int32), dtype=wp.int32, device=dev)

        self.rest_positions = farr(rest, types.vec3)
        self.vertex_mass = farr(mass)
        self.vertex_instance = iarr(vertex_instance)
        self.vertex_pinned = iarr(pinned)
        self.instance_step_divisor = iarr(np.ones(len(instances)))
        self.instance_active = iarr(np.ones(len(instances)))
        self.vertex_friction = farr(vertex_friction)
        self.vertex_damping_mass = farr(vertex_damping_mass)
        self.vertex_body_part = iarr(body_part)
        self.triangles = iarr(faces)
        self.tri_inv_rest = farr(inv_rest, types.mat22)
        self.tri_rest_area = farr(area)
        self.tri_lambda = farr(lam_h)
        self.tri_mu = farr(mu_h)
        self.tri_damping = farr(tri_damping)
        self.tri_instance = iarr(tri_instance)
        self.hinges = iarr(hinges)
        self.hinge_stiffness = farr(hinge_stiffness)
        self.hinge_rest_angle = farr(rest_angle)
        self.hinge_damping = farr(hinge_damping)
        self.hinge_instance = iarr(hinge_instance)
        self.attach_vertex = iarr(attach.vertex)
        self.attach_face = iarr(attach.face)
        self.attach_bary = farr(attach.bary.reshape(-1, 3), types.vec3)
        self.attach_offset = farr(attach.offset.reshape(-1, 3), types.vec3)
        self.attach_stiffness = farr(attach.stiffness)
        self.bsr_offsets = iarr(self.pattern.offsets)
        self.bsr_columns = iarr(self.pattern.columns)
        self.bsr_rows = iarr(self.pattern.rows)
        self.diag_slots = iarr(self.pattern.diag_slots)
        self.tri_slots = iarr(self.pattern.tri_slots)
        self.hinge_slots = iarr(self.pattern.hinge_slots)
        return self

    # -- use ----------------------------------------------------------------------------------

    @property
    def vec3(self):
        """The vec3 type of this model's arrays (wp.vec3 or wp.vec3d)."""
        return scalar_types(self.scalar).vec3

    @property
    def mat33(self):
        """The 3x3 block type of this model's Hessian (wp.mat33 or wp.mat33d)."""
        return scalar_types(self.scalar).mat33

    @property
    def nnz(self) -> int:
        """Number of 3x3 blocks in the Hessian pattern."""
        return self.pattern.nnz

    def state(self) -> ClothState:
        """A new state at the rest positions with zero velocities."""
        return ClothState(positions=wp.clone(self.rest_positions),
                          velocities=wp.zeros(self.num_vertices, dtype=self.vec3, device=self.device))

    def new_hessian(self) -> wp.sparse.BsrMatrix:
        """A V x V matrix of 3x3 blocks with this model's fixed pattern and zero values.

        Its ``values`` (nnz,) array is what the energies accumulate into; zero it with
        ``H.values.zero_()`` before each assembly (a memset, graph-capture safe).
        """
        import warp.sparse as wps

        nv = self.num_vertices
        mat = wps.bsr_zeros(nv, nv, block_type=self.mat33, device=self.device)
        wps.bsr_set_from_triplets(mat, self.bsr_rows, self.bsr_columns, None, prune_numerical_zeros=False)
        mat.values.zero_()
        # The slot maps index values in this exact order: make sure Warp kept our (row, column) order.
        if mat.nnz_sync() != self.nnz or not np.array_equal(mat.columns.numpy()[: self.nnz], self.pattern.columns):
            raise RuntimeError("warp.sparse built a different block order than the model's BSR pattern")
        return mat

    def new_gradient(self) -> wp.array:
        """A zeroed (V,) vec3 array for gradients [J/m] (forces are its negative)."""
        return wp.zeros(self.num_vertices, dtype=self.vec3, device=self.device)

    def new_energy(self) -> wp.array:
        """A zeroed (num_instances,) array for per-instance energies [J]."""
        return wp.zeros(self.num_instances, dtype=self.scalar, device=self.device)

    def instance_slice(self, k: int) -> slice:
        """Vertex range of instance k in the concatenated arrays."""
        return slice(int(self.vertex_start[k]), int(self.vertex_start[k + 1]))

    def __repr__(self) -> str:
        return (f"ClothModel(instances={self.num_instances}, vertices={self.num_vertices}, "
                f"triangles={self.num_triangles}, hinges={self.num_hinges}, nnz={self.nnz}, "
                f"scalar={self.scalar.__name__}, device={self.device})")
