"""Acclaim ASF skeletons and AMC motions, read into the walker's joint space.

The 56 hinge joints of dm_control's CMU humanoid are named `<bone><dof>` exactly as
in the CMU ASF files and take `deg2rad(AMC value)`, so conversion is a renaming
plus the root transform (Y-up ASF units to Z-up metres). The parser is keyed by
bone name (dm_control's `suite.utils.parse_amc.parse` keeps only the value order
of its own humanoid) and treats a carriage return as whitespace, so CRLF files and
stray CRs both parse. Rotation helpers for the AMC Euler convention live here too,
because the BVH reader converts into the same AMC angles.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from dm_control.suite.utils.parse_amc import CONVERSION_LENGTH, MOCAP_DT
from dm_control.utils import transformations as tr

#: ASF length unit (`:units length 0.45`, inches / 0.45) to metres.
LENGTH_TO_METRES: float = CONVERSION_LENGTH
#: Frame rate of every CMU AMC and cgspeed BVH file.
MOCAP_FPS: float = 1.0 / MOCAP_DT
#: ASF/AMC frame (Y up) to MuJoCo world frame (Z up): (x, y, z) -> (x, -z, y).
Y2Z: np.ndarray = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
_DOF_AXES = ("rx", "ry", "rz")


@dataclasses.dataclass(frozen=True)
class AsfBone:
    """One ASF bone: rest direction and length (ASF units), `axis` angles (deg), dofs."""

    name: str
    direction: np.ndarray
    length: float
    axis: np.ndarray
    axis_order: str
    dofs: tuple[str, ...]

    @property
    def axis_matrix(self) -> np.ndarray:
        """C of the bone: local joint frame in the global rest frame (C^T R C is the AMC rotation)."""
        if self.axis_order.upper() != "XYZ":
            raise ValueError(f"bone {self.name}: axis order {self.axis_order!r} is not supported (CMU uses XYZ)")
        return amc_rotation(*self.axis)


@dataclasses.dataclass(frozen=True)
class AsfSkeleton:
    """Bones (by name, file order) and the parent -> children hierarchy of an ASF file."""

    bones: dict[str, AsfBone]
    children: dict[str, tuple[str, ...]]

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Hinge joint names `<bone><dof>` in file order; these are the walker's mocap joint names."""
        return tuple(b.name + d for b in self.bones.values() for d in b.dofs)

    def leg_length_m(self) -> float:
        """Left femur + tibia in metres, the subject's leg used to scale root translation."""
        return (self.bones["lfemur"].length + self.bones["ltibia"].length) * LENGTH_TO_METRES


@dataclasses.dataclass(frozen=True)
class MocapFrames:
    """A clip at its capture rate in the walker's coordinates, before scaling and resampling.

    Shared by the AMC and BVH readers so the rest of the pipeline does not care which
    format a clip came from. Root position is in metres of the *subject* (unscaled).
    """

    root_pos: np.ndarray  # (T, 3) metres, Z up
    root_quat: np.ndarray  # (T, 4) w first, hemisphere-continuous
    joints: np.ndarray  # (T, J) radians
    joint_names: tuple[str, ...]  # J names `<bone><dof>`
    fps: float
    leg_length: float  # subject's femur + tibia in metres

    @property
    def num_frames(self) -> int:
        return int(self.root_pos.shape[0])


# --------------------------------------------------------------------------- rotations
def _axis_rot(axis: int, deg: np.ndarray) -> np.ndarray:
    a = np.deg2rad(np.asarray(deg, dtype=np.float64))
    c, s = np.cos(a), np.sin(a)
    m = np.zeros(a.shape + (3, 3))
    i, j = [k for k in range(3) if k != axis]
    m[..., axis, axis] = 1.0
    m[..., i, i] = c
    m[..., j, j] = c
    m[..., i, j] = -s if axis != 1 else s
    m[..., j, i] = s if axis != 1 else -s
    return m


def amc_rotation(rx, ry, rz) -> np.ndarray:
    """Rz(rz) Ry(ry) Rx(rx) from degrees (ASF `axis XYZ` order); broadcasts over leading dims."""
    return _axis_rot(2, rz) @ _axis_rot(1, ry) @ _axis_rot(0, rx)


def amc_angles(m: np.ndarray) -> np.ndarray:
    """Inverse of `amc_rotation`: (..., 3, 3) -> (..., 3) degrees (rx, ry, rz), ry in [-90, 90]."""
    ry = np.arcsin(np.clip(-m[..., 2, 0], -1.0, 1.0))
    rx = np.arctan2(m[..., 2, 1], m[..., 2, 2])
    rz = np.arctan2(m[..., 1, 0], m[..., 0, 0])
    return np.rad2deg(np.stack([rx, ry, rz], axis=-1))


def matrices_to_quats(mats: np.ndarray) -> np.ndarray:
    """(T, 3, 3) -> (T, 4) w-first quaternions, sign-aligned frame to frame so interpolation is short-path."""
    q = np.stack([tr.mat_to_quat(m) for m in mats])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    if q[0, 0] < 0:
        q[0] = -q[0]
    for t in range(1, len(q)):
        if np.dot(q[t], q[t - 1]) < 0:
            q[t] = -q[t]
    return q


def root_to_walker(tx_ty_tz: np.ndarray, rx_ry_rz_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """AMC root channels (T, 3)+(T, 3) -> walker root position (metres, unscaled) and quaternion."""
    pos = np.asarray(tx_ty_tz, dtype=np.float64) @ Y2Z.T * LENGTH_TO_METRES
    r = np.asarray(rx_ry_rz_deg, dtype=np.float64)
    mats = Y2Z @ amc_rotation(r[:, 0], r[:, 1], r[:, 2])
    return pos, matrices_to_quats(mats)


# --------------------------------------------------------------------------- parsing
def _lines(path: str | Path) -> list[str]:
    """Lines split on LF only; `\r` is left in place and later dropped as whitespace by str.split()."""
    return Path(path).read_bytes().decode("utf-8", errors="replace").split("\n")


def parse_asf(path: str | Path) -> AsfSkeleton:
    """Read an ASF file's bones, hierarchy and length unit."""
    bones: dict[str, AsfBone] = {}
    children: dict[str, tuple[str, ...]] = {}
    length_unit = 0.45
    section = ""
    cur: dict | None = None
    for raw in _lines(path):
        tok = raw.split()
        if not tok or tok[0].startswith("#"):
            continue
        if tok[0].startswith(":"):
            section = tok[0][1:]
            continue
        key = tok[0]
        if section == "units" and key == "length":
            length_unit = float(tok[1])
        elif section == "bonedata":
            if key == "begin":
                cur = {"dofs": ()}
            elif key == "end" and cur is not None:
                bones[cur["name"]] = AsfBone(
                    name=cur["name"],
                    direction=np.array(cur.get("direction", (0.0, 0.0, 0.0))),
                    length=float(cur.get("length", 0.0)),
                    axis=np.array(cur.get("axis", (0.0, 0.0, 0.0))),
                    axis_order=cur.get("axis_order", "XYZ"),
                    dofs=cur["dofs"],
                )
                cur = None
            elif cur is not None:
                if key == "name":
                    cur["name"] = tok[1]
                elif key == "direction":
                    cur["direction"] = tuple(float(v) for v in tok[1:4])
                elif key == "length":
                    cur["length"] = float(tok[1])
                elif key == "axis":
                    cur["axis"] = tuple(float(v) for v in tok[1:4])
                    cur["axis_order"] = tok[4] if len(tok) > 4 else "XYZ"
                elif key == "dof":
                    cur["dofs"] = tuple(d.lower() for d in tok[1:] if d.lower() in _DOF_AXES)
        elif section == "hierarchy" and key not in ("begin", "end"):
            children[key] = children.get(key, ()) + tuple(tok[1:])
    if not bones:
        raise ValueError(f"{path}: no :bonedata bones found; is this an ASF file?")
    if abs(length_unit - 0.45) > 1e-9:  # LENGTH_TO_METRES (dm_control's 0.056444) assumes CMU units
        raise ValueError(f"{path}: `:units length {length_unit}`; only CMU skeletons (length 0.45) are supported")
    return AsfSkeleton(bones=bones, children=children)


def read_amc(path: str | Path) -> dict[str, np.ndarray]:
    """AMC values by bone name: {bone: (T, k) array in file units (deg, ASF lengths)}.

    Frames start at a line holding only an integer; each following line is
    `bone v1 ... vk`. Header lines (`#`, `:`) are skipped.
    """
    frames: list[dict[str, list[float]]] = []
    for raw in _lines(path):
        tok = raw.split()
        if not tok or tok[0].startswith(("#", ":")):
            continue
        if len(tok) == 1 and tok[0].isdigit():
            frames.append({})
        elif frames:
            frames[-1][tok[0]] = [float(v) for v in tok[1:]]
    if not frames:
        raise ValueError(f"{path}: no motion frames found; is this an AMC file?")
    names = list(frames[0])
    for i, f in enumerate(frames):
        if list(f) != names or any(len(f[n]) != len(frames[0][n]) for n in names):
            raise ValueError(f"{path}: frame {i + 1} lists different bones or value counts than frame 1")
    return {n: np.array([f[n] for f in frames], dtype=np.float64) for n in names}


def amc_to_frames(values: dict[str, np.ndarray], skeleton: AsfSkeleton) -> MocapFrames:
    """Map AMC values onto root pose + named hinge angles (radians) with the ASF's dof lists."""
    root = values["root"]
    pos, quat = root_to_walker(root[:, 0:3], root[:, 3:6])
    cols, names = [], []
    num_frames = root.shape[0]
    for bone in skeleton.bones.values():
        if not bone.dofs:
            continue
        v = values.get(bone.name)
        if v is None:
            raise ValueError(f"motion has no values for ASF bone {bone.name} (dofs {bone.dofs})")
        if v.shape != (num_frames, len(bone.dofs)):
            raise ValueError(f"bone {bone.name}: values shaped {v.shape}, ASF lists dofs {bone.dofs}")
        for k, dof in enumerate(bone.dofs):
            cols.append(np.deg2rad(v[:, k]))
            names.append(bone.name + dof)
    return MocapFrames(
        root_pos=pos,
        root_quat=quat,
        joints=np.stack(cols, axis=1),
        joint_names=tuple(names),
        fps=MOCAP_FPS,
        leg_length=skeleton.leg_length_m(),
    )


def load_amc(amc_path: str | Path, asf_path: str | Path) -> MocapFrames:
    """Read an AMC motion with its subject's ASF skeleton into `MocapFrames`."""
    return amc_to_frames(read_amc(amc_path), parse_asf(asf_path))
