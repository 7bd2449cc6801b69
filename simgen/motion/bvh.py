"""BVH motion capture files retargeted onto an SMPL-format body.

Parsing: the HIERARCHY (joints, offsets, channels in any order, End Sites) and MOTION sections of a
BVH file; rotation channels are intrinsic Euler angles in degrees applied in the listed order
(R = R_1 R_2 R_3), position channels replace the joint's offset along their axis.

Joint mapping: BVH joint names are normalised (namespace before ':' dropped, a 3ds Max 'Bip01'
prefix dropped, lower case, only letters and digits) and matched against name stems for the
limbs, pelvis and head; this covers the CMU "3dsmax-friendly" skeleton of ../shared/mocap (Hips,
LeftHip, LeftKnee, LeftAnkle, LeftToe, LeftCollar, LeftShoulder, LeftElbow, LeftWrist, LFingers,
Head), the CMU "MotionBuilder-friendly" and Mixamo skeletons (LeftUpLeg, LeftLeg, LeftFoot,
LeftToeBase, LeftShoulder as clavicle, LeftArm, LeftForeArm, LeftHand, ...), Daz (lThigh, lShin,
lFoot, lCollar, lShldr, lForeArm, lHand), Unreal (thigh_l, calf_l, clavicle_l, ...), 3ds Max biped
and SMPL's own names. The torso is mapped by structure rather than by name (names disagree across
skeletons: Mixamo's 'Spine1' is CMU-MB's 'Spine'): spine3 is the lowest common ancestor of the head
and the two arms, spine1 the first and spine2 the last joint between the pelvis and spine3, neck the
parent of the head. For the CMU files this gives spine1 <- lowerback, spine2 <- Chest, spine3 <-
Chest2, neck <- Neck (the joint at shoulder height; 'lowerneck' sits at the top of the chest) and
left_wrist <- LeftWrist, left_hand <- LFingers ('lhand', the palm, is folded into the wrist).
Unmapped BVH joints are reported in a :class:`BvhMappingWarning`; their rotations reach the body
through the world rotations of the mapped joints below them.

Retargeting by world rotations: the BVH's rest pose (all channels zero) is generally not SMPL's
T-pose, so each mapped SMPL joint j gets a constant rest alignment A_j, the rotation that takes
SMPL's rest bone directions (from the body's rest joints) to the BVH's rest bone directions. With
Q_b(t) the world rotation of the BVH joint b mapped to j (identity in the BVH rest pose), the SMPL
joint's world rotation is G_j(t) = D_j(t) Q_b(t) A_j, where, for a joint with one bone, D_j(t) is the
smallest rotation that makes the SMPL bone point exactly along the BVH bone in that frame (it absorbs
unmapped joints inside the BVH bone, e.g. CMU's 'lhand'); joints with several bones (pelvis, spine3)
take D = I and a rest alignment that matches the main bone exactly (spine for the pelvis, neck for
spine3) and the others (hips, shoulders) best about it. SMPL's leaf joints (head, toes, hands) have
no child joint to give their segment a direction; since SMPL-format bodies rest in a T-pose, their
segments are taken to point up (head), forward (toes) and along the wrist-hand line (hands), and
are aligned with the BVH joint's own segment (towards its children / End Site). A mapped joint
with no usable segment takes its BVH rotation relative to the BVH frame of its parent's bone,
expressed in the parent's alignment. SMPL local rotations follow as G_parent^T G_j; unmapped SMPL joints
stay at rest relative to their parent.

Collars whose BVH joint sits on its parent (CMU's LeftCollar on Chest2: a clavicle that starts on the
spine) are the exception: they take the BVH clavicle's rotation from its rest, G_j(t) = Q_b(t), without
bone alignment. CMU's clavicle bone rises 26 degrees from the chest's midline to the shoulder, the open
body's falls 8 degrees from beside the neck: the two bones pivot at different points and their
directions do not compare. Matching them would shrug SMPL's shoulders by the difference in every frame
(34 degrees on the CMU clips: a skinned shoulder squeezed up against the neck, on which no shirt stays).
Skeletons whose clavicle starts beside the spine (Mixamo, Daz, Unreal, SMPL) keep the alignment. The upper arm is
still aligned to the BVH's by direction, so the arms point where the capture's do.

Root translation: the midpoint of SMPL's two hip joints follows the midpoint of the BVH's hip joints
(the pelvis joint itself when the hips are not mapped), scaled by the ratio of the body's leg length
(hip-knee-ankle, averaged over both legs) to the BVH skeleton's; with no legs mapped, the ratio of
skeleton heights. Anchoring the leg roots rather than the pelvis joint keeps the feet where the
BVH's feet are although the pelvis-to-hip offsets of the two skeletons differ. The ratio also makes
the loader independent of the file's length unit (metres, centimetres or inches). A BVH whose rest
skeleton stands along +Z is turned Y-up first.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from simgen.body.model import NUM_JOINTS, SMPL_JOINT_NAMES, SMPL_PARENTS, BodyModel
from simgen.errors import InputError
from simgen.motion.clip import MotionClip
from simgen.motion.ops import LOADER_MAX_SINK, put_on_floor, resample
from simgen.rotations import axis_angle_to_matrix, euler_to_matrix, matrix_to_axis_angle

__all__ = ["load_bvh", "parse_bvh", "map_bvh_joints", "BvhSkeleton", "BvhMappingWarning", "DEFAULT_BVH_FPS"]

DEFAULT_BVH_FPS = 30.0

_J = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
_SPINE_CHAIN = {_J["spine1"], _J["spine2"], _J["spine3"], _J["neck"], _J["head"]}
# Joints retargeted by their rotation from rest instead of by bone direction when their BVH joint sits
# on its parent (module docstring).
_COLLARS = (_J["left_collar"], _J["right_collar"])


class BvhMappingWarning(UserWarning):
    """Some BVH joints have no SMPL counterpart (listed in the message)."""


# ------------------------------------------------------------------------------------------- parsing
@dataclass
class BvhSkeleton:
    """A parsed BVH file.

    names: joint names as written; parents, int shape (J,), -1 for the root, parents before children;
    offsets: rest offsets from the parent [file units], shape (J, 3); channels: per joint, the channel
    names in file order ('Xposition', 'Zrotation', ...); channel_start: first column of each joint's
    channels in a motion row, shape (J,); end_sites: (joint index, offset (3,)) pairs;
    frame_time [s]; motion: channel values, shape (F, C) (degrees for rotations).
    """

    names: list[str]
    parents: np.ndarray
    offsets: np.ndarray
    channels: list[list[str]]
    channel_start: np.ndarray
    end_sites: list[tuple[int, np.ndarray]]
    frame_time: float
    motion: np.ndarray
    path: Path = field(default_factory=lambda: Path("<bvh>"))

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def fps(self) -> float:
        """Frame rate [1/s]; 1/frame_time snapped to an integer when the file's rounding of the frame
        time explains the difference (0.008333 s -> 120 fps)."""
        fps = 1.0 / self.frame_time
        whole = round(fps)
        if whole > 0 and abs(1.0 / whole - self.frame_time) <= 1e-4 * self.frame_time:
            return float(whole)
        return fps

    def children(self, j: int) -> list[int]:
        return [int(c) for c in np.flatnonzero(self.parents == j)]

    def rest_positions(self) -> np.ndarray:
        """World joint positions in the rest pose (all channels zero) [file units], shape (J, 3)."""
        P = np.zeros((self.num_joints, 3))
        for j in range(self.num_joints):
            p = self.parents[j]
            P[j] = self.offsets[j] if p < 0 else P[p] + self.offsets[j]
        return P

    def forward(self) -> tuple[np.ndarray, np.ndarray]:
        """World rotations, shape (F, J, 3, 3), and positions [file units], shape (F, J, 3), per frame.

        World rotations are relative to the rest pose (identity there).
        """
        F, Jn = self.num_frames, self.num_joints
        Q = np.empty((F, Jn, 3, 3))
        P = np.empty((F, Jn, 3))
        for j in range(Jn):
            cols = self.motion[:, self.channel_start[j] : self.channel_start[j] + len(self.channels[j])]
            t = np.broadcast_to(self.offsets[j], (F, 3)).copy()
            order, angles = "", []
            for k, ch in enumerate(self.channels[j]):
                axis = "XYZ".index(ch[0].upper())
                if ch[1:].lower() == "position":
                    t[:, axis] = cols[:, k]
                else:
                    order += ch[0].upper()
                    angles.append(cols[:, k])
            R = euler_to_matrix(np.radians(np.stack(angles, axis=-1)), order) if order else np.eye(3)
            p = self.parents[j]
            if p < 0:
                Q[:, j] = R
                P[:, j] = t
            else:
                Q[:, j] = Q[:, p] @ R
                P[:, j] = P[:, p] + np.einsum("fab,fb->fa", Q[:, p], t)
        return Q, P


_CHANNEL = re.compile(r"^[XYZxyz](position|rotation)$", re.IGNORECASE)


def _parse_float(tok: str, path: Path, what: str) -> float:
    try:
        v = float(tok)
    except ValueError:
        raise InputError(f"BVH file {path}: {what} has the non-number {tok[:20]!r}") from None
    if not np.isfinite(v):
        raise InputError(f"BVH file {path}: {what} is not finite ({tok[:20]!r})")
    return v


def parse_bvh(path: str | Path) -> BvhSkeleton:
    """Read a BVH file. Raises InputError naming the file and the section at fault."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"BVH file {path} does not exist")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"BVH file {path} is not a text file (invalid UTF-8)") from None
    m = re.search(r"\bMOTION\b", text)
    if not text.lstrip().startswith("HIERARCHY") or m is None:
        raise InputError(f"BVH file {path} lacks the HIERARCHY or MOTION section")
    tokens = re.findall(r"[{}]|[^\s{}]+", text[: m.start()])

    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray] = []
    channels: list[list[str]] = []
    end_sites: list[tuple[int, np.ndarray]] = []
    stack: list[int] = []  # open blocks: joint index, or -2 - parent for an End Site
    i, n = 1, len(tokens)
    seen_root = False

    def need(k: int, what: str) -> None:
        if i + k > n:
            raise InputError(f"BVH file {path}: HIERARCHY ends inside {what}")

    while i < n:
        tok = tokens[i]
        if tok in ("ROOT", "JOINT"):
            if (tok == "ROOT") == bool(stack) or (tok == "ROOT" and seen_root):
                raise InputError(f"BVH file {path}: HIERARCHY has a misplaced {tok} (one ROOT, JOINTs inside it)")
            if stack and stack[-1] < 0:
                raise InputError(f"BVH file {path}: HIERARCHY has a JOINT inside an End Site")
            seen_root = True
            j = i + 1
            while j < n and tokens[j] != "{":
                j += 1
            if j >= n or j == i + 1:
                raise InputError(f"BVH file {path}: HIERARCHY has a {tok} without a name or '{{'")
            names.append(" ".join(tokens[i + 1 : j]))
            parents.append(stack[-1] if stack else -1)
            offsets.append(np.zeros(3))
            channels.append([])
            stack.append(len(names) - 1)
            i = j + 1
        elif tok == "End":
            need(3, "an End Site")
            if tokens[i + 1] != "Site" or tokens[i + 2] != "{" or not stack or stack[-1] < 0:
                raise InputError(f"BVH file {path}: HIERARCHY has a malformed End Site")
            end_sites.append((stack[-1], np.zeros(3)))
            stack.append(-2 - stack[-1])
            i += 3
        elif tok == "OFFSET":
            need(4, "an OFFSET")
            if not stack:
                raise InputError(f"BVH file {path}: HIERARCHY has an OFFSET outside a joint")
            off = np.array([_parse_float(t, path, "an OFFSET") for t in tokens[i + 1 : i + 4]])
            if stack[-1] >= 0:
                offsets[stack[-1]] = off
            else:
                end_sites[-1] = (end_sites[-1][0], off)
            i += 4
        elif tok == "CHANNELS":
            need(2, "CHANNELS")
            if not stack or stack[-1] < 0:
                raise InputError(f"BVH file {path}: HIERARCHY has CHANNELS outside a joint")
            try:
                k = int(tokens[i + 1])
            except ValueError:
                raise InputError(f"BVH file {path}: CHANNELS count {tokens[i + 1][:20]!r} is not an integer") from None
            if not 0 <= k <= 6:
                raise InputError(f"BVH file {path}: CHANNELS count {k} is not between 0 and 6")
            need(2 + k, "CHANNELS")
            chans = tokens[i + 2 : i + 2 + k]
            bad = [c for c in chans if not _CHANNEL.match(c)]
            if bad:
                raise InputError(f"BVH file {path}: unknown channel {bad[0][:20]!r} of joint {names[stack[-1]]!r}")
            channels[stack[-1]] = chans
            i += 2 + k
        elif tok == "}":
            if not stack:
                raise InputError(f"BVH file {path}: HIERARCHY has an unmatched '}}'")
            stack.pop()
            i += 1
        else:
            raise InputError(f"BVH file {path}: unexpected token {tok[:20]!r} in HIERARCHY")
    if stack or not names:
        raise InputError(f"BVH file {path}: HIERARCHY is incomplete (unclosed '{{' or no ROOT)")

    motion_text = text[m.end():]
    mf = re.match(r"\s*Frames:\s*(\S+)\s*Frame\s+Time:\s*(\S+)", motion_text)
    if mf is None:
        raise InputError(f"BVH file {path}: MOTION section lacks 'Frames:' and 'Frame Time:'")
    try:
        num_frames = int(mf.group(1))
    except ValueError:
        raise InputError(f"BVH file {path}: field 'Frames' is not an integer ({mf.group(1)[:20]!r})") from None
    frame_time = _parse_float(mf.group(2), path, "field 'Frame Time'")
    if frame_time <= 0.0:
        raise InputError(f"BVH file {path}: field 'Frame Time' must be positive, got {frame_time}")
    if num_frames < 1:
        raise InputError(f"BVH file {path}: field 'Frames' must be at least 1, got {num_frames}")
    counts = [len(c) for c in channels]
    C = int(sum(counts))
    if C == 0:
        raise InputError(f"BVH file {path}: HIERARCHY declares no CHANNELS")
    try:
        values = np.array(motion_text[mf.end():].split(), dtype=np.float64)
    except ValueError:
        raise InputError(f"BVH file {path}: MOTION data contains a non-number") from None
    if values.size != num_frames * C:
        raise InputError(f"BVH file {path}: MOTION has {values.size} values but 'Frames' {num_frames} x "
                         f"{C} channels needs {num_frames * C}")
    if not np.all(np.isfinite(values)):
        raise InputError(f"BVH file {path}: MOTION data contains NaN or inf")
    return BvhSkeleton(
        names=names,
        parents=np.array(parents, dtype=np.int64),
        offsets=np.array(offsets, dtype=np.float64).reshape(-1, 3),
        channels=channels,
        channel_start=np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64),
        end_sites=end_sites,
        frame_time=frame_time,
        motion=values.reshape(num_frames, C),
        path=path,
    )


# ------------------------------------------------------------------------------------------- mapping
# Name stems per left-side SMPL joint, in priority order; each stem is tried as left+stem, l+stem,
# stem+left, stem+l (and the same with right/r). The collar is looked for before the shoulder, so
# 'LeftShoulder' is the clavicle where no 'LeftCollar' exists (Mixamo) and the upper arm otherwise
# (CMU); 'LeftFoot' is the ankle where no 'LeftAnkle' exists.
_SIDE_STEMS: dict[str, tuple[str, ...]] = {
    "hip": ("hip", "upleg", "thigh", "upperleg"),
    "knee": ("knee", "leg", "shin", "calf", "lowerleg"),
    "ankle": ("ankle", "foot"),
    "foot": ("toebase", "toe", "toes", "ball", "toe0", "foot"),
    "collar": ("collar", "clavicle", "shoulder"),
    "shoulder": ("arm", "shldr", "upperarm", "shoulder"),
    "elbow": ("elbow", "forearm", "lowerarm"),
    "wrist": ("wrist", "hand"),
    "hand": ("fingers", "fingerbase", "handmiddle1", "mid1", "middle1", "middle01", "handindex1", "index1",
             "hand"),
}
_PELVIS_NAMES = ("hips", "hip", "pelvis", "root")
_HEAD_NAMES = ("head",)


def _normalise(name: str) -> str:
    name = name.rsplit(":", 1)[-1].lower()
    name = re.sub(r"[^a-z0-9]", "", name)
    return re.sub(r"^bip0*1", "", name)


def _lca(parents: np.ndarray, nodes: list[int]) -> int:
    """Lowest common ancestor (a node counts as its own ancestor) of BVH joints."""
    def chain(j: int) -> list[int]:
        out = []
        while j >= 0:
            out.append(j)
            j = int(parents[j])
        return out[::-1]

    chains = [chain(j) for j in nodes]
    k = 0
    while all(len(c) > k for c in chains) and len({c[k] for c in chains}) == 1:
        k += 1
    return chains[0][k - 1] if k else -1


def _is_ancestor(parents: np.ndarray, a: int, b: int) -> bool:
    """True when BVH joint a is a strict ancestor of b."""
    j = int(parents[b])
    while j >= 0:
        if j == a:
            return True
        j = int(parents[j])
    return False


def map_bvh_joints(skel: BvhSkeleton, joint_map: dict[str, str | None] | None = None) -> dict[int, int]:
    """SMPL joint index -> BVH joint index for every SMPL joint that has a counterpart.

    joint_map: optional {BVH joint name: SMPL joint name, or None to keep it unmapped}; its entries
    override the automatic rules (module docstring), which fill in the other joints. Mappings that
    contradict the SMPL tree (a joint not below its mapped SMPL ancestor's joint) are dropped.
    Raises InputError when nothing can be mapped.
    """
    where = f"BVH file {skel.path}"
    by_norm: dict[str, int] = {}
    for j, nm in enumerate(skel.names):
        by_norm.setdefault(_normalise(nm), j)
    mapping: dict[int, int] = {}
    excluded: set[int] = set()
    if joint_map:
        index = {nm: j for j, nm in enumerate(skel.names)}
        for bname, sname in joint_map.items():
            if bname not in index:
                raise InputError(f"{where}: joint_map names the joint {bname!r}, which the file does not have")
            if sname is None:
                excluded.add(index[bname])
                continue
            if sname not in _J:
                raise InputError(f"{where}: joint_map maps {bname!r} to {sname!r}, which is not an SMPL joint name")
            if _J[sname] in mapping:
                raise InputError(f"{where}: joint_map maps two joints to the SMPL joint {sname!r}")
            mapping[_J[sname]] = index[bname]
            excluded.add(index[bname])
    taken = set(excluded) | set(mapping.values())

    def claim(smpl: int, candidates) -> None:
        if smpl in mapping:
            return
        for cand in candidates:
            j = by_norm.get(cand)
            if j is not None and j not in taken:
                mapping[smpl] = j
                taken.add(j)
                return

    claim(_J["pelvis"], _PELVIS_NAMES)
    claim(_J["head"], _HEAD_NAMES)
    for side, short in (("left", "l"), ("right", "r")):
        for part in ("hip", "knee", "ankle", "foot", "collar", "shoulder", "elbow", "wrist", "hand"):
            cands = [f for stem in _SIDE_STEMS[part] for f in (side + stem, short + stem, stem + side, stem + short)]
            claim(_J[f"{side}_{part}"], cands)
    if not mapping:
        raise InputError(f"{where}: no joint name could be mapped to an SMPL joint "
                         f"(joints: {', '.join(skel.names[:12])}{', ...' if skel.num_joints > 12 else ''})")
    if _J["pelvis"] not in mapping and 0 not in taken:
        mapping[_J["pelvis"]] = 0  # the BVH root is the body's root
        taken.add(0)
    if _J["pelvis"] not in mapping:
        raise InputError(f"{where}: no joint can serve as SMPL's pelvis (the root {skel.names[0]!r} is excluded "
                         f"or mapped elsewhere)")

    # Torso by structure: spine3 joins the head and both arms.
    parents = skel.parents
    anchors = [mapping[k] for k in (_J["head"],) if k in mapping]
    for side in ("left", "right"):
        arm = next((mapping[_J[f"{side}_{p}"]] for p in ("collar", "shoulder") if _J[f"{side}_{p}"] in mapping), None)
        if arm is not None:
            anchors.append(arm)
    pelvis = mapping.get(_J["pelvis"])
    if len(anchors) >= 2 and pelvis is not None:
        s3 = _lca(parents, anchors)
        if s3 >= 0 and s3 not in anchors and _is_ancestor(parents, pelvis, s3):
            path = []
            j = int(parents[s3])
            while j != pelvis:
                path.append(j)
                j = int(parents[j])
            path = [j for j in path[::-1] if j not in excluded]
            if s3 not in taken:
                mapping.setdefault(_J["spine3"], s3)
                taken.add(s3)
            if path and _J["spine1"] not in mapping and path[0] not in taken:
                mapping[_J["spine1"]] = path[0]
                taken.add(path[0])
            if len(path) >= 2 and _J["spine2"] not in mapping and path[-1] not in taken:
                mapping[_J["spine2"]] = path[-1]
                taken.add(path[-1])
            head = mapping.get(_J["head"])
            if head is not None and _J["neck"] not in mapping:
                nk = int(parents[head])
                if nk != s3 and nk not in taken and _is_ancestor(parents, s3, nk):
                    mapping[_J["neck"]] = nk
                    taken.add(nk)

    # Keep only mappings consistent with the SMPL tree.
    for j in range(1, NUM_JOINTS):
        if j not in mapping:
            continue
        a = int(SMPL_PARENTS[j])
        while a >= 0 and a not in mapping:
            a = int(SMPL_PARENTS[a])
        if a >= 0 and not _is_ancestor(parents, mapping[a], mapping[j]):
            warnings.warn(f"{where}: joint {skel.names[mapping[j]]!r} is not below {skel.names[mapping[a]]!r}, so it "
                          f"is not used as SMPL's {SMPL_JOINT_NAMES[j]}", BvhMappingWarning, stacklevel=3)
            del mapping[j]
    return dict(sorted(mapping.items()))


# ------------------------------------------------------------------------------------------- retargeting
def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotations taking unit vectors a to unit vectors b, shapes (..., 3) -> (..., 3, 3)."""
    a, b = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1, keepdims=True)
    c = np.sum(a * b, axis=-1, keepdims=True)
    angle = np.arctan2(s, c)
    # Opposite vectors: turn by pi about any axis perpendicular to a.
    helper = np.where(np.abs(a[..., :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    perp = _unit(np.cross(a, helper))
    axis = np.where(s > 1e-12, axis / np.maximum(s, 1e-300), perp)
    return axis_angle_to_matrix(axis * angle)


def _up_rotation(rest: np.ndarray, mapping: dict[int, int]) -> np.ndarray:
    """Rotation turning the BVH rest skeleton's up axis (a signed coordinate axis) into +Y."""
    P = rest
    pelvis = P[mapping[_J["pelvis"]]] if _J["pelvis"] in mapping else P[0]
    ups = [P[mapping[k]] - pelvis for k in (_J["head"], _J["neck"], _J["spine3"]) if k in mapping]
    ups += [pelvis - P[mapping[k]] for k in (_J["left_knee"], _J["right_knee"], _J["left_ankle"],
                                              _J["right_ankle"]) if k in mapping]
    if not ups:
        return np.eye(3)
    up = np.mean([_unit(u) for u in ups], axis=0)
    axis = int(np.argmax(np.abs(up)))
    e = np.zeros(3)
    e[axis] = np.sign(up[axis]) or 1.0
    if e[1] == 1.0:
        return np.eye(3)
    if e[1] == -1.0:
        return np.diag([1.0, -1.0, -1.0])
    return _min_rotation(e, np.array([0.0, 1.0, 0.0]))


@dataclass
class _JointPlan:
    """How one mapped SMPL joint is driven: its rest alignment and bone pairs."""

    bvh: int
    align: np.ndarray  # (3, 3) rest alignment A_j
    pairs: list[tuple[int, int]]  # (SMPL end joint, BVH end joint) of each bone used
    follower: bool  # no bone of its own: driven by its BVH rotation relative to the parent's bone frame
    rest_relative: bool = False  # G_j = Q_b: the BVH joint's rotation from its rest, no bone alignment


def _leaf_direction(j: int, smpl_rest: np.ndarray) -> np.ndarray:
    """Rest direction of an SMPL leaf joint's segment, which its joints do not give: SMPL-format bodies
    rest in a T-pose (docs/architecture.md, "Bodies"), so the head points up (+Y), the toes forward (+Z) and the hand
    continues the wrist-hand line."""
    if j == _J["head"]:
        return np.array([0.0, 1.0, 0.0])
    if j in (_J["left_foot"], _J["right_foot"]):
        return np.array([0.0, 0.0, 1.0])
    return _unit(smpl_rest[j] - smpl_rest[int(SMPL_PARENTS[j])])


def _bvh_leaf_directions(skel: BvhSkeleton, rest: np.ndarray, W: np.ndarray, eps: float) -> dict[int, np.ndarray]:
    """Rest direction of each BVH joint's own segment: the mean direction to its children and End Sites
    (joints whose segment has no length are left out)."""
    vecs: dict[int, list[np.ndarray]] = {j: [] for j in range(skel.num_joints)}
    for c in range(skel.num_joints):
        if skel.parents[c] >= 0:
            vecs[int(skel.parents[c])].append(rest[c] - rest[skel.parents[c]])
    for j, off in skel.end_sites:
        vecs[j].append(W @ off)
    out = {}
    for j, vs in vecs.items():
        units = [_unit(v) for v in vs if np.linalg.norm(v) > eps]
        if units and np.linalg.norm(np.mean(units, axis=0)) > 0.5:
            out[j] = _unit(np.mean(units, axis=0))
    return out


def _plan(skel_rest: np.ndarray, smpl_rest: np.ndarray, mapping: dict[int, int], eps: float,
          bvh_leaf_dirs: dict[int, np.ndarray], rest_relative: set[int]) -> dict[int, _JointPlan]:
    children = {j: [int(c) for c in np.flatnonzero(SMPL_PARENTS == j)] for j in range(NUM_JOINTS)}

    def targets(j: int) -> list[int]:
        out = []
        for c in children[j]:
            out.extend([c] if c in mapping else targets(c))
        return out

    def expand(j: int, c: int) -> list[tuple[int, int]]:
        # A BVH bone of (near) zero length (CMU's lowerback sits on Hips, LeftCollar on Chest2) gives no
        # direction: use the next mapped joints below it, on both skeletons alike.
        if np.linalg.norm(skel_rest[mapping[c]] - skel_rest[mapping[j]]) > eps:
            return [(c, mapping[c])]
        return [p for d in targets(c) for p in expand(j, d)]

    plans: dict[int, _JointPlan] = {}
    for j in range(NUM_JOINTS):
        if j not in mapping:
            continue
        b = mapping[j]
        pairs = [p for c in targets(j) for p in expand(j, c)]
        if j in rest_relative:
            plans[j] = _JointPlan(b, np.eye(3), pairs, follower=False, rest_relative=True)
            continue
        if not children[j] and b in bvh_leaf_dirs:
            # SMPL leaf (head, toes, hand) whose BVH joint has a segment: align the two segments.
            plans[j] = _JointPlan(b, _min_rotation(_leaf_direction(j, smpl_rest), bvh_leaf_dirs[b]), [], False)
            continue
        if not pairs:
            a = int(SMPL_PARENTS[j])
            while a >= 0 and a not in mapping:
                a = int(SMPL_PARENTS[a])
            align = plans[a].align if a >= 0 else np.eye(3)
            plans[j] = _JointPlan(b, align, [], follower=a >= 0)
            continue
        s = _unit(np.array([smpl_rest[c] - smpl_rest[j] for c, _ in pairs]))
        v = _unit(np.array([skel_rest[e] - skel_rest[b] for _, e in pairs]))
        main = next((k for k, (c, _) in enumerate(pairs) if c in _SPINE_CHAIN), None)
        if main is None:
            main = int(np.argmax([np.linalg.norm(smpl_rest[c] - smpl_rest[j]) for c, _ in pairs]))
        A = _min_rotation(s[main], v[main])
        if len(pairs) > 1:
            # Twist about the main bone that best lines up the other bones' components across it.
            n = v[main]
            num = den = 0.0
            for k in range(len(pairs)):
                if k == main:
                    continue
                x = A @ s[k]
                x = x - n * (x @ n)
                y = v[k] - n * (v[k] @ n)
                num += np.cross(x, y) @ n
                den += x @ y
            A = axis_angle_to_matrix(n * np.arctan2(num, den)) @ A
        plans[j] = _JointPlan(b, A, pairs, follower=False)
    return plans


def _retarget(skel: BvhSkeleton, smpl_rest: np.ndarray, mapping: dict[int, int]):
    """SMPL poses (F, 24, 3), SMPL pelvis joint positions [m] (F, 3) in the Y-up BVH world scaled to the
    body, the scale body/BVH, the rules used, the up rotation W and the BVH rest height."""
    rest = skel.rest_positions()
    W = _up_rotation(rest, mapping)
    Q, P = skel.forward()
    Q = W @ Q @ W.T
    P = P @ W.T
    rest = rest @ W.T
    height = float(np.ptp(rest[:, 1])) if skel.num_joints > 1 else 0.0
    eps = max(0.01 * height, 1e-9)

    # A clavicle that starts on the spine (CMU's LeftCollar on Chest2) pivots elsewhere than SMPL's.
    rest_relative = {j for j in _COLLARS if j in mapping and skel.parents[mapping[j]] >= 0
                     and np.linalg.norm(rest[mapping[j]] - rest[skel.parents[mapping[j]]]) <= eps}
    plans = _plan(rest, smpl_rest, mapping, eps, _bvh_leaf_directions(skel, rest, W, eps), rest_relative)
    F = skel.num_frames
    G = np.empty((F, NUM_JOINTS, 3, 3))
    for j in range(NUM_JOINTS):
        p = int(SMPL_PARENTS[j])
        if j not in plans:
            G[:, j] = G[:, p] if p >= 0 else np.eye(3)
            continue
        plan = plans[j]
        if plan.follower:
            a = p
            while a not in plans:
                a = int(SMPL_PARENTS[a])
            pa = plans[a]
            # The BVH frame that the parent's world rotation stands for: the joint carrying its bone.
            frame = int(skel.parents[pa.pairs[0][1]]) if len(pa.pairs) == 1 else pa.bvh
            rel = np.swapaxes(Q[:, frame], -1, -2) @ Q[:, plan.bvh]
            G[:, j] = G[:, a] @ pa.align.T @ rel @ pa.align
            continue
        if plan.rest_relative:
            G[:, j] = Q[:, plan.bvh]
            continue
        M = Q[:, plan.bvh] @ plan.align
        if len(plan.pairs) == 1 and j != 0:  # the pelvis keeps the BVH root's own orientation
            c, e = plan.pairs[0]
            s = _unit(smpl_rest[c] - smpl_rest[j])
            current = P[:, e] - P[:, plan.bvh]
            ok = np.linalg.norm(current, axis=-1) > eps
            D = _min_rotation(M @ s, _unit(current))
            D[~ok] = np.eye(3)
            M = D @ M
        G[:, j] = M

    local = np.empty_like(G)
    local[:, 0] = G[:, 0]
    for j in range(1, NUM_JOINTS):
        local[:, j] = np.swapaxes(G[:, SMPL_PARENTS[j]], -1, -2) @ G[:, j]
    poses = matrix_to_axis_angle(local)

    def leg(points: np.ndarray, side: str, index) -> float | None:
        ids = [_J[f"{side}_{n}"] for n in ("hip", "knee", "ankle")]
        if not all(k in index for k in ids):
            return None
        q = np.array([points[index[k]] for k in ids])
        return float(np.linalg.norm(q[1] - q[0]) + np.linalg.norm(q[2] - q[1]))

    identity = {k: k for k in range(NUM_JOINTS)}
    ratios = [(leg(smpl_rest, s, identity), leg(rest, s, mapping)) for s in ("left", "right")]
    ratios = [(a, b) for a, b in ratios if b is not None and b > eps]
    if ratios:
        scale = float(np.mean([a for a, _ in ratios]) / np.mean([b for _, b in ratios]))
        scale_rule = "leg length"
    else:
        scale = float(np.ptp(smpl_rest[:, 1]) / max(height, 1e-9))
        scale_rule = "skeleton height"
    # Root placement: the SMPL leg roots follow the BVH leg roots. Anchoring the midpoint of the two
    # hip joints (rather than the pelvis joint, whose offset to the hips differs between skeletons:
    # 9 cm above them in the CMU files, ~1 cm on the open body) keeps the feet where the BVH's feet are.
    hips = [_J["left_hip"], _J["right_hip"]]
    if all(k in mapping for k in hips):
        bvh_anchor = 0.5 * (P[:, mapping[hips[0]]] + P[:, mapping[hips[1]]])
        smpl_offset = np.einsum("fab,b->fa", G[:, 0], 0.5 * (smpl_rest[hips[0]] + smpl_rest[hips[1]]) - smpl_rest[0])
        anchor_rule = "hip midpoint"
    else:
        bvh_anchor = P[:, mapping[_J["pelvis"]]]
        smpl_offset = np.zeros((F, 3))
        anchor_rule = "pelvis"
    pelvis = scale * bvh_anchor - smpl_offset  # world position of the SMPL pelvis joint
    return poses, pelvis, scale, f"{scale_rule}; anchor {anchor_rule}", W, height


def load_bvh(
    path: str | Path,
    *,
    body: BodyModel,
    name: str | None = None,
    on_floor: bool = True,
    fps: float | None = None,
    joint_map: dict[str, str | None] | None = None,
) -> MotionClip:
    """Load a BVH file retargeted onto `body` (module docstring) as a Y-up MotionClip.

    body: the SMPL-format body (its rest joints at zero betas set SMPL's rest bone directions and leg
    length); fps: output frame rate [1/s] (default 30; the clip is slerp-resampled from the file's
    rate); joint_map: {BVH joint name: SMPL joint name or None} overriding the automatic mapping.
    The SMPL hip midpoint follows the BVH's, scaled by the leg-length ratio body/BVH; with on_floor
    the lowest foot point of the first 0.5 s is moved to y = 0 and frames where a foot would still sink
    more than LOADER_MAX_SINK (2 cm) are lifted smoothly. name defaults to the stem.
    Raises InputError for unreadable files, non-positive frame times or fps, and files none of whose
    joints can be mapped; warns (BvhMappingWarning) listing BVH joints left unmapped.
    """
    path = Path(path)
    if fps is not None:
        try:
            fps = float(fps)
        except (TypeError, ValueError):
            raise InputError(f"BVH import of {path}: fps must be a number, got {fps!r}") from None
        if not np.isfinite(fps) or fps <= 0.0:
            raise InputError(f"BVH import of {path}: fps must be positive, got {fps}")
    skel = parse_bvh(path)
    mapping = map_bvh_joints(skel, joint_map)
    unmapped = [skel.names[j] for j in range(skel.num_joints) if j not in mapping.values()]
    if unmapped:
        warnings.warn(f"BVH file {path}: {len(unmapped)} joints have no SMPL counterpart and are folded into the "
                      f"mapped joints below them: {', '.join(unmapped)}", BvhMappingWarning, stacklevel=2)
    smpl_rest = body.rest_joints()[0]
    poses, pelvis, scale, scale_rule, W, height = _retarget(skel, smpl_rest, mapping)
    trans = pelvis - smpl_rest[0]
    meta = {
        "source": "bvh",
        "source_file": path.name,
        "source_fps": skel.fps,
        "bvh_mapping": {SMPL_JOINT_NAMES[k]: skel.names[v] for k, v in mapping.items()},
        "bvh_unmapped": unmapped,
        "bvh_scale": scale,
        "bvh_scale_rule": scale_rule,
        "bvh_height": height,
        "bvh_up_rotation": W.round(12).tolist(),
    }
    clip = MotionClip(name or path.stem, skel.fps, poses, trans, meta)
    target = DEFAULT_BVH_FPS if fps is None else fps
    if clip.num_frames > 1 and target != clip.fps:
        clip = resample(clip, target)
    elif clip.num_frames == 1:
        clip = MotionClip(clip.name, target, clip.poses, clip.trans, clip.meta)
    if on_floor:
        clip = put_on_floor(clip, body, max_sink=LOADER_MAX_SINK)
    return clip
