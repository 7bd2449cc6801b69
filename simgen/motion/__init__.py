"""Body motions: MotionClip, loaders (AMASS, BVH, simgen .npz), operations and the motion library.

Clips use SMPL's 24 joints (axis-angle, shape (T, 24, 3)) and root translation (T, 3) [m], Y-up,
on the floor y = 0 (docs/architecture.md, "Motions").
"""

from simgen.motion.amass import load_amass
from simgen.motion.bvh import BvhMappingWarning, load_bvh
from simgen.motion.clearance import arm_torso_penetration, separate_arms
from simgen.motion.clip import MotionClip
from simgen.motion.library import import_motion, library_split, list_motions, load_motion
from simgen.motion.motion_file import load_motion_file, save_motion
from simgen.motion.ops import (
    apply_world_rotation,
    blend_from_rest,
    concatenate,
    mirror,
    pose_at,
    poses_at,
    put_on_floor,
    quats_at,
    resample,
    trim,
)

__all__ = [
    "MotionClip",
    "separate_arms",
    "arm_torso_penetration",
    "load_amass",
    "load_bvh",
    "BvhMappingWarning",
    "load_motion_file",
    "save_motion",
    "list_motions",
    "load_motion",
    "library_split",
    "import_motion",
    "resample",
    "pose_at",
    "poses_at",
    "quats_at",
    "mirror",
    "blend_from_rest",
    "apply_world_rotation",
    "put_on_floor",
    "trim",
    "concatenate",
]
