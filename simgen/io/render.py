"""Offscreen rendering of bodies and garments: one frame to PNG, a sequence to H.264 MP4.

Scenes follow docs/architecture.md ("Units and axes"): metres, Y up, a checker floor at y = 0.
Bodies are drawn in a neutral skin tone, garments in distinct colours
(:data:`simgen.io.usd.ROLE_COLORS`, :data:`GARMENT_PALETTE`), smooth-shaded under a light kit.

Framing (one implementation, :func:`follow_cameras`, used whenever a caller passes no camera): a
3/4 front view whose camera follows the body's root across the floor (the horizontal centroid of
the body meshes per frame, smoothed with a Gaussian of 0.5 s so the camera glides instead of
jittering with the gait) at one distance for the whole sequence, chosen so that everything drawn
spans :data:`BODY_FILL` (80 %) of the image height at its tallest. The floor scrolls under the
body, so motion still reads as motion. Pictures and videos are :data:`DEFAULT_SIZE` (1280x720)
unless a size is given. A small legend (``legend=``: garment, shape, motion, ... and the frame
number; :func:`scene_legend` builds the usual one) sits in the upper-left corner.

Headless use: with no ``DISPLAY``/``WAYLAND_DISPLAY`` this module points VTK at its EGL render
window (Mesa's software EGL is enough: Debian packages libegl1, libegl-mesa0, libgl1-mesa-dri, as
installed by ``.ci/system-deps.sh``), or at OSMesa when only libOSMesa is present, before pyvista
creates a window. Setting ``VTK_DEFAULT_OPENGL_WINDOW`` yourself overrides that choice.

pyvista, VTK and imageio are imported inside the functions: the GPU machine has none of them.
"""

from __future__ import annotations

import ctypes
import math
import os
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from simgen._fileio import temp_path_beside
from simgen.errors import InputError
from simgen.io.usd import ROLE_COLORS, MeshTrack

__all__ = [
    "BODY_FILL",
    "DEFAULT_SIZE",
    "GARMENT_PALETTE",
    "Camera",
    "RenderError",
    "default_camera",
    "describe_betas",
    "follow_cameras",
    "frame_text",
    "render_frame",
    "render_sequence",
    "scene_legend",
    "sequence_bounds",
]

#: Image (width, height) [px] of every render that does not ask for another size.
DEFAULT_SIZE: tuple[int, int] = (1280, 720)
#: Share of the image height that the scene spans at its tallest frame (:func:`follow_cameras`).
BODY_FILL = 0.8
#: [s] standard deviation of the Gaussian that smooths the followed root path.
FOLLOW_SMOOTHING = 0.5

#: Colours of successive garments in one scene (RGB in [0, 1]); the first is the garment role's.
GARMENT_PALETTE: tuple[tuple[float, float, float], ...] = (
    ROLE_COLORS["garment"],
    (0.78, 0.33, 0.25),
    (0.24, 0.58, 0.44),
    (0.55, 0.40, 0.70),
)

# [m] Garments are drawn this far out along their vertex normals: cloth resting 0.2 mm outside the
# skin (the solver's projection offset) is closer than the depth buffer resolves in a full-body
# view, and the body would show through it in patches. Only the image moves; no data does.
GARMENT_DISPLAY_OFFSET = 1.5e-3

_BACKGROUND_BOTTOM = (0.97, 0.97, 0.96)
_BACKGROUND_TOP = (0.78, 0.84, 0.91)
_FLOOR_COLORS = ((0.84, 0.83, 0.80), (0.74, 0.73, 0.70))
_FLOOR_TILE = 0.5  # [m] checker tile edge: big enough to read, small enough to show motion
_MIN_FLOOR_HALF_SIZE = 4.0  # [m]

# A mesh to draw: (points (V, 3), faces (F, 3)) or (points, faces, color), or a MeshTrack.
MeshLike = MeshTrack | tuple[Any, ...]
Progress = Callable[[int, int], None]
RGB = tuple[float, float, float]
# A mesh with the fixed colour it is drawn in (None: its per-vertex colours).
_Item = tuple[MeshTrack, RGB | None]


class RenderError(RuntimeError):
    """Offscreen rendering is not possible on this machine (no usable OpenGL stack)."""


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in world coordinates [m].

    Attributes:
        position: camera centre, shape (3,).
        focal_point: the point looked at, shape (3,).
        view_up: the world direction that appears up in the image, shape (3,).
        view_angle: vertical field of view [deg].
    """

    position: tuple[float, float, float]
    focal_point: tuple[float, float, float]
    view_up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    view_angle: float = 30.0


def _view_basis(azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors (back, right, up) of a camera turned ``azimuth`` deg about +Y from +Z towards
    +X and raised ``elevation`` deg: ``back`` points from the scene to the camera."""
    az, el = math.radians(azimuth), math.radians(elevation)
    back = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    return back, right, up


def default_camera(
    bounds: Any,
    *,
    aspect: float = 4.0 / 3.0,
    azimuth: float = 30.0,
    elevation: float = 12.0,
    view_angle: float = 30.0,
    margin: float = 0.08,
) -> Camera:
    """A fixed 3/4 front view that keeps a whole box in the picture (for composed pictures such
    as the docs' grids; renders of bodies take :func:`follow_cameras` by default).

    The camera looks at the centre of ``bounds`` from the front (+Z, where SMPL bodies face),
    turned ``azimuth`` degrees towards +X and raised ``elevation`` degrees, Y up. Its distance is
    the smallest at which every corner of the box lies inside the view frustum, with ``margin``
    (a fraction of the half field of view) left free at the tightest image border.

    Args:
        bounds: axis-aligned box [m], shape (2, 3): rows min and max (e.g. from
            :func:`sequence_bounds`), or pyvista's (xmin, xmax, ymin, ymax, zmin, zmax).
        aspect: image width / height.
        azimuth: rotation about +Y from the +Z axis towards +X [deg].
        elevation: angle above the horizontal [deg].
        view_angle: vertical field of view [deg].
        margin: free fraction of the half field of view at the tightest border, in [0, 0.5).
    """
    box = np.asarray(bounds, dtype=np.float64)
    if box.shape == (6,):
        box = box.reshape(3, 2).T
    if box.shape != (2, 3) or not np.isfinite(box).all() or (box[1] < box[0]).any():
        raise InputError(f"camera bounds must be a finite (2, 3) min/max box, got {np.shape(bounds)}")
    if not (aspect > 0 and 0 < view_angle < 170 and 0 <= margin < 0.5):
        raise InputError("camera aspect must be > 0, view_angle in (0, 170) deg, margin in [0, 0.5)")
    back, right, up = _view_basis(azimuth, elevation)

    center = box.mean(axis=0)
    corners = np.array([[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    rel = corners - center
    x, y, z = rel @ right, rel @ up, rel @ back
    tan_v = math.tan(math.radians(view_angle) / 2) * (1.0 - margin)
    tan_h = math.tan(math.radians(view_angle) / 2) * aspect * (1.0 - margin)
    # A corner at camera-frame (x, y, z) is inside when |x| <= (D - z) tan_h and |y| <= (D - z) tan_v.
    distance = float(np.max(np.maximum(z + np.abs(x) / tan_h, z + np.abs(y) / tan_v)))
    # A degenerate (flat or point) box still needs the camera in front of it.
    distance = max(distance, float(np.max(z)) + 0.1, 0.1)
    position = center + distance * back
    return Camera(_floats(position), _floats(center), _floats(up), float(view_angle))


def follow_cameras(
    tracks: Sequence[MeshTrack],
    *,
    aspect: float = DEFAULT_SIZE[0] / DEFAULT_SIZE[1],
    fps: float = 30.0,
    fill: float = BODY_FILL,
    azimuth: float = 30.0,
    elevation: float = 10.0,
    view_angle: float = 30.0,
    smoothing: float = FOLLOW_SMOOTHING,
) -> list[Camera]:
    """One camera per frame that follows the body and keeps it at ``fill`` of the image height.

    This is the framing of every render made without an explicit camera (the demo, ``simgen
    simulate``, ``render``, ``garment preview``, ``dataset export``): keep it the only one.

    - Root: per frame, the horizontal (x, z) centroid of the vertices of the tracks whose role is
      "body" (of all tracks when none is), smoothed over time by a Gaussian of ``smoothing``
      seconds (its ends extended by point reflection, so a steady walk is followed without lag).
      The camera moves with it; its height, direction and distance stay fixed.
    - Direction: a 3/4 front view, turned ``azimuth`` deg from +Z towards +X and raised
      ``elevation`` deg (as :func:`default_camera`).
    - Distance and height: over every frame and every vertex of every track, measured from the
      followed root, the smallest distance at which the highest and the lowest points project
      ``fill`` of the image height apart (centred vertically) and every point fits the width
      (5 % free at the sides). So the tallest frame spans ``fill`` of the height; a frame where the
      body crouches or jumps spans less.

    Args:
        tracks: the meshes drawn; animated tracks must share one frame count T (static ones are
            held).
        aspect: image width / height.
        fps: frame rate [1/s] of the tracks (the smoothing is in seconds).
        fill: share of the image height spanned at the tallest frame, in (0, 1).
        azimuth, elevation, view_angle: the view [deg].
        smoothing: standard deviation [s] of the root path's Gaussian (0: follow every wobble).

    Returns:
        T cameras (1 when every track is static).
    """
    tracks = list(tracks)
    if not tracks or not all(isinstance(t, MeshTrack) for t in tracks):
        raise InputError("follow_cameras needs a non-empty list of MeshTrack objects")
    counts = {t.num_frames for t in tracks if not t.static}
    if len(counts) > 1:
        raise InputError(f"animated mesh tracks have different frame counts {sorted(counts)}")
    if not (aspect > 0 and 0 < view_angle < 170 and 0 < fill < 1 and fps > 0 and smoothing >= 0):
        raise InputError("camera aspect and fps must be > 0, view_angle in (0, 170) deg, fill in (0, 1), "
                         "smoothing >= 0")
    n_frames = counts.pop() if counts else 1
    subject = [t for t in tracks if t.role == "body"] or tracks

    def at(track: MeshTrack, k: int) -> np.ndarray:
        return np.asarray(track.frame(0 if track.static else k), dtype=np.float64)

    root = np.array([np.concatenate([at(t, k) for t in subject]).mean(axis=0)[[0, 2]] for k in range(n_frames)])
    if not np.isfinite(root).all():
        raise InputError("mesh points must be finite to frame them")
    root = _smooth(root, smoothing * float(fps))

    back, right, up = _view_basis(azimuth, elevation)
    tan_v = math.tan(math.radians(view_angle) / 2) * fill
    tan_h = math.tan(math.radians(view_angle) / 2) * aspect * 0.95
    top, bottom, side, near = -np.inf, np.inf, -np.inf, -np.inf
    for k in range(n_frames):
        rel = np.concatenate([at(t, k) for t in tracks]) - [root[k, 0], 0.0, root[k, 1]]
        x, y, z = rel @ right, rel @ up, rel @ back
        # A point at camera-frame (x, y - s, z) (s: the look-at height along `up`) projects to
        # (y - s) / (D - z). The highest at +tan_v and the lowest at -tan_v need
        # D = (max(y + tan_v z) - min(y - tan_v z)) / (2 tan_v), s = their mean.
        top = max(top, float(np.max(y + tan_v * z)))
        bottom = min(bottom, float(np.min(y - tan_v * z)))
        side = max(side, float(np.max(z + np.abs(x) / tan_h)))
        near = max(near, float(np.max(z)))
    distance = max((top - bottom) / (2.0 * tan_v), side, near + 0.1, 0.1)
    # With a larger distance than the height needs (a wide pose), keep the scene centred.
    shift = 0.5 * ((top - tan_v * distance) + (bottom + tan_v * distance))
    cameras = []
    for k in range(n_frames):
        focal = np.array([root[k, 0], 0.0, root[k, 1]]) + shift * up
        cameras.append(Camera(_floats(focal + distance * back), _floats(focal), _floats(up), float(view_angle)))
    return cameras


def _smooth(path: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of a path (T, k) along time with standard deviation ``sigma`` [frames].

    The ends are extended by point reflection (x[-j] = 2 x[0] - x[j]), which keeps straight-line
    motion straight (no lag at the ends, unlike repeating the end value)."""
    path = np.asarray(path, dtype=np.float64)
    n = len(path)
    radius = min(int(math.ceil(3.0 * sigma)), n - 1)
    if sigma <= 0 or radius < 1:
        return path
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    kernel /= kernel.sum()
    head = 2.0 * path[0] - path[radius:0:-1]
    tail = 2.0 * path[-1] - path[-2:-radius - 2:-1]
    padded = np.concatenate([head, path, tail])
    return np.stack([np.convolve(padded[:, c], kernel, mode="valid") for c in range(path.shape[1])], axis=1)


def describe_betas(betas: Any) -> str:
    """A short text for a body shape, for legends: "mean shape (betas 0)", "betas 1.5, -0.5"
    (the values up to the last non-zero one, 2 decimals), or, past four values, the non-zero ones
    by index: "b0 1.5, b6 0.2" (at most four, then "+n"). betas: (B,), or None for the mean shape."""
    b = np.zeros(1) if betas is None else np.atleast_1d(np.asarray(betas, dtype=np.float64))
    if b.ndim != 1:
        raise InputError(f"betas must be one shape vector (B,), got shape {b.shape}")
    values = np.round(b, 2) + 0.0  # + 0.0: no "-0"
    nonzero = np.flatnonzero(values)
    if nonzero.size == 0:
        return "mean shape (betas 0)"
    if nonzero[-1] < 4:
        return "betas " + ", ".join(f"{v:g}" for v in values[: nonzero[-1] + 1])
    shown = ", ".join(f"b{i} {values[i]:g}" for i in nonzero[:4])
    return f"betas {shown}" + (f" +{nonzero.size - 4}" if nonzero.size > 4 else "")


def scene_legend(*, garment: str | None = None, betas: Any = None, motion: str | None = None,
                 **more: str) -> dict[str, str]:
    """The legend of a render: {"garment": NAME, "shape": :func:`describe_betas`, "motion": NAME}
    plus ``more`` entries, in that order (None values left out). :func:`render_sequence` and
    :func:`render_frame` add the frame number."""
    out = {}
    if garment is not None:
        out["garment"] = str(garment)
    out["shape"] = describe_betas(betas)
    if motion is not None:
        out["motion"] = str(motion)
    out.update({k: str(v) for k, v in more.items() if v is not None})
    return out


def _floats(vector: np.ndarray) -> tuple[float, float, float]:
    """A 3-vector as plain Python floats (readable reprs, no numpy scalars in a Camera)."""
    return (float(vector[0]), float(vector[1]), float(vector[2]))


def sequence_bounds(tracks: Sequence[MeshTrack]) -> np.ndarray:
    """Union of the bounds of all frames of all tracks [m], shape (2, 3): rows min and max."""
    boxes = np.stack([t.bounds() for t in tracks])
    return np.stack([boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)])


def render_frame(
    path_png: str | os.PathLike,
    meshes: Sequence[MeshLike],
    *,
    camera: Camera | None = None,
    size: tuple[int, int] = DEFAULT_SIZE,
    floor: bool = True,
    title: str | None = None,
    frame: int = 0,
    ambient_occlusion: bool = False,
    legend: Mapping[str, str] | None = None,
    frame_label: str | None = None,
    fps: float = 30.0,
) -> Path:
    """Render meshes to a PNG.

    Args:
        path_png: output ``.png`` file (written atomically; parent folders are created).
        meshes: each a :class:`MeshTrack` (its frame ``frame`` is drawn), or a tuple
            ``(points (V, 3) [m], faces (F, 3))`` or ``(points, faces, color)`` where color is an
            RGB triple in [0, 1], per-vertex colours (V, 3), a role name ("body", "garment",
            "other") or None. Tuples without a colour: the first is drawn as a body, the others
            as garments.
        camera: fixed camera; default: frame ``frame`` of :func:`follow_cameras` over all the
            tracks' frames, so the picture is the same as that frame of :func:`render_sequence`.
        size: image (width, height) in pixels, each in [16, 8192].
        floor: draw the checker floor at y = 0.
        title: text drawn in the upper-left corner (above the legend).
        frame: frame index used for MeshTrack entries.
        ambient_occlusion: darken creases and contact with the floor (screen-space ambient
            occlusion); about 5x slower.
        legend: lines "key  value" drawn in the upper-left corner (:func:`scene_legend`), followed
            by a "frame" line: ``frame_label``, or "k / T-1 (t s)".
        frame_label: the frame line of the legend instead of the frame number.
        fps: frame rate [1/s] of animated tracks: the frame line's time and the camera's smoothing.

    Returns:
        The path written.

    Raises:
        InputError: bad meshes, size, frame or path. RenderError: no OpenGL for offscreen use.
    """
    path = _check_path(path_png, ".png")
    width, height = _check_size(size)
    items = _items_from_meshes(meshes)
    if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)):
        raise InputError(f"frame must be an integer, got {frame!r}")
    for track, _ in items:
        if not track.static and not (0 <= frame < track.num_frames):
            raise InputError(f"frame {frame} is outside mesh {track.name!r}'s {track.num_frames} frames")
    _check_fps(fps)
    tracks = [t for t, _ in items]
    n_frames = max([t.num_frames for t in tracks if not t.static], default=1)
    if camera is not None:
        cam = camera
    elif len({t.num_frames for t in tracks if not t.static}) <= 1:
        cam = follow_cameras(tracks, aspect=width / height, fps=fps)[frame if n_frames > 1 else 0]
    else:  # tracks of different lengths: frame this one frame alone
        still = [MeshTrack(t.name, t.frame(frame), t.faces, role=t.role) for t in tracks]
        cam = follow_cameras(still, aspect=width / height)[0]
    _check_camera(cam)
    text = _legend_text(title, legend, frame_label if frame_label is not None
                        else frame_text(frame, n_frames, fps) if legend else None)

    scene = _Scene(items, (width, height), floor=floor, ambient_occlusion=ambient_occlusion)
    try:
        image = scene.draw(frame, cam, text)
    finally:
        scene.close()

    import imageio.v3 as iio

    tmp = temp_path_beside(path)
    try:
        iio.imwrite(tmp, image, extension=".png")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def render_sequence(
    path_mp4: str | os.PathLike,
    tracks: Sequence[MeshTrack],
    *,
    fps: float,
    size: tuple[int, int] = DEFAULT_SIZE,
    camera: Camera | Sequence[Camera] | None = None,
    floor: bool = True,
    title: str | None = None,
    progress: Progress | None = None,
    ambient_occlusion: bool = False,
    legend: Mapping[str, str] | None = None,
    frame_labels: Sequence[str] | None = None,
) -> Path:
    """Render mesh tracks to an H.264 MP4 (yuv420p), one video frame per track frame.

    Args:
        path_mp4: output ``.mp4`` file (written atomically; parent folders are created).
        tracks: the meshes; animated tracks must share one frame count T, static tracks are held.
            Colours: a track's ``colors`` if set, else its role's (garments take successive
            :data:`GARMENT_PALETTE` colours).
        fps: frame rate of the video (> 0), normally the sequence's.
        size: video (width, height) in pixels, each in [16, 8192]; odd values are rounded up to
            even, which yuv420p needs.
        camera: one fixed camera, or one camera per frame (T of them); default
            :func:`follow_cameras` (follows the body, which spans 80 % of the height).
        floor: draw the checker floor at y = 0.
        title: text drawn in the upper-left corner of every frame (above the legend).
        progress: called as ``progress(done, total)`` after each frame is encoded.
        ambient_occlusion: darken creases and contact with the floor (screen-space ambient
            occlusion); about 5x slower per frame.
        legend: lines "key  value" in the upper-left corner (:func:`scene_legend`), followed by a
            "frame" line per frame: ``frame_labels[k]``, or "k / T-1 (t s)".
        frame_labels: T texts for the legend's frame line (e.g. to name start-protocol frames).

    Returns:
        The path written.

    Raises:
        InputError: bad tracks, fps, size, cameras or path. RenderError: no OpenGL for offscreen use.
    """
    path = _check_path(path_mp4, ".mp4")
    width, height = _check_size(size)
    width += width % 2
    height += height % 2
    _check_fps(fps)
    tracks = list(tracks)
    if not tracks or not all(isinstance(t, MeshTrack) for t in tracks):
        raise InputError("render_sequence needs a non-empty list of MeshTrack objects")
    counts = {t.num_frames for t in tracks if not t.static}
    if len(counts) > 1:
        raise InputError(f"animated mesh tracks have different frame counts {sorted(counts)}")
    n_frames = counts.pop() if counts else 1
    items = _items_from_tracks(tracks)
    if camera is None:
        cameras = follow_cameras(tracks, aspect=width / height, fps=fps)
    elif isinstance(camera, Camera):
        cameras = [camera]
    else:
        cameras = list(camera) if isinstance(camera, Sequence) else [camera]
        if len(cameras) != n_frames:
            raise InputError(f"camera: give one Camera or one per frame ({n_frames}), got {len(cameras)}")
    for cam in cameras:
        _check_camera(cam)
    if frame_labels is not None:
        frame_labels = [str(label) for label in frame_labels]
        if len(frame_labels) != n_frames:
            raise InputError(f"frame_labels: give one per frame ({n_frames}), got {len(frame_labels)}")

    def text(k: int) -> str | None:
        label = frame_labels[k] if frame_labels is not None else (frame_text(k, n_frames, fps) if legend else None)
        return _legend_text(title, legend, label)

    import imageio_ffmpeg

    scene = _Scene(items, (width, height), floor=floor, ambient_occlusion=ambient_occlusion)
    tmp = temp_path_beside(path)
    try:
        writer = imageio_ffmpeg.write_frames(
            str(tmp),
            (width, height),
            fps=float(fps),
            codec="libx264",
            pix_fmt_in="rgb24",
            pix_fmt_out="yuv420p",
            quality=None,
            macro_block_size=2,
            ffmpeg_log_level="error",
            # crf 18: visually lossless for flat-shaded renders; faststart: playable while loading.
            output_params=["-crf", "18", "-preset", "medium", "-movflags", "+faststart"],
        )
        writer.send(None)
        try:
            for i in range(n_frames):
                image = scene.draw(i, cameras[i if len(cameras) > 1 else 0], text(i))
                writer.send(np.ascontiguousarray(image))
                if progress is not None:
                    progress(i + 1, n_frames)
        finally:
            writer.close()
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    finally:
        scene.close()
    return path


def frame_text(frame: int, n_frames: int, fps: float) -> str:
    """The legend's frame line: "k / T-1 (t s)" of a sequence, "k" of a still."""
    if n_frames <= 1:
        return f"{frame}"
    return f"{frame} / {n_frames - 1}  ({frame / fps:.2f} s)"


def _legend_text(title: str | None, legend: Mapping[str, str] | None, frame_line: str | None) -> str | None:
    """The text block of the upper-left corner: the title, then "key  value" lines."""
    lines = [str(title)] if title else []
    rows = list((legend or {}).items()) + ([("frame", frame_line)] if frame_line is not None else [])
    width = max((len(str(k)) for k, _ in rows), default=0)
    lines += [f"{str(k):<{width}}  {v}" for k, v in rows]
    return "\n".join(lines) if lines else None


def _check_fps(fps: Any) -> None:
    if isinstance(fps, bool) or not isinstance(fps, (int, float, np.integer, np.floating)):
        raise InputError(f"fps must be a number, got {fps!r}")
    if not math.isfinite(fps) or fps <= 0:
        raise InputError(f"fps must be a positive number, got {fps}")


# --- scene ------------------------------------------------------------------------------------


class _Scene:
    """One offscreen plotter whose meshes, camera and legend are updated in place frame after frame."""

    def __init__(
        self,
        items: list[_Item],
        size: tuple[int, int],
        *,
        floor: bool,
        ambient_occlusion: bool,
    ) -> None:
        _prepare_headless()
        import pyvista as pv

        self._items = items
        self._size = size
        plotter = pv.Plotter(off_screen=True, window_size=list(size), lighting="light kit")
        self._plotter = plotter
        plotter.set_background(_BACKGROUND_BOTTOM, top=_BACKGROUND_TOP)
        if ambient_occlusion:
            # Screen-space AO is noisy without supersampling, and multisampling does not combine
            # with VTK's render passes: SSAA here (about 5x the cost of a plain frame).
            plotter.enable_ssao(radius=0.3, bias=0.005, kernel_size=64)
            plotter.enable_anti_aliasing("ssaa")
        else:
            # Multisampling: smooth silhouettes and floor tiles at a fraction of SSAA's cost.
            plotter.enable_anti_aliasing("msaa")

        self._polys = []
        for track, rgb in items:
            cells = np.hstack([np.full((len(track.faces), 1), 3, np.int64), track.faces]).reshape(-1)
            points, normals = _display_points(track, 0)
            poly = pv.PolyData(points, cells)
            poly.point_data["Normals"] = normals
            poly.point_data.active_normals_name = "Normals"
            style = dict(smooth_shading=False, ambient=0.18, diffuse=0.85, specular=0.12, specular_power=20.0)
            colors = track.frame_colors(0)
            if colors is None:
                actor = plotter.add_mesh(poly, color=rgb, **style)
            else:
                poly.point_data["rgb"] = _to_uint8(colors)
                actor = plotter.add_mesh(poly, scalars="rgb", rgb=True, **style)
            # Interpolate our per-frame vertex normals (pyvista's smooth_shading would compute
            # normals once, on a copy that does not follow the animation).
            actor.prop.interpolation = "phong"
            self._polys.append(poly)

        if floor:
            plotter.add_mesh(_floor_mesh(_frame_bounds(items, None)), scalars="rgb", rgb=True,
                             ambient=0.35, diffuse=0.7, specular=0.0)
        self._text = None

    def _legend(self, text: str | None) -> None:
        """Show ``text`` in the upper-left corner: monospaced, dark on a light translucent box."""
        if text is None:
            if self._text is not None:
                self._text.SetVisibility(False)
            return
        # One space of padding around the text inside its box.
        padded = "\n".join(f" {line} " for line in text.split("\n"))
        if self._text is None:
            width, height = self._size
            font = max(6, round(height / 72))
            actor = self._plotter.add_text(padded, position=(round(font * 0.8), height - round(font * 0.8)),
                                           font_size=font, color=(0.08, 0.08, 0.08), font="courier")
            prop = actor.GetTextProperty()
            prop.SetVerticalJustificationToTop()
            prop.SetJustificationToLeft()
            prop.SetBackgroundColor(1.0, 1.0, 1.0)
            prop.SetBackgroundOpacity(0.72)
            prop.SetLineSpacing(1.15)
            self._text = actor
        self._text.SetInput(padded)
        self._text.SetVisibility(True)

    def draw(self, frame: int, camera: Camera, text: str | None = None) -> np.ndarray:
        """Pose every mesh at ``frame``, look through ``camera``, show ``text`` in the corner, and
        return the image, shape (H, W, 3) uint8."""
        for (track, _), poly in zip(self._items, self._polys):
            if track.static and frame > 0:
                continue
            points, normals = _display_points(track, frame)
            poly.points = points
            poly.point_data["Normals"] = normals
            poly.point_data.active_normals_name = "Normals"
            colors = track.frame_colors(frame)
            if colors is not None and track.colors.ndim == 3:
                poly.point_data["rgb"] = _to_uint8(colors)
        cam = self._plotter.camera
        cam.position = camera.position
        cam.focal_point = camera.focal_point
        cam.up = camera.view_up
        cam.view_angle = camera.view_angle
        self._legend(text)
        # Near and far planes follow the moving meshes and the floor.
        self._plotter.renderer.ResetCameraClippingRange()
        self._plotter.render()
        image = self._plotter.screenshot(return_img=True)
        width, height = self._size
        if image.shape[:2] != (height, width):
            got = f"{image.shape[1]}x{image.shape[0]}"
            raise RenderError(f"the renderer returned a {got} image instead of {width}x{height}")
        return image[..., :3]

    def close(self) -> None:
        self._plotter.close()


def _display_points(track: MeshTrack, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """Points (float32) and vertex normals of a track at a frame as drawn: garments moved
    GARMENT_DISPLAY_OFFSET out along their normals."""
    points = np.asarray(track.frame(frame), dtype=np.float64)
    normals = _vertex_normals(points, track.faces)
    if track.role == "garment":
        points = points + GARMENT_DISPLAY_OFFSET * normals
    return points.astype(np.float32), normals


def _prepare_headless() -> None:
    """Pick VTK's offscreen render window when there is no display to talk to."""
    if sys.platform != "linux" or "VTK_DEFAULT_OPENGL_WINDOW" in os.environ:
        return
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return
    if _loadable("libEGL.so.1") and (_loadable("libEGL_mesa.so.0") or _loadable("libEGL_nvidia.so.0")):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"
    elif _loadable("libOSMesa.so.8") or _loadable("libOSMesa.so"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkOSOpenGLRenderWindow"
    else:
        raise RenderError(
            "offscreen rendering needs EGL (Debian: libegl1 libegl-mesa0 libgl1-mesa-dri) or OSMesa "
            "(libosmesa6); install them with apt-get, or run .ci/system-deps.sh of the simgen repository as root"
        )


def _loadable(name: str) -> bool:
    try:
        ctypes.CDLL(name)
    except OSError:
        return False
    return True


# --- inputs -----------------------------------------------------------------------------------


def _items_from_tracks(tracks: Sequence[MeshTrack]) -> list[_Item]:
    items = []
    garments = 0
    for track in tracks:
        if track.colors is not None:
            items.append((track, None))
        elif track.role == "garment":
            items.append((track, GARMENT_PALETTE[garments % len(GARMENT_PALETTE)]))
            garments += 1
        else:
            items.append((track, ROLE_COLORS[track.role]))
    return items


def _items_from_meshes(meshes: Sequence[MeshLike]) -> list[_Item]:
    if isinstance(meshes, MeshTrack):
        meshes = [meshes]
    elif isinstance(meshes, tuple) and len(meshes) in (2, 3) and np.ndim(meshes[0]) == 2:
        raise InputError("meshes must be a list of meshes: wrap a single (points, faces) tuple in [ ]")
    meshes = list(meshes)
    if not meshes:
        raise InputError("meshes must be a non-empty list of MeshTrack or (points, faces[, color]) entries")
    tracks: list[MeshTrack] = []
    fixed: dict[int, RGB] = {}
    for i, entry in enumerate(meshes):
        if isinstance(entry, MeshTrack):
            tracks.append(entry)
            continue
        if not isinstance(entry, (tuple, list)) or len(entry) not in (2, 3):
            raise InputError(f"mesh {i} must be a MeshTrack or a (points, faces[, color]) tuple")
        points, faces = entry[0], entry[1]
        color = entry[2] if len(entry) == 3 else None
        if np.ndim(points) != 2:
            raise InputError(f"mesh {i}: points must have shape (V, 3), got {np.shape(points)}")
        role = "body" if i == 0 else "garment"
        colors = None
        if isinstance(color, str):
            if color not in ROLE_COLORS:
                raise InputError(f"mesh {i}: color {color!r} is not a role name {sorted(ROLE_COLORS)}")
            role = color
        elif color is not None:
            arr = np.asarray(color, dtype=np.float64) if _numeric(color) else None
            if arr is not None and arr.shape == (3,):
                if not (np.isfinite(arr).all() and arr.min() >= 0 and arr.max() <= 1):
                    raise InputError(f"mesh {i}: color must be RGB in [0, 1], got {tuple(arr)}")
                fixed[i] = (float(arr[0]), float(arr[1]), float(arr[2]))
            elif arr is not None and arr.ndim == 2:
                colors = arr
            else:
                raise InputError(
                    f"mesh {i}: color must be an RGB triple, (V, 3) colours, a role name or None"
                )
        tracks.append(MeshTrack(f"mesh{i}", points, faces, colors=colors, role=role))
    items = _items_from_tracks(tracks)
    return [(track, fixed.get(i, rgb)) for i, (track, rgb) in enumerate(items)]


def _numeric(value: Any) -> bool:
    try:
        return np.asarray(value).dtype.kind in "fiu"
    except (TypeError, ValueError):
        return False


def _frame_bounds(items: list[_Item], frame: int | None) -> np.ndarray:
    """Bounds [m], shape (2, 3), of one frame of every mesh (of all frames when frame is None)."""
    if frame is None:
        return sequence_bounds([t for t, _ in items])
    pts = np.concatenate([t.frame(frame) for t, _ in items])
    return np.stack([pts.min(axis=0), pts.max(axis=0)]).astype(np.float64)


def _check_path(path: str | os.PathLike, suffix: str) -> Path:
    path = Path(path)
    if path.suffix.lower() != suffix:
        raise InputError(f"output {str(path)!r} must end in {suffix}")
    if path.is_dir():
        raise InputError(f"output {str(path)!r} is a folder")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def _check_size(size: Any) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in size)
        exact = all(float(v) == int(v) for v in size)
    except (TypeError, ValueError):
        raise InputError(f"size must be (width, height) in pixels, got {size!r}") from None
    if not exact or not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise InputError(f"size must be whole pixels in [16, 8192], got {size!r}")
    return width, height


def _check_camera(camera: Any) -> None:
    if not isinstance(camera, Camera):
        raise InputError(f"camera must be a simgen.io.render.Camera, got {type(camera).__name__}")
    values = np.array(
        [*camera.position, *camera.focal_point, *camera.view_up, camera.view_angle], dtype=np.float64
    )
    if not np.isfinite(values).all() or np.allclose(camera.position, camera.focal_point):
        raise InputError("camera position, focal point and view up must be finite, position != focal point")




# --- geometry ---------------------------------------------------------------------------------


def _vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, shape (V, 3) float32 (smooth shading of moving meshes)."""
    p = np.asarray(points, dtype=np.float64)
    tri = p[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    n = np.zeros_like(p)
    idx = faces.reshape(-1)
    for axis in range(3):
        n[:, axis] = np.bincount(idx, weights=np.repeat(face_n[:, axis], 3), minlength=len(p))
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 0, n / np.maximum(length, 1e-30), np.array([0.0, 1.0, 0.0]))
    return n.astype(np.float32)


def _to_uint8(colors: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(colors) * 255.0), 0, 255).astype(np.uint8)


def _floor_mesh(bounds: np.ndarray) -> Any:
    """A checker plane at y = 0 under the scene, tiles aligned to the world grid."""
    import pyvista as pv

    extent = float(np.max(bounds[1, [0, 2]] - bounds[0, [0, 2]]))
    half = max(_MIN_FLOOR_HALF_SIZE, 2.0 * extent)
    n_tiles = 2 * math.ceil(half / _FLOOR_TILE)
    center = np.round(bounds.mean(axis=0) / _FLOOR_TILE) * _FLOOR_TILE
    size = n_tiles * _FLOOR_TILE
    # 1 mm below y = 0: feet resting on the floor would otherwise z-fight with it.
    plane = pv.Plane(
        center=(center[0], -1e-3, center[2]),
        direction=(0.0, 1.0, 0.0),
        i_size=size,
        j_size=size,
        i_resolution=n_tiles,
        j_resolution=n_tiles,
    )
    cc = plane.cell_centers().points
    parity = (np.floor(cc[:, 0] / _FLOOR_TILE) + np.floor(cc[:, 2] / _FLOOR_TILE)).astype(np.int64) % 2
    plane.cell_data["rgb"] = _to_uint8(np.asarray(_FLOOR_COLORS)[parity])
    return plane
