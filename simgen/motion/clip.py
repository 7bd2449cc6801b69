"""MotionClip: a body motion as SMPL joint rotations and root translation sampled at a fixed rate."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from simgen.errors import InputError

__all__ = ["MotionClip"]


@dataclass(eq=False)
class MotionClip:
    """A motion clip in SMPL's 24-joint layout, Y-up.

    name: identifier (library name or import name).
    fps: frames per second [1/s], > 0.
    poses: axis-angle joint rotations [rad], shape (T, 24, 3), SMPL joint order (pose[:, 0] is the
      global orientation).
    trans: root translation [m], shape (T, 3), with SMPL's meaning:
      posed vertex = R (v - J0) + J0 + trans, J0 the rest pelvis joint.
    meta: provenance and extras (source file, attribution, split, description, ...), JSON-serialisable.
    """

    name: str
    fps: float
    poses: np.ndarray
    trans: np.ndarray
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        where = f"motion {self.name!r}"
        try:
            self.fps = float(self.fps)
        except (TypeError, ValueError):
            raise InputError(f"{where}: field 'fps' must be a number, got {self.fps!r}") from None
        if not np.isfinite(self.fps) or self.fps <= 0.0:
            raise InputError(f"{where}: field 'fps' must be positive, got {self.fps}")
        self.poses = np.ascontiguousarray(self.poses, dtype=np.float64)
        self.trans = np.ascontiguousarray(self.trans, dtype=np.float64)
        if self.poses.ndim != 3 or self.poses.shape[1:] != (24, 3) or self.poses.shape[0] < 1:
            raise InputError(f"{where}: field 'poses' must have shape (T, 24, 3) with T >= 1, got {self.poses.shape}")
        if self.trans.shape != (self.poses.shape[0], 3):
            raise InputError(f"{where}: field 'trans' must have shape ({self.poses.shape[0]}, 3), "
                             f"got {self.trans.shape}")
        if not (np.all(np.isfinite(self.poses)) and np.all(np.isfinite(self.trans))):
            raise InputError(f"{where}: fields 'poses'/'trans' contain NaN or inf")

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])

    @property
    def duration(self) -> float:
        """Time from the first to the last frame [s]."""
        return (self.num_frames - 1) / self.fps

    @property
    def times(self) -> np.ndarray:
        """Frame times [s], shape (T,)."""
        return np.arange(self.num_frames) / self.fps

    def __repr__(self) -> str:
        return f"MotionClip({self.name!r}, fps={self.fps:g}, frames={self.num_frames}, {self.duration:.2f} s)"
