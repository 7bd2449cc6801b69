"""LBS preview of a garment on a moving body: the linear-skinning baseline, no physics.

The garment's rest vertices (on the template body) are carried to the shaped rest body by the
body's shape blendshape diffused to the garment (thesis eq. 6.5,
:func:`simgen.garment.skinning.shape_offsets`), then posed with the garment's skinning weights by
the shaped body's skinning transforms of every frame (:func:`simgen.garment.skinning.lbs`). The
closest-point offset (barycentric at the closest body point) is available with
``shape_method="closest"``, but it jumps where the closest body point does (between the legs,
under the arms) and tears garments apart as the body grows: single edges stretch up to 2x on the
T-shirt and 5.8x on the dress at betas of +-2, against at most 1.6x diffused. With betas = 0 this
is exactly the thesis's LBS baseline: the template garment skinned with the body's pose.
Pose-dependent body correctives do not move the garment.

Outputs, in OUT_DIR: NAME_CLIP.usdc (body and garment as time-sampled meshes, checked with
``validate_usd``), NAME_CLIP.png (the middle frame) and NAME_CLIP.mp4 (every frame).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from simgen.errors import InputError

__all__ = ["preview_garment", "joint_colors", "render_skin_weights", "JOINT_PALETTE"]


def _palette() -> np.ndarray:
    """24 distinguishable RGB colours, one per SMPL joint: the spine warm (red to yellow), the
    left limbs greens and oranges, the right limbs blues and teals, darker towards the extremities,
    so that a left/right split and every joint boundary along a limb show."""
    from simgen.body.model import SMPL_JOINT_NAMES

    colors = {
        "pelvis": (0.80, 0.25, 0.25), "spine1": (0.95, 0.55, 0.20), "spine2": (0.95, 0.80, 0.25),
        "spine3": (0.80, 0.90, 0.35), "neck": (0.60, 0.40, 0.80), "head": (0.90, 0.60, 0.85),
        "left_hip": (0.25, 0.65, 0.30), "left_knee": (0.55, 0.85, 0.45), "left_ankle": (0.10, 0.40, 0.15),
        "left_foot": (0.70, 0.90, 0.65), "right_hip": (0.20, 0.45, 0.80), "right_knee": (0.50, 0.75, 0.95),
        "right_ankle": (0.10, 0.20, 0.55), "right_foot": (0.75, 0.85, 1.00),
        "left_collar": (0.60, 0.30, 0.15), "left_shoulder": (0.95, 0.45, 0.10), "left_elbow": (1.00, 0.70, 0.45),
        "left_wrist": (0.70, 0.20, 0.10), "left_hand": (1.00, 0.85, 0.70),
        "right_collar": (0.35, 0.25, 0.55), "right_shoulder": (0.15, 0.65, 0.65), "right_elbow": (0.55, 0.90, 0.85),
        "right_wrist": (0.05, 0.40, 0.40), "right_hand": (0.75, 0.95, 0.95),
    }
    return np.array([colors[name] for name in SMPL_JOINT_NAMES], dtype=np.float64)


#: RGB in [0, 1] per SMPL joint, shape (24, 3), used by :func:`joint_colors`.
JOINT_PALETTE = _palette()


def joint_colors(skin_weights, *, mode: str = "dominant") -> np.ndarray:
    """Per-vertex colours (V, 3) in [0, 1] showing skinning weights (V, 24).

    mode "dominant": the colour of the joint with the largest weight; "blend": the weighted mean of
    the joints' colours (shows how smoothly the weights change).
    """
    w = np.asarray(skin_weights, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 24:
        raise InputError(f"skin_weights must have shape (V, 24), got {w.shape}")
    if mode == "dominant":
        return JOINT_PALETTE[np.argmax(w, axis=1)]
    if mode == "blend":
        return np.clip(w @ JOINT_PALETTE / np.maximum(w.sum(axis=1, keepdims=True), 1e-12), 0.0, 1.0)
    raise InputError(f"mode must be 'dominant' or 'blend', got {mode!r}")


def render_skin_weights(garment, body, path_png, *, mode: str = "dominant", size: tuple[int, int] = (1280, 720),
                        azimuth: float = 30.0) -> Path:
    """Render the garment on the template body in rest pose, coloured by its skinning weights.

    The body is drawn in its neutral colour; mode as in :func:`joint_colors`; the view is
    :func:`simgen.io.render.follow_cameras`' turned ``azimuth`` deg. Returns the PNG path.
    """
    from simgen.io.render import follow_cameras, render_frame
    from simgen.io.usd import MeshTrack

    tracks = [MeshTrack("body", body.v_template, body.faces, role="body"),
              MeshTrack("garment", garment.vertices, garment.faces,
                        colors=joint_colors(garment.skin_weights, mode=mode), role="garment")]
    cam = follow_cameras(tracks, aspect=size[0] / size[1], azimuth=azimuth)[0]
    return render_frame(path_png, tracks, camera=cam, size=size,
                        title=f"{garment.name}: skinning weights ({mode} joint)")


def _prim_name(text: str) -> str:
    out = "".join(c if c.isalnum() or c == "_" else "_" for c in text)
    return out if out and not out[0].isdigit() else f"_{out}"


def preview_garment(garment, body, clip, *, out_dir, betas=None, video: bool = True,
                    frames: int | Sequence[int] | None = None, progress: Callable[[int, int], None] | None = None,
                    size: tuple[int, int] = (1280, 720), color_by_joint: bool = False,
                    shape_method: str = "diffused") -> dict[str, Path]:
    """Write the LBS preview of a garment on a body following a motion clip.

    Args:
        garment: a :class:`~simgen.garment.Garment`, or a garment name looked up with
            :func:`simgen.garment.load_garment` for this body.
        body: the :class:`~simgen.body.BodyModel`; a garment made for another body is refused.
        clip: a :class:`~simgen.motion.MotionClip`, or the name of a library clip.
        out_dir: output folder (created).
        betas: body shape, (B',) (zero-padded); None: the template shape.
        video: also render NAME_CLIP.mp4 (the slow part: ~0.1-0.3 s per frame on a CPU).
        frames: None (all frames), an int n (the first n frames) or a sequence of frame indices;
            every k-th frame (a regular stride) is written at the clip's fps / k, so the preview
            keeps the clip's speed; other selections at the clip's fps.
        progress: called as progress(done, total) after each rendered video frame.
        size: video and picture size (width, height) in pixels. The camera follows the body
            (:func:`simgen.io.render.follow_cameras`); a legend names garment, shape, motion and
            frame; the picture is the middle frame.
        color_by_joint: colour the garment by its dominant skinning joint instead of one colour.
        shape_method: "diffused" (default) or "closest" transfer of the body's shape offset to
            the garment (see the module docstring).

    Returns:
        {"usd": Path, "png": Path, "video": Path (when video)} in out_dir, files named
        NAME_CLIP.usdc / .png / .mp4.

    Raises:
        InputError: bad garment, clip, betas or frames. RuntimeError: the written USD fails
        validation (a bug, not bad input).
    """
    from simgen.assets import body_asset_id
    from simgen.garment.garment import Garment
    from simgen.garment.library import check_garment_body, load_garment
    from simgen.garment.skinning import lbs, shape_offsets
    from simgen.io.render import render_frame, render_sequence, scene_legend
    from simgen.io.usd import MeshTrack, validate_usd, write_usd
    from simgen.motion import MotionClip, load_motion

    if isinstance(garment, str):
        garment = load_garment(garment, body=body)
    if not isinstance(garment, Garment):
        raise InputError(f"garment must be a Garment or a garment name, got {type(garment).__name__}")
    check_garment_body(garment, body)
    if isinstance(clip, str):
        clip = load_motion(clip, body_id=body_asset_id(body))
    if not isinstance(clip, MotionClip):
        raise InputError(f"clip must be a MotionClip or a motion name, got {type(clip).__name__}")

    try:
        width, height = (int(x) for x in size)
    except (TypeError, ValueError):
        raise InputError(f"size must be (width, height) in pixels, got {size!r}") from None
    if not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise InputError(f"size must be (width, height) with each in [16, 8192] pixels, got {size!r}")
    T = clip.num_frames
    if frames is None:
        idx = np.arange(T)
    elif isinstance(frames, (int, np.integer)) and not isinstance(frames, bool):
        if not 1 <= frames <= T:
            raise InputError(f"frames must be between 1 and the clip's {T} frames, got {frames}")
        idx = np.arange(int(frames))
    else:
        try:
            idx = np.asarray(list(frames), dtype=np.int64)
        except (TypeError, ValueError):
            raise InputError(f"frames must be None, a count or a list of frame indices, got {frames!r}") from None
        if idx.size == 0 or idx.min() < 0 or idx.max() >= T:
            raise InputError(f"frames must be indices in [0, {T - 1}] of clip {clip.name!r}, got {frames!r}")
    b = body.check_betas(np.zeros(body.num_betas) if betas is None else betas)
    if b.shape[0] != 1:
        raise InputError(f"betas must be one shape vector (B,), got shape {np.shape(betas)}")

    skin = garment.metadata.get("skinning")
    skin_method = skin.get("method") if isinstance(skin, dict) else skin
    rest = garment.vertices + shape_offsets(garment.vertices, body, b, method=shape_method)[0]
    out = body.forward_sequence(b[0], clip.poses[idx], clip.trans[idx])
    garment_points = lbs(rest, garment.skin_weights, out.transforms)

    out_dir = Path(out_dir)
    stem = f"{garment.name}_{clip.name}"
    colors = None
    if color_by_joint:
        colors = joint_colors(garment.skin_weights)
    tracks = [
        MeshTrack("body", out.vertices, body.faces, role="body"),
        MeshTrack(_prim_name(garment.name), garment_points, garment.faces, colors=colors, role="garment"),
    ]
    # Every k-th frame plays at fps / k, so the preview keeps the clip's speed.
    steps = np.diff(idx)
    fps = clip.fps / float(steps[0]) if len(steps) and steps[0] > 0 and np.all(steps == steps[0]) else clip.fps
    usd_path = write_usd(out_dir / f"{stem}.usdc", tracks, fps=fps, metadata={
        "kind": "lbs_preview",
        "garment": garment.name,
        "body_id": body_asset_id(body),
        "body_hash": body.hash,
        "motion": clip.name,
        "frames": [int(i) for i in idx],
        "betas": [float(x) for x in b[0]],
        "skinning": str(skin_method or "unknown"),
        "shape_offsets": shape_method,
    })
    errors = validate_usd(usd_path)
    if errors:
        raise RuntimeError(f"{usd_path}: the written USD fails validation: {errors[0]}")
    result = {"usd": usd_path}

    legend = scene_legend(garment=f"{garment.name} (LBS, no physics)", betas=b[0], motion=clip.name)
    labels = [f"{k} / {len(idx) - 1}  (clip frame {i})" for k, i in enumerate(idx)]
    result["png"] = render_frame(out_dir / f"{stem}.png", tracks, size=(width, height), frame=len(idx) // 2,
                                 legend=legend, frame_label=labels[len(idx) // 2], fps=fps)
    if video:
        result["video"] = render_sequence(out_dir / f"{stem}.mp4", tracks, fps=fps, size=(width, height),
                                          legend=legend, frame_labels=labels, progress=progress)
    return result
