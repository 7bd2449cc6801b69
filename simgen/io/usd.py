"""USD export of mesh sequences (animated bodies and garments).

One stage per sequence. Layout of a written file::

    #usda 1.0 (upAxis = "Y", metersPerUnit = 1, timeCodesPerSecond = fps, framesPerSecond = fps,
               startTimeCode = start_frame, endTimeCode = start_frame + T - 1,
               defaultPrim = "<root_name>", customLayerData = {simgen_version, ...metadata})
    def Xform "<root_name>" (kind = "component")
        def Mesh "<track name>" (customData = {"simgen:role": "body" | "garment" | ...})
            faceVertexCounts, faceVertexIndices      written once (topology never changes)
            points                                   float3[], one time sample per frame
            extent                                   one time sample per frame (bounds of the points)
            primvars:displayColor                    per-vertex colours (interpolation "vertex"),
                                                     or one constant colour chosen by the role
            subdivisionScheme = "none", orientation = "rightHanded", doubleSided (garments)

Frame ``i`` of a track is stored at time code ``start_frame + i``. A static track (points of shape
(V, 3)) is written as default values without time samples. Units are metres, Y is up, the floor is
y = 0 (see docs/architecture.md, "Units and axes").

pxr (usd-core) is imported inside the functions: the GPU machine has no usd-core, and
:class:`MeshTrack` is also the currency of :mod:`simgen.io.render`.
"""

from __future__ import annotations

import math
import os
import re
import uuid
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from simgen.errors import InputError

__all__ = ["ROLE_COLORS", "MeshTrack", "read_usd_info", "read_usd_meshes", "validate_usd", "write_usd"]

#: Default display colours (linear-ish RGB in [0, 1]) by role: a neutral skin tone for bodies and a
#: muted blue for garments, so the two read apart in usdview and in renders.
ROLE_COLORS: dict[str, tuple[float, float, float]] = {
    "body": (0.86, 0.70, 0.60),
    "garment": (0.22, 0.42, 0.72),
    "other": (0.60, 0.60, 0.60),
}

# Roles whose surfaces are open sheets: both sides must be drawn.
_DOUBLE_SIDED_ROLES = frozenset({"garment", "other"})

_ROLE_KEY = "simgen:role"
# USD prim names: an identifier (letters, digits, underscore; not starting with a digit). UTF-8
# identifiers are legal in USD >= 24, but ASCII names keep files portable to older readers.
_IDENTIFIER = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True, eq=False)
class MeshTrack:
    """One triangle mesh over a sequence of frames.

    Arguments are checked and normalised on construction; bad input raises :class:`InputError`
    naming the track and the field.

    Attributes:
        name: prim name in the USD file (letters, digits, ``_``; not starting with a digit).
        points: vertex positions [m], shape (T, V, 3) for an animated mesh or (V, 3) for a static
            one; stored as float32.
        faces: triangle vertex indices, shape (F, 3), each in [0, V); stored as int32.
        colors: optional per-vertex RGB in [0, 1], shape (V, 3) (constant over time) or (T, V, 3);
            stored as float32. ``None`` means "use the role's colour" (:data:`ROLE_COLORS`).
        role: what the mesh is: ``"body"``, ``"garment"`` or ``"other"``. It picks the default
            colour and whether the surface is double-sided (garments and others are).
    """

    name: str
    points: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    role: str = "body"
    _static: bool = field(init=False, repr=False)

    def __post_init__(self) -> None:
        name = self.name
        if not isinstance(name, str) or not _IDENTIFIER.match(name):
            raise InputError(
                f"mesh track name {name!r} is not a valid USD prim name "
                "(use letters, digits and '_', not starting with a digit)"
            )
        if self.role not in ROLE_COLORS:
            raise InputError(
                f"mesh track {name!r}: role {self.role!r} is not one of {sorted(ROLE_COLORS)}"
            )

        points = _as_float_array(self.points, name, "points")
        if points.ndim == 2:
            static = True
            points = points[None]
        elif points.ndim == 3:
            static = False
        else:
            raise InputError(
                f"mesh track {name!r}: points must have shape (T, V, 3) or (V, 3), "
                f"got {tuple(points.shape)}"
            )
        n_frames, n_verts, dim = points.shape
        if dim != 3 or n_verts < 3 or n_frames < 1:
            raise InputError(
                f"mesh track {name!r}: points must have shape (T, V, 3) with T >= 1 and V >= 3, "
                f"got {tuple(points.shape)}"
            )
        # Checked after the cast: finite float64 values beyond float32's range become inf.
        with np.errstate(over="ignore", invalid="ignore"):
            points32 = np.ascontiguousarray(points, dtype=np.float32)
        if not np.isfinite(points32).all():
            bad = np.argwhere(~np.isfinite(points32).all(axis=2))[0]
            where = f"vertex {bad[1]}" if static else f"frame {bad[0]}, vertex {bad[1]}"
            raise InputError(f"mesh track {name!r}: points are not finite at {where}")

        faces = np.asarray(self.faces)
        if faces.dtype.kind not in "iu":
            raise InputError(
                f"mesh track {name!r}: faces must be integer vertex indices, got dtype {faces.dtype}"
            )
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] < 1:
            raise InputError(
                f"mesh track {name!r}: faces must have shape (F, 3) with F >= 1, "
                f"got {tuple(faces.shape)}"
            )
        if faces.min() < 0 or faces.max() >= n_verts:
            raise InputError(
                f"mesh track {name!r}: faces index vertices in [{faces.min()}, {faces.max()}] "
                f"but points have only {n_verts} vertices"
            )

        colors = self.colors
        if colors is not None:
            colors = _as_float_array(colors, name, "colors")
            if colors.ndim == 2:
                colors = colors[None]
            ok = colors.ndim == 3 and colors.shape[1:] == (n_verts, 3)
            ok = ok and (colors.shape[0] == 1 or (not static and colors.shape[0] == n_frames))
            if not ok:
                expected = f"({n_verts}, 3)" + ("" if static else f" or ({n_frames}, {n_verts}, 3)")
                raise InputError(
                    f"mesh track {name!r}: colors must have shape {expected}, "
                    f"got {tuple(np.shape(self.colors))}"
                )
            colors = np.ascontiguousarray(colors, dtype=np.float32)
            if not np.isfinite(colors).all() or colors.min() < 0.0 or colors.max() > 1.0:
                raise InputError(f"mesh track {name!r}: colors must be finite RGB values in [0, 1]")
            if colors.shape[0] == 1:
                colors = colors[0]

        object.__setattr__(self, "points", points32[0] if static else points32)
        object.__setattr__(self, "faces", np.ascontiguousarray(faces, dtype=np.int32))
        object.__setattr__(self, "colors", colors)
        object.__setattr__(self, "_static", static)

    @property
    def static(self) -> bool:
        """True when the mesh does not move (points of shape (V, 3))."""
        return self._static

    @property
    def num_frames(self) -> int:
        """Number of frames T (1 for a static mesh)."""
        return 1 if self._static else int(self.points.shape[0])

    @property
    def num_vertices(self) -> int:
        """Number of vertices V."""
        return int(self.points.shape[-2])

    def frame(self, i: int) -> np.ndarray:
        """Vertex positions [m] of frame ``i``, shape (V, 3) float32 (a static mesh for any i)."""
        return self.points if self._static else self.points[i]

    def frame_colors(self, i: int) -> np.ndarray | None:
        """Per-vertex RGB of frame ``i``, shape (V, 3), or None when the track has no colours."""
        if self.colors is None or self.colors.ndim == 2:
            return self.colors
        return self.colors[i]

    def bounds(self) -> np.ndarray:
        """Axis-aligned bounds [m] over all frames, shape (2, 3): rows are min and max."""
        pts = self.points.reshape(-1, 3)
        return np.stack([pts.min(axis=0), pts.max(axis=0)]).astype(np.float64)


def write_usd(
    path: str | os.PathLike,
    tracks: Iterable[MeshTrack],
    *,
    fps: float,
    root_name: str = "simgen",
    metadata: Mapping[str, Any] | None = None,
    start_frame: int = 0,
    format: str | None = None,
) -> Path:
    """Write mesh tracks as one USD stage, atomically.

    Args:
        path: output file; ``.usdc`` (binary crate, the default format), ``.usda`` (text) or
            ``.usd`` (crate unless ``format="usda"``). Missing parent folders are created.
        tracks: the meshes; names must be unique. All animated tracks must have the same number
            of frames T; static tracks are held over the whole range.
        fps: frames per second (> 0); becomes timeCodesPerSecond and framesPerSecond.
        root_name: name of the root Xform, which is the stage's defaultPrim.
        metadata: extra facts stored as the layer's customLayerData (body id, motion name, ...):
            str keys, values bool/int/float/str, lists of one of those, or nested mappings.
            ``simgen_version`` is added unless given.
        start_frame: time code of the first frame (an integer).
        format: ``"usdc"`` or ``"usda"`` to force the encoding of a ``.usd`` file; must agree
            with a ``.usdc``/``.usda`` suffix.

    Returns:
        The path written.

    Raises:
        InputError: bad tracks, fps, names, metadata or path; nothing is written then.
    """
    path = Path(path)
    tracks = list(tracks)
    file_format = _file_format(path, format)
    if not isinstance(fps, (int, float, np.integer, np.floating)) or isinstance(fps, bool):
        raise InputError(f"fps must be a number, got {fps!r}")
    fps = float(fps)
    if not math.isfinite(fps) or fps <= 0.0:
        raise InputError(f"fps must be a positive number, got {fps}")
    if isinstance(start_frame, bool) or not isinstance(start_frame, (int, np.integer)):
        raise InputError(f"start_frame must be an integer, got {start_frame!r}")
    start_frame = int(start_frame)
    if not isinstance(root_name, str) or not _IDENTIFIER.match(root_name):
        raise InputError(f"root_name {root_name!r} is not a valid USD prim name")
    if not tracks:
        raise InputError("no mesh tracks to write")
    names: set[str] = set()
    for track in tracks:
        if not isinstance(track, MeshTrack):
            raise InputError(f"tracks must be MeshTrack objects, got {type(track).__name__}")
        if track.name in names:
            raise InputError(f"mesh track name {track.name!r} is used twice")
        if track.name == root_name:
            raise InputError(f"mesh track name {track.name!r} equals the root prim name")
        names.add(track.name)
    animated = {t.name: t.num_frames for t in tracks if not t.static}
    if len(set(animated.values())) > 1:
        counts = ", ".join(f"{n}: {c}" for n, c in animated.items())
        raise InputError(f"animated mesh tracks have different frame counts ({counts})")
    n_frames = next(iter(animated.values()), 1)
    layer_data = _layer_data(metadata)

    from pxr import Gf, Kind, Sdf, Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.LinearUnits.meters)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)
    stage.SetStartTimeCode(start_frame)
    stage.SetEndTimeCode(start_frame + n_frames - 1)
    layer = stage.GetRootLayer()
    layer.documentation = f"simgen mesh sequence: {len(tracks)} mesh(es), {n_frames} frame(s)"
    layer.customLayerData = layer_data

    root = UsdGeom.Xform.Define(stage, Sdf.Path.absoluteRootPath.AppendChild(root_name))
    stage.SetDefaultPrim(root.GetPrim())
    # A model root makes the file referenceable as an asset; meshes directly under it make it a
    # leaf model, i.e. a component.
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)

    for track in tracks:
        mesh = UsdGeom.Mesh.Define(stage, root.GetPath().AppendChild(track.name))
        prim = mesh.GetPrim()
        prim.SetCustomDataByKey(_ROLE_KEY, track.role)
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.CreateDoubleSidedAttr(track.role in _DOUBLE_SIDED_ROLES)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(track.faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(track.faces.reshape(-1)))

        points_attr = mesh.CreatePointsAttr()
        extent_attr = mesh.CreateExtentAttr()
        if track.static:
            points_attr.Set(Vt.Vec3fArray.FromNumpy(track.points))
            extent_attr.Set(Vt.Vec3fArray.FromNumpy(_extent(track.points)))
        else:
            for i in range(track.num_frames):
                time = Usd.TimeCode(start_frame + i)
                points_attr.Set(Vt.Vec3fArray.FromNumpy(track.points[i]), time)
                extent_attr.Set(Vt.Vec3fArray.FromNumpy(_extent(track.points[i])), time)

        color = mesh.CreateDisplayColorPrimvar()
        if track.colors is None:
            color.SetInterpolation(UsdGeom.Tokens.constant)
            color.Set(Vt.Vec3fArray([Gf.Vec3f(*ROLE_COLORS[track.role])]))
        else:
            color.SetInterpolation(UsdGeom.Tokens.vertex)
            if track.colors.ndim == 2:
                color.Set(Vt.Vec3fArray.FromNumpy(track.colors))
            else:
                for i in range(track.num_frames):
                    color.Set(Vt.Vec3fArray.FromNumpy(track.colors[i]), Usd.TimeCode(start_frame + i))

    _export_atomically(layer, path, file_format)
    return path


def read_usd_meshes(path: str | os.PathLike) -> dict[str, MeshTrack]:
    """Read the meshes of a USD file back as :class:`MeshTrack` objects, keyed by prim name.

    Reads every ``Mesh`` prim on the stage (triangles only; names must be unique). A mesh with
    time-sampled points yields points of shape (T, V, 3) sampled at each integer time code from
    the stage's start to end time code (at the points' own time samples when the stage has no
    time code range); a mesh without time samples yields (V, 3). Per-vertex displayColor comes back
    as ``colors``; a constant colour (the role default) as ``colors=None``. The role is read from
    the prim's ``simgen:role`` custom data ("other" when absent).

    Raises:
        InputError: the file is missing or not a USD file, or holds a non-triangle mesh.
    """
    path = Path(path)
    stage = _open_stage(path)
    from pxr import Usd, UsdGeom

    stage_times = None
    if stage.HasAuthoredTimeCodeRange():
        start, end = stage.GetStartTimeCode(), stage.GetEndTimeCode()
        stage_times = [Usd.TimeCode(t) for t in range(int(math.floor(start)), int(math.floor(end)) + 1)]
    result: dict[str, MeshTrack] = {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        mesh = UsdGeom.Mesh(prim)
        name = prim.GetName()
        if name in result:
            raise InputError(f"{path}: two meshes are named {name!r}; mesh names must be unique")
        # Files from elsewhere may have no time code range: then each mesh's own samples count.
        times = stage_times or [Usd.TimeCode(t) for t in mesh.GetPointsAttr().GetTimeSamples()]
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int64)
        indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
        if counts.size == 0 or not np.all(counts == 3):
            raise InputError(f"{path}: mesh {prim.GetPath()} is not a triangle mesh")
        faces = indices.reshape(-1, 3)

        points_attr = mesh.GetPointsAttr()
        animated = points_attr.GetNumTimeSamples() > 0
        if animated:
            points = np.stack([np.asarray(points_attr.Get(t), dtype=np.float32) for t in times])
        else:
            points = np.asarray(points_attr.Get(), dtype=np.float32)

        colors = None
        color = mesh.GetDisplayColorPrimvar()
        if color and color.HasAuthoredValue() and color.GetInterpolation() == UsdGeom.Tokens.vertex:
            if color.GetAttr().GetNumTimeSamples() > 0:
                colors = np.stack([np.asarray(color.Get(t), dtype=np.float32) for t in times])
            else:
                colors = np.asarray(color.Get(), dtype=np.float32)

        role = prim.GetCustomDataByKey(_ROLE_KEY)
        role = role if role in ROLE_COLORS else "other"
        result[name] = MeshTrack(name, points, faces, colors=colors, role=role)
    return result


def read_usd_info(path: str | os.PathLike) -> dict[str, Any]:
    """Stage-level facts of a USD file as plain Python values.

    Returns:
        ``{"up_axis": "Y", "meters_per_unit": 1.0, "time_codes_per_second": fps,
        "frames_per_second": fps, "start_time_code": ..., "end_time_code": ...,
        "default_prim": "simgen", "metadata": {customLayerData, lists as lists}}``.

    Raises:
        InputError: the file is missing or cannot be opened as a USD stage.
    """
    stage = _open_stage(Path(path))
    from pxr import UsdGeom

    default_prim = stage.GetDefaultPrim()
    return {
        "up_axis": str(UsdGeom.GetStageUpAxis(stage)),
        "meters_per_unit": float(UsdGeom.GetStageMetersPerUnit(stage)),
        "time_codes_per_second": float(stage.GetTimeCodesPerSecond()),
        "frames_per_second": float(stage.GetFramesPerSecond()),
        "start_time_code": float(stage.GetStartTimeCode()),
        "end_time_code": float(stage.GetEndTimeCode()),
        "default_prim": default_prim.GetName() if default_prim else None,
        "metadata": _plain(stage.GetRootLayer().customLayerData),
    }


def validate_usd(path: str | os.PathLike, *, strict: bool = False) -> list[str]:
    """Validate a USD file with OpenUSD's validation framework (``pxr.UsdValidation``).

    Runs the same validators as ``usdchecker --useNewValidationFramework`` without ``--arkit``:
    every registered validator except the usdz-only ones (keyword ``UsdzValidators``), over all
    prims and all time codes.

    Args:
        path: the USD file.
        strict: also report warnings (as ``usdchecker --strict`` fails on them).

    Returns:
        One message per problem as USD words it, which starts with the severity and names the
        validator, e.g. ``"Error: (usdGeomValidators:StageMetadataChecker.MissingUpAxisMetadata)
        Stage with root layer <...> does not specify an upAxis."``; errors only unless ``strict``,
        then warnings too. Empty when the file is valid. Info-level notes are never reported.

    Raises:
        InputError: the file is missing or cannot be opened as a USD stage.
    """
    path = Path(path)
    stage = _open_stage(path)
    try:
        from pxr import UsdValidation
    except ImportError:
        # Older usd-core kept a different validation API (and usdchecker's ComplianceChecker).
        raise RuntimeError("validate_usd needs usd-core >= 25.05, which has pxr.UsdValidation") from None

    registry = UsdValidation.ValidationRegistry()
    validators = {}
    for meta in registry.GetAllValidatorMetadata():
        if "UsdzValidators" in list(meta.GetKeywords()):
            continue
        if meta.isSuite:
            contained = registry.GetOrLoadValidatorSuiteByName(meta.name).GetContainedValidators()
        else:
            contained = [registry.GetOrLoadValidatorByName(meta.name)]
        for validator in contained:
            validators[validator.GetMetadata().name] = validator
    # Built from validators, not from their metadata: the Python binding of the metadata
    # constructor is shadowed by the schema-type one in usd-core 26.
    context = UsdValidation.ValidationContext(list(validators.values()))
    messages = []
    for error in context.Validate(stage):
        kind = error.GetType()
        if kind == UsdValidation.ValidationErrorType.Error:
            messages.append(error.GetErrorAsString())
        elif strict and kind == UsdValidation.ValidationErrorType.Warn:
            messages.append(error.GetErrorAsString())
    return messages


# --- helpers ---------------------------------------------------------------------------------


def _as_float_array(value: Any, track: str, field_name: str) -> np.ndarray:
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"mesh track {track!r}: {field_name} is not an array ({exc})") from None
    if array.dtype.kind not in "fiu" or array.dtype == np.bool_:
        raise InputError(f"mesh track {track!r}: {field_name} must be numbers, got dtype {array.dtype}")
    return array


def _extent(points: np.ndarray) -> np.ndarray:
    """Bounds of one frame's points, shape (2, 3) float32 (USD's extent: min row, max row)."""
    return np.stack([points.min(axis=0), points.max(axis=0)]).astype(np.float32)


def _file_format(path: Path, requested: str | None) -> str:
    suffix = path.suffix.lower()
    if requested is not None and requested not in ("usdc", "usda"):
        raise InputError(f"format must be 'usdc' or 'usda', got {requested!r}")
    if suffix in (".usdc", ".usda"):
        implied = suffix[1:]
        if requested is not None and requested != implied:
            raise InputError(f"format {requested!r} contradicts the file name {path.name!r}")
        return implied
    if suffix == ".usd":
        return requested or "usdc"
    raise InputError(f"USD output {str(path)!r} must end in .usdc, .usda or .usd")


def _layer_data(metadata: Mapping[str, Any] | None) -> dict[str, Any]:
    data: dict[str, Any] = {}
    if metadata is not None:
        if not isinstance(metadata, Mapping):
            raise InputError(f"metadata must be a mapping, got {type(metadata).__name__}")
        data = _usd_dict(metadata, "metadata")
    data.setdefault("simgen_version", _simgen_version())
    return data


def _usd_dict(mapping: Mapping[str, Any], where: str) -> dict[str, Any]:
    out = {}
    for key, value in mapping.items():
        if not isinstance(key, str) or not key:
            raise InputError(f"{where} keys must be non-empty strings, got {key!r}")
        out[key] = _usd_value(value, f"{where}[{key!r}]")
    return out


def _usd_value(value: Any, where: str) -> Any:
    """Turn a metadata value into something both USD encodings store (lists become typed arrays:
    the crate format cannot hold a list of untyped values)."""
    if isinstance(value, Mapping):
        return _usd_dict(value, where)
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, (str, bool, int)):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise InputError(f"{where} must be finite, got {value}")
        return value
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, (list, tuple, np.ndarray)):
        from pxr import Vt

        items = value.tolist() if isinstance(value, np.ndarray) else list(value)
        if any(isinstance(v, (list, tuple, Mapping)) for v in items):
            raise InputError(f"{where} must be a flat list (nest mappings, not lists)")
        items = [_usd_value(v, where) for v in items]
        kinds = {type(v) for v in items}
        if kinds <= {str} and items:
            return Vt.StringArray(items)
        if kinds <= {bool} and items:
            return Vt.BoolArray(items)
        if kinds <= {int} and items:
            return Vt.Int64Array(items)
        if kinds <= {int, float}:
            return Vt.DoubleArray([float(v) for v in items])
        raise InputError(f"{where} must be a list of one scalar type (all str, bool or numbers)")
    raise InputError(f"{where} has unsupported type {type(value).__name__} for USD metadata")


def _plain(value: Any) -> Any:
    """customLayerData as read back (Vt arrays, nested dicts) as plain Python values."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (str, bool, int, float)):
        return value
    try:
        return [_plain(v) for v in value]
    except TypeError:
        return value


def _simgen_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("simgen")
    except PackageNotFoundError:
        return "unknown"


def _export_atomically(layer: Any, path: Path, file_format: str) -> None:
    """Export ``layer`` to a temporary file beside ``path`` and rename it into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # A fresh name in the same folder (so the rename is atomic) that ends in the format's suffix
    # (Sdf picks the encoding from it). Not mkstemp: Sdf creates the file itself, with the
    # permissions the umask gives, as for any other file the user writes.
    tmp = path.parent / f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp.{file_format}"
    try:
        if not layer.Export(str(tmp)):
            raise OSError(f"could not write USD file {path}")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _open_stage(path: Path) -> Any:
    if not path.is_file():
        raise InputError(f"USD file {str(path)!r} does not exist")
    from pxr import Sdf, Tf, Usd

    # A layer still open in this process would be served from Sdf's registry as it was when
    # first read; the file may have been rewritten since.
    cached = Sdf.Layer.Find(str(path))
    if cached is not None:
        cached.Reload(force=True)
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        first = str(exc).strip().splitlines()[-1] if str(exc).strip() else "unreadable"
        raise InputError(f"{str(path)!r} is not a readable USD file ({first.strip()})") from None
    if stage is None:
        raise InputError(f"{str(path)!r} is not a readable USD file")
    return stage
