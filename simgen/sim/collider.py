"""The body the cloth collides with: one refittable warp.Mesh per instance, plus the post-step
projection that keeps cloth vertices out of it.

Every cloth instance of a batched model has its own body (own shape and motion), and bodies of
different instances overlap in space, so each instance gets its own ``wp.Mesh``; the contact and
friction kernels look the mesh up by the vertex's instance (``mesh_ids``, 0 = no body).

All instances' body vertices live in one flat array (instance-major, the layout of
:attr:`simgen.body.warp_lbs.WarpBody.vertices_flat`), and each mesh is built once on its slice:
moving the body only writes those points and calls ``refit()`` (no rebuild, no allocation).
Within one solver step the body moves linearly from its previous to its new position
(:meth:`BodyCollider.set_time`), with the constant velocity (new - previous) / dt that friction
reads through ``wp.mesh_eval_velocity``.
"""


import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from simgen.errors import InputError
from simgen.sim.warp_toolkit import module_name, scalar_types
from simgen.body.surface_query import contact_funcs
from simgen.params import ContactParams
from simgen.sim.energies.contact import part_inputs

__all__ = ["BodyCollider", "collider_kernels"]


@wp.kernel(enable_backward=False)
def _lerp_points(start: wp.array(dtype=wp.vec3), end: wp.array(dtype=wp.vec3), t: float,
                 out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = start[i] + t * (end[i] - start[i])


@wp.kernel(enable_backward=False)
def _finite_difference(start: wp.array(dtype=wp.vec3), end: wp.array(dtype=wp.vec3), inv_dt: float,
                       step_divisor: wp.array(dtype=wp.int32), vertices_per_body: int, out: wp.array(dtype=wp.vec3)):
    # The bodies are stacked instance-major: body vertex i belongs to instance i // Vb.
    i = wp.tid()
    out[i] = (end[i] - start[i]) * (inv_dt * float(step_divisor[i // vertices_per_body]))


@functools.cache
def collider_kernels(scalar) -> SimpleNamespace:
    """Kernels for one scalar type: ``.project`` (push out + velocity fix) and ``.penetration``."""
    T = scalar_types(scalar)
    vec3 = T.vec3
    body_contact = contact_funcs(scalar).body_contact
    mod = module_name(__name__, scalar)
    zero = scalar(0.0)

    @wp.kernel(enable_backward=False, module=mod)
    def project(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        vertex_instance: wp.array(dtype=wp.int32),
        pinned: wp.array(dtype=wp.int32),
        body_meshes: wp.array(dtype=wp.uint64),
        offset: scalar,
        query_distance: float,
        vertex_part: wp.array(dtype=wp.int32),
        part_masks: wp.array(dtype=wp.int32),
        use_parts: int,
        pinch_distance: float,
        touch_distance: float,
        depth_before: wp.array(dtype=scalar),
        count_inside: wp.array(dtype=wp.int32),
        touching: wp.array(dtype=wp.int32),
        touch_normal: wp.array(dtype=vec3),
        touch_plane: wp.array(dtype=scalar),
    ):
        i = wp.tid()
        inst = vertex_instance[i]
        mesh = body_meshes[inst]
        if mesh == wp.uint64(0):
            return
        home = int(-1)
        if use_parts != 0:
            home = vertex_part[i]
        found, d, n, face, bu, bv, own = body_contact(mesh, part_masks, home, x[i], query_distance, pinch_distance)
        if found != 0 and d < scalar(touch_distance) and touching.shape[0] > 0:
            # The half-space the vertex must stay in: n . x >= n . (closest body point) + offset.
            touching[i] = 1
            touch_normal[i] = n
            touch_plane[i] = wp.dot(n, x[i]) - d + offset
        if found == 0 or d >= zero:
            return
        wp.atomic_max(depth_before, inst, -d)
        wp.atomic_add(count_inside, inst, 1)
        if pinned[i] != 0:
            return
        # Onto the surface (plus offset) along the outward normal of the closest feature.
        x[i] = x[i] + (offset - d) * n
        # Remove the velocity component that moves into the body (relative to the body's surface).
        v_body = vec3(wp.mesh_eval_velocity(mesh, face, bu, bv))
        vn = wp.dot(v[i] - v_body, n)
        if vn < zero:
            v[i] = v[i] - vn * n

    @wp.kernel(enable_backward=False, module=mod)
    def penetration(
        x: wp.array(dtype=vec3),
        vertex_instance: wp.array(dtype=wp.int32),
        body_meshes: wp.array(dtype=wp.uint64),
        query_distance: float,
        vertex_part: wp.array(dtype=wp.int32),
        part_masks: wp.array(dtype=wp.int32),
        use_parts: int,
        pinch_distance: float,
        depth: wp.array(dtype=scalar),
        count_inside: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        inst = vertex_instance[i]
        mesh = body_meshes[inst]
        if mesh == wp.uint64(0):
            return
        home = int(-1)
        if use_parts != 0:
            home = vertex_part[i]
        found, d, n, face, bu, bv, own = body_contact(mesh, part_masks, home, x[i], query_distance, pinch_distance)
        if found != 0 and d < zero:
            wp.atomic_max(depth, inst, -d)
            wp.atomic_add(count_inside, inst, 1)

    return SimpleNamespace(project=project, penetration=penetration)


class BodyCollider:
    """One watertight body mesh per cloth instance, moved in place and refit.

    Build with :meth:`from_static` (given vertices/faces, e.g. a sphere in tests) or
    :meth:`from_warp_body` (the skinned SMPL-format body). Attributes:

    - num_instances (I), num_body_vertices (Vb), faces: int32 (Fb*3,) warp array, shared by all meshes.
    - points [m]: (I*Vb,) wp.vec3, the current body vertices (instance-major), the meshes' points.
    - velocities [m/s]: (I*Vb,) wp.vec3, the body's vertex velocities over the current step.
    - meshes: list of I ``wp.Mesh``; mesh_ids: (I,) uint64 warp array for the energy kernels.
    - refit_slots: the instances whose meshes :meth:`refit` refits (None: all); a pool leaves its
      idle slots out once an eighth of its slots are idle (their bodies are off: mesh id 0;
      :func:`simgen.sim.frame_runner.refit_slots`).
    - part_masks: (Fb,) int32 warp array of body part bit masks per face
      (:func:`simgen.body.parts.face_part_masks`), or None: contact's part rule (where the body
      intersects itself, :mod:`simgen.body.surface_query`) is on only with them.

    Body vertices are float32 (``wp.Mesh`` is); cloth models of either scalar type can use it.
    """

    def __init__(self, points: np.ndarray, faces: np.ndarray, *, part_masks=None, device=None) -> None:
        points = np.asarray(points, dtype=np.float32)
        faces = np.asarray(faces)
        if points.ndim != 3 or points.shape[2] != 3 or points.shape[1] < 4:
            raise InputError(f"body vertices must have shape (I, V, 3) with V >= 4, got {points.shape}")
        if not np.all(np.isfinite(points)):
            raise InputError("body vertices contain NaN or inf")
        if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
            raise InputError(f"body faces must be integers of shape (F, 3), got {faces.dtype} {faces.shape}")
        if faces.min() < 0 or faces.max() >= points.shape[1]:
            raise InputError(f"body faces index vertex {int(faces.max())} of {points.shape[1]}")
        self.device = wp.get_device(device)
        self.num_instances = int(points.shape[0])
        self.num_body_vertices = int(points.shape[1])
        self.num_body_faces = int(len(faces))
        dev = self.device
        flat = points.reshape(-1, 3)
        self.points = wp.array(flat, dtype=wp.vec3, device=dev)
        self.velocities = wp.zeros(len(flat), dtype=wp.vec3, device=dev)
        # Start and end of the current step: set_time interpolates between them.
        self._start = wp.array(flat, dtype=wp.vec3, device=dev)
        self._end = wp.array(flat, dtype=wp.vec3, device=dev)
        self.faces = wp.array(np.ascontiguousarray(faces, dtype=np.int32).reshape(-1), dtype=wp.int32, device=dev)
        nv = self.num_body_vertices
        self.meshes = [
            wp.Mesh(points=self.points[k * nv:(k + 1) * nv], indices=self.faces,
                    velocities=self.velocities[k * nv:(k + 1) * nv])
            for k in range(self.num_instances)
        ]
        self.mesh_ids = wp.array(np.array([m.id for m in self.meshes], dtype=np.uint64), dtype=wp.uint64, device=dev)
        self.part_masks = None
        if part_masks is not None:
            part_masks = np.asarray(part_masks)
            if part_masks.shape != (len(faces),) or not np.issubdtype(part_masks.dtype, np.integer):
                raise InputError(f"body part_masks must be {len(faces)} integers (one per face), got {part_masks.shape}")
            self.part_masks = wp.array(part_masks.astype(np.int32), dtype=wp.int32, device=dev)
        self._warp_body = None
        self._no_touch: dict = {}
        self._one_step = wp.array(np.ones(self.num_instances, dtype=np.int32), dtype=wp.int32, device=dev)
        self.refit_slots: tuple | None = None

    @classmethod
    def from_static(cls, vertices, faces, *, num_instances: int = 1, part_masks=None, device=None) -> "BodyCollider":
        """A static body: vertices [m] (V, 3) shared by all instances, or (I, V, 3); faces (F, 3),
        counter-clockwise seen from outside, watertight; part_masks as in the class doc."""
        v = np.asarray(vertices, dtype=np.float64)
        if v.ndim == 2:
            v = np.broadcast_to(v, (int(num_instances),) + v.shape)
        return cls(v, faces, part_masks=part_masks, device=device)

    @classmethod
    def from_warp_body(cls, body, *, seam_width: float | None = None, device=None) -> "BodyCollider":
        """A collider following a posed :class:`simgen.body.warp_lbs.WarpBody` (its instance count
        and current vertices); call :meth:`update` after each ``pose_from_quats``. Its part masks
        come from the body model's skinning weights on the template (seam_width [m]: see
        :func:`simgen.body.parts.face_part_masks`; None takes its default)."""
        from simgen.body.parts import DEFAULT_SEAM_WIDTH, face_part_masks, face_parts

        model = body.model
        faces = np.asarray(model.faces)
        masks = face_part_masks(model.v_template, faces, face_parts(model.weights, faces),
                                seam_width=DEFAULT_SEAM_WIDTH if seam_width is None else seam_width)
        v = body.vertices.numpy()
        self = cls(v, body.faces.numpy().reshape(-1, 3), part_masks=masks,
                   device=device if device is not None else body.device)
        self._warp_body = body
        return self

    def update(self, positions=None, velocities=None, *, dt: float | None = None, step_divisor=None) -> None:
        """Move the body to new vertex positions for the coming step and refit.

        positions [m]: (I, Vb, 3) or (I*Vb, 3) numpy, or an (I*Vb,) wp.vec3 array on the device;
          None with a WarpBody-built collider copies the WarpBody's current vertices on the device.
        velocities [m/s]: the body's vertex velocities over the step, same shapes; if None, they are
          (positions - previous positions) / dt when dt [s] is given, else zero (a teleport).
        step_divisor: int32 (I,) warp array (a cloth model's ``instance_step_divisor``): instance k's
          bodies moved in dt / step_divisor[k] (None: all in dt).
        The previous positions become the start of the step (see :meth:`set_time`); the meshes are
        left at the new positions.
        """
        wp.copy(self._start, self.points)
        if positions is None:
            if self._warp_body is None:
                raise InputError("BodyCollider.update needs positions unless it follows a WarpBody")
            src = self._warp_body.vertices_flat
            if src.shape != self._end.shape:
                raise InputError(f"the WarpBody now poses {src.shape[0]} vertices (instances x vertices) but the "
                                 f"collider was built for {self._end.shape[0]}")
            wp.copy(self._end, src)
        else:
            self._assign(self._end, positions, "positions")
        if velocities is not None:
            self._assign(self.velocities, velocities, "velocities")
        elif dt is not None:
            if not dt > 0:
                raise InputError(f"time step must be > 0, got {dt!r}")
            if step_divisor is None:
                step_divisor = self._one_step
            elif step_divisor.shape != (self.num_instances,):
                raise InputError(f"step_divisor must hold one int32 per body ({self.num_instances}), got shape "
                                 f"{step_divisor.shape}")
            wp.launch(_finite_difference, dim=len(self.points), device=self.device,
                      inputs=[self._start, self._end, 1.0 / dt, step_divisor, self.num_body_vertices,
                              self.velocities])
        else:
            self.velocities.zero_()
        wp.copy(self.points, self._end)
        self.refit()

    def _assign(self, dst: wp.array, values, what: str) -> None:
        if isinstance(values, wp.array):
            if values.shape != dst.shape:
                raise InputError(f"body {what} must have shape {dst.shape}, got {values.shape}")
            wp.copy(dst, values)
            return
        a = np.asarray(values, dtype=np.float32).reshape(-1, 3)
        if len(a) != len(dst):
            raise InputError(f"body {what} must hold {len(dst)} vertices (I x Vb), got {len(a)}")
        dst.assign(a)

    def set_time(self, fraction: float) -> None:
        """Place the body at start + fraction * (end - start) of the current step and refit
        (fraction in [0, 1]; used by solver substeps)."""
        wp.launch(_lerp_points, dim=len(self.points), device=self.device,
                  inputs=[self._start, self._end, float(fraction), self.points])
        self.refit()

    def refit(self) -> None:
        """Refit the BVHs of the meshes of ``refit_slots`` (every mesh when None) to their current
        points (no rebuild)."""
        for k in range(self.num_instances) if self.refit_slots is None else self.refit_slots:
            self.meshes[k].refit()

    def check_model(self, model) -> None:
        """Raise InputError unless this collider has one body per instance of ``model`` and the body
        triangles its attachments are tied to."""
        if model.num_instances != self.num_instances:
            raise InputError(f"the body collider has {self.num_instances} bodies but the cloth model has "
                             f"{model.num_instances} instances")
        if model.num_attachments and int(model.host.attach_face.max()) >= self.num_body_faces:
            raise InputError(f"the cloth model's waistband is tied to body triangle {int(model.host.attach_face.max())}, "
                             f"but the body has {self.num_body_faces}: build the model on the body it is simulated with")

    def project(self, model, state, *, offset: float = 0.0, query_distance: float = 0.05,
                pinch_distance: float = ContactParams.pinch_distance, depth=None, count=None,
                touching=None, touch_distance: float = ContactParams.margin, touch_normal=None,
                touch_plane=None) -> None:
        """Push every free cloth vertex inside its body (signed distance < 0) onto the surface.

        model: the ClothModel; state: its ClothState, modified in place: the position moves along
        the outward normal to signed distance ``offset`` [m] and the velocity loses the component
        that points into the body (relative to the body's velocity). query_distance [m]: deepest
        penetration that is found. pinch_distance [m]: the part rule of the contact
        (:class:`ContactParams`; with :attr:`part_masks` and a model with home parts, cloth on its own
        part is not pushed out of another part pressing into it). Optional outputs, (I,) per instance, accumulated with max/add:
        depth [m] (model scalar) of the deepest vertex before projection, count (int32) of vertices
        found inside (pinned ones included, though they are not moved). touching: optional (V,) int32,
        set to 1 (never reset here) for every vertex within ``touch_distance`` [m] of its body before
        projection, inside included; for those, touch_normal (V,) vec3 and touch_plane (V,) [m] (model
        scalar; given with touching) receive the half-space n . x >= plane that keeps the vertex
        ``offset`` outside the body (the impact filter's zones respect it).
        """
        self.check_model(model)
        if depth is None:
            depth = wp.zeros(model.num_instances, dtype=model.scalar, device=model.device)
        if count is None:
            count = wp.zeros(model.num_instances, dtype=wp.int32, device=model.device)
        touching, touch_normal, touch_plane = self._touch_outputs(model, touching, touch_normal, touch_plane)
        wp.launch(collider_kernels(model.scalar).project, dim=model.num_vertices, device=model.device, inputs=[
            state.positions, state.velocities, model.vertex_instance, model.vertex_pinned, self.mesh_ids,
            offset, query_distance, *part_inputs(model, self.part_masks, pinch_distance), float(touch_distance),
            depth, count, touching, touch_normal, touch_plane])

    def _touch_outputs(self, model, touching, normal, plane) -> tuple:
        """project()'s touching outputs, checked: all three (V,) arrays, or none (empty arrays of the
        model's types, made once per scalar type)."""
        given = [a is not None for a in (touching, normal, plane)]
        if not any(given):
            key = model.scalar
            if key not in self._no_touch:
                self._no_touch[key] = (wp.empty(0, dtype=wp.int32, device=model.device),
                                       wp.empty(0, dtype=model.vec3, device=model.device),
                                       wp.empty(0, dtype=model.scalar, device=model.device))
            return self._no_touch[key]
        n = model.num_vertices
        if not all(given) or any(a.shape != (n,) for a in (touching, normal, plane)):
            raise InputError(f"BodyCollider.project needs touching, touch_normal and touch_plane together, each of "
                             f"shape ({n},) (one per cloth vertex), or none of them")
        return touching, normal, plane

    def penetration(self, model, positions, *, query_distance: float = 0.05,
                    pinch_distance: float = ContactParams.pinch_distance) -> tuple[np.ndarray, np.ndarray]:
        """Per instance: the maximum depth [m] of cloth vertices inside the body (0 if none), shape
        (I,), and the share of the instance's vertices inside, shape (I,) (host sync). Inside means
        a negative contact distance, with the contact's part rule (see :meth:`project`)."""
        self.check_model(model)
        depth = wp.zeros(model.num_instances, dtype=model.scalar, device=model.device)
        count = wp.zeros(model.num_instances, dtype=wp.int32, device=model.device)
        wp.launch(collider_kernels(model.scalar).penetration, dim=model.num_vertices, device=model.device,
                  inputs=[positions, model.vertex_instance, self.mesh_ids, query_distance,
                          *part_inputs(model, self.part_masks, pinch_distance), depth, count])
        nv = np.diff(model.vertex_start)
        return depth.numpy().astype(np.float64), count.numpy() / nv
