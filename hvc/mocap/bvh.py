"""cgspeed BVH files (the "MotionBuilder-friendly" CMU conversion) to AMC angles.

cgspeed BVH is the AMC data re-expressed with identity rest rotations: a BVH joint's
ZYX channels give R = Rz Ry Rx in the global rest frame, and the AMC rotation of the
corresponding ASF bone is M = C^T R C with C the bone's ASF `axis` rotation. M is
decomposed back as Rz Ry Rx into AMC (rx, ry, rz), which makes the conversion exact;
the ASF axes are identical for every CMU subject, so any CMU ASF supplies C. Frame 0
of these files is an added rest pose and is dropped.

BVH names differ from ASF names: each BVH joint rotates the segment to its child, whose
OFFSET equals the ASF bone's direction * length, so `LeftUpLeg` is `lfemur`, `LeftLeg`
`ltibia`, `Spine` `upperback`, `LeftHand` `lwrist` (cgspeed sets the wrist and thorax
lengths to zero), and so on. `mapping_report` checks that correspondence on a file.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from hvc.mocap.asf_amc import (
    LENGTH_TO_METRES,
    AsfSkeleton,
    MocapFrames,
    amc_angles,
    amc_rotation,
    amc_to_frames,
    parse_asf,
)

#: cgspeed BVH joint -> ASF bone it rotates (the bone whose vector is the child's OFFSET).
BVH_TO_ASF: dict[str, str] = {
    "Hips": "root",
    "LHipJoint": "lhipjoint", "LeftUpLeg": "lfemur", "LeftLeg": "ltibia",
    "LeftFoot": "lfoot", "LeftToeBase": "ltoes",
    "RHipJoint": "rhipjoint", "RightUpLeg": "rfemur", "RightLeg": "rtibia",
    "RightFoot": "rfoot", "RightToeBase": "rtoes",
    "LowerBack": "lowerback", "Spine": "upperback", "Spine1": "thorax",
    "Neck": "lowerneck", "Neck1": "upperneck", "Head": "head",
    "LeftShoulder": "lclavicle", "LeftArm": "lhumerus", "LeftForeArm": "lradius",
    "LeftHand": "lwrist", "LeftFingerBase": "lhand", "LeftHandIndex1": "lfingers", "LThumb": "lthumb",
    "RightShoulder": "rclavicle", "RightArm": "rhumerus", "RightForeArm": "rradius",
    "RightHand": "rwrist", "RightFingerBase": "rhand", "RightHandIndex1": "rfingers", "RThumb": "rthumb",
}  # fmt: skip
_DOF_INDEX = {"rx": 0, "ry": 1, "rz": 2}


@dataclasses.dataclass(frozen=True)
class BvhJoint:
    name: str
    parent: str | None
    offset: np.ndarray  # (3,) in the parent's rest frame (= global rest frame for cgspeed)
    channels: tuple[str, ...]
    end_offset: np.ndarray | None  # OFFSET of an `End Site` child, if any


@dataclasses.dataclass(frozen=True)
class BvhMotion:
    """Hierarchy (file order) and the raw channel matrix (frames, channels) of a BVH file."""

    joints: dict[str, BvhJoint]
    motion: np.ndarray
    frame_time: float

    def channel_index(self) -> dict[tuple[str, str], int]:
        """(joint, channel name) -> column of `motion`."""
        out, col = {}, 0
        for j in self.joints.values():
            for ch in j.channels:
                out[(j.name, ch.lower())] = col
                col += 1
        return out

    def children(self, name: str) -> list[str]:
        return [j.name for j in self.joints.values() if j.parent == name]


def read_bvh(path: str | Path) -> BvhMotion:
    """Parse a BVH file (any line endings) into its hierarchy and motion matrix."""
    tokens = Path(path).read_bytes().decode("utf-8", errors="replace").split()
    if not tokens or tokens[0].upper() != "HIERARCHY":
        raise ValueError(f"{path}: not a BVH file (no HIERARCHY header)")
    joints: dict[str, BvhJoint] = {}
    pos = 1

    def block(name: str | None, parent: str | None) -> np.ndarray:
        """Parse `{ OFFSET .. [CHANNELS ..] children }` after a ROOT/JOINT/End Site name; returns OFFSET."""
        nonlocal pos
        if tokens[pos] != "{":
            raise ValueError(f"{path}: expected '{{' after {name or 'End Site'}, got {tokens[pos]!r}")
        pos += 1
        offset, channels, end_offset = np.zeros(3), (), None
        if name is not None:
            joints[name] = None  # type: ignore[assignment]  # keep file (channel) order
        while tokens[pos] != "}":
            key = tokens[pos].upper()
            if key == "OFFSET":
                offset = np.array([float(v) for v in tokens[pos + 1 : pos + 4]])
                pos += 4
            elif key == "CHANNELS":
                n = int(tokens[pos + 1])
                channels = tuple(tokens[pos + 2 : pos + 2 + n])
                pos += 2 + n
            elif key == "JOINT":
                child = tokens[pos + 1]
                pos += 2
                block(child, name)
            elif key == "END":  # End Site
                pos += 2
                end_offset = block(None, name)
            else:
                raise ValueError(f"{path}: unexpected token {tokens[pos]!r} in HIERARCHY")
        pos += 1
        if name is not None:
            joints[name] = BvhJoint(name, parent, offset, channels, end_offset)
        return offset

    if tokens[pos].upper() != "ROOT":
        raise ValueError(f"{path}: expected ROOT, got {tokens[pos]!r}")
    pos += 2
    block(tokens[pos - 1], None)
    # MOTION / Frames: N / Frame Time: dt / N rows of floats.
    head = [t.lower() for t in tokens[pos : pos + 6]]
    if head[:2] != ["motion", "frames:"] or head[3:5] != ["frame", "time:"]:
        raise ValueError(f"{path}: malformed MOTION header {tokens[pos : pos + 6]}")
    num_frames, frame_time = int(tokens[pos + 2]), float(tokens[pos + 5])
    values = np.array(tokens[pos + 6 :], dtype=np.float64)
    num_channels = sum(len(j.channels) for j in joints.values())
    if values.size != num_frames * num_channels:
        raise ValueError(f"{path}: {values.size} motion values, expected {num_frames} x {num_channels} channels")
    return BvhMotion(joints=joints, motion=values.reshape(num_frames, num_channels), frame_time=frame_time)


def _rotation(motion: BvhMotion, joint: str, index: dict[tuple[str, str], int], rows: slice) -> np.ndarray:
    """R (T, 3, 3) from a joint's rotation channels, composed in the file's channel order."""
    j = motion.joints[joint]
    r = np.broadcast_to(np.eye(3), (motion.motion[rows].shape[0], 3, 3)).copy()
    for ch in j.channels:
        if ch.lower().endswith("rotation"):
            ang = motion.motion[rows, index[(joint, ch.lower())]]
            ax = "xyz".index(ch[0].lower())
            zero = np.zeros_like(ang)
            r = r @ amc_rotation(*(ang if k == ax else zero for k in range(3)))
    return r


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def _best_branch(ang: np.ndarray, absent: list[int]) -> np.ndarray:
    """Per frame, the Euler solution (rx, ry, rz) or (rx+180, 180-ry, rz+180) with less motion on absent axes.

    `amc_angles` always returns |ry| <= 90; a one-dof bone such as the wrist (ry in
    [-180, 0]) needs the other branch beyond 90 degrees. 3-dof CMU bones keep |ry| <= 90.
    """
    if not absent:
        return ang
    alt = _wrap_deg(ang + np.array([180.0, 0.0, 180.0]))
    alt[:, 1] = _wrap_deg(180.0 - ang[:, 1])
    use_alt = np.abs(alt[:, absent]).sum(1) < np.abs(ang[:, absent]).sum(1) - 1e-9
    return np.where(use_alt[:, None], alt, ang)


def _unwrap_deg(a: np.ndarray) -> np.ndarray:
    """Remove +-360 jumps over time (atan2 wraps at 180) so interpolation and velocities stay smooth."""
    out = np.rad2deg(np.unwrap(np.deg2rad(a), axis=0))
    return out - 360.0 * np.round(out[:1] / 360.0)


def bvh_to_amc_values(
    motion: BvhMotion, skeleton: AsfSkeleton, drop_first_frame: bool = True
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """AMC-style values {bone: (T, k)} (root: tx ty tz rx ry rz; bones: their ASF dofs, degrees).

    Also returns, per bone, the largest |angle| (deg) on axes the ASF bone does *not*
    have: exact data and a correct name mapping give ~0 there, so it verifies both.
    """
    rows = slice(1 if drop_first_frame else 0, None)
    index = motion.channel_index()
    root = "Hips" if "Hips" in motion.joints else next(iter(motion.joints))
    pos = np.stack([motion.motion[rows, index[(root, c + "position")]] for c in "xyz"], axis=1)
    root_angles = amc_angles(_rotation(motion, root, index, rows))
    values: dict[str, np.ndarray] = {"root": np.concatenate([pos, root_angles], axis=1)}
    off_dof: dict[str, float] = {}
    for joint in motion.joints:
        bone_name = BVH_TO_ASF.get(joint)
        if joint == root or bone_name is None:
            continue
        bone = skeleton.bones[bone_name]
        c = bone.axis_matrix
        m = c.T @ _rotation(motion, joint, index, rows) @ c
        keep = [_DOF_INDEX[d] for d in bone.dofs]
        rest = [k for k in range(3) if k not in keep]
        ang = _best_branch(amc_angles(m), rest)
        off_dof[bone_name] = float(np.abs(ang[:, rest]).max()) if rest else 0.0
        if keep:
            values[bone_name] = _unwrap_deg(ang[:, keep])
    return values, off_dof


def leg_length_m(motion: BvhMotion) -> float:
    """Subject's left femur + tibia in metres, from the OFFSETs of LeftLeg and LeftFoot."""
    return float(
        (np.linalg.norm(motion.joints["LeftLeg"].offset) + np.linalg.norm(motion.joints["LeftFoot"].offset))
        * LENGTH_TO_METRES
    )


def mapping_report(motion: BvhMotion, skeleton: AsfSkeleton) -> dict[str, float]:
    """Per mapped bone, |segment OFFSET - ASF direction * length| (ASF units); verifies `BVH_TO_ASF`.

    The segment of a BVH joint is its first child's (or End Site's) non-zero OFFSET.
    cgspeed gives some segments zero length (hip roots, thorax, wrists); those bones are
    left out. Meaningful only when `skeleton` is the same subject's ASF.
    """
    report = {}
    for joint, bone_name in BVH_TO_ASF.items():
        if joint not in motion.joints or bone_name == "root":
            continue
        segs = [motion.joints[k].offset for k in motion.children(joint)]
        if motion.joints[joint].end_offset is not None:
            segs.append(motion.joints[joint].end_offset)
        segs = [s for s in segs if np.linalg.norm(s) > 1e-6]
        if segs:
            bone = skeleton.bones[bone_name]
            report[bone_name] = float(np.linalg.norm(segs[0] - bone.direction * bone.length))
    return report


def _fps(frame_time: float) -> float:
    """cgspeed writes 1/120 s as `.0083333`; snap to the integer rate so resampled times stay on the grid."""
    fps = 1.0 / frame_time
    return float(round(fps)) if abs(fps - round(fps)) < 1e-2 else fps


def load_bvh(bvh_path: str | Path, asf_path: str | Path, drop_first_frame: bool = True) -> MocapFrames:
    """Read a cgspeed BVH into `MocapFrames`; `asf_path` is any CMU ASF (it supplies bone axes and dofs).

    The subject's leg length comes from the BVH OFFSETs, not from that ASF.
    """
    motion = read_bvh(bvh_path)
    skeleton = parse_asf(asf_path)
    values, _ = bvh_to_amc_values(motion, skeleton, drop_first_frame=drop_first_frame)
    frames = amc_to_frames(values, skeleton)
    return dataclasses.replace(frames, fps=_fps(motion.frame_time), leg_length=leg_length_m(motion))
