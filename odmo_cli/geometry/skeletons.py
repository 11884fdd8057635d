"""Named skeletons: joint names, parents, kinematic chains and up axis.

One definition per dataset. Joint 0 is always the root (pelvis). `parents[j]` is the joint
that bone j hangs from (-1 for the root); the chains are the ones the papers draw with.
"""

from __future__ import annotations

from dataclasses import dataclass

from odmo_cli.errors import UserError


@dataclass(frozen=True)
class Skeleton:
    name: str
    joint_names: tuple[str, ...]
    chains: tuple[tuple[int, ...], ...]
    up_axis: str  # "+y" or "-y": the direction of "up" in the dataset's own frame
    bvh_names: tuple[str, ...] | None = None  # the usual BVH names of the joints (None: use joint_names)
    legs: tuple[tuple[int, int, int, int], ...] = ()  # (hip, knee, ankle, toe) of each leg

    @property
    def feet(self) -> tuple[int, ...]:
        """The foot joints (ankle and toe of each leg): what touches the floor."""
        return tuple(j for leg in self.legs for j in leg[2:])

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def parents(self) -> tuple[int, ...]:
        """Parent of every joint, derived from the chains (each chain starts at a joint already placed)."""
        parents = [-2] * self.n_joints
        parents[0] = -1
        for chain in self.chains:
            for parent, child in zip(chain[:-1], chain[1:]):
                parents[child] = parent
        return tuple(parents)

    @property
    def bones(self) -> tuple[tuple[int, int], ...]:
        """(parent, child) pairs, one per non-root joint, in joint order."""
        return tuple((p, j) for j, p in enumerate(self.parents) if p >= 0)

    @property
    def up_index(self) -> int:
        return "xyz".index(self.up_axis[-1])

    @property
    def up_sign(self) -> float:
        return -1.0 if self.up_axis.startswith("-") else 1.0

    def y_up_rotation(self):
        """(3, 3) proper rotation taking the dataset's frame to y-up, the subject's left kept on +x:
        identity for +y, half a turn about x for -y. UserError for other up axes."""
        import numpy as np

        if self.up_index != 1:
            raise UserError(f"skeleton {self.name!r} is {self.up_axis}-up; only y-up and -y-up frames can be turned y-up")
        return np.diag([1.0, self.up_sign, self.up_sign])

    @property
    def ground_axes(self) -> tuple[int, int]:
        """The two axes spanning the ground plane (end points are given in these)."""
        return ground_axes(self.up_index)


def ground_axes(up: int) -> tuple[int, int]:
    """The two axes spanning the ground plane of a frame whose vertical axis is `up`, in order."""
    return tuple(i for i in range(3) if i != up)  # type: ignore[return-value]


_SMPL_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
)

# Left/right of cmu20 checked on walking clips of the Action2Motion release (joints 4-7 and
# 12-15 lie on the walker's left of the direction of travel).
_CMU20_NAMES = (
    "root", "thorax", "neck", "head",
    "left_shoulder", "left_elbow", "left_wrist", "left_hand",
    "right_shoulder", "right_elbow", "right_wrist", "right_hand",
    "left_hip", "left_knee", "left_ankle", "left_toe",
    "right_hip", "right_knee", "right_ankle", "right_toe",
)

def _sided(names: dict[str, str]) -> dict[str, str]:
    """left_* -> Left*, plus the right_* -> Right* twins."""
    out = dict(names)
    for k, v in names.items():
        if k.startswith("left_"):
            out["right_" + k[5:]] = "Right" + v[4:]
    return out


# The names MotionBuilder, Blender's Rigify/Mixamo retargeting and the CMU BVH conversion use for
# these bones (Hips, Spine, LeftUpLeg, LeftArm, ...). cmu20's are those the CMU BVH release gives
# the joints A2M kept, so an exported file reads back with the same joint map as the release.
_SMPL_BVH = _sided({
    "pelvis": "Hips", "left_hip": "LeftUpLeg", "left_knee": "LeftLeg", "left_ankle": "LeftFoot",
    "left_foot": "LeftToeBase", "spine1": "Spine", "spine2": "Spine1", "spine3": "Spine2", "neck": "Neck",
    "head": "Head", "left_collar": "LeftShoulder", "left_shoulder": "LeftArm", "left_elbow": "LeftForeArm",
    "left_wrist": "LeftHand", "left_hand": "LeftFingerBase",
})
_CMU20_BVH = _sided({
    "root": "Hips", "thorax": "Spine1", "neck": "Neck", "head": "Head", "left_shoulder": "LeftArm",
    "left_elbow": "LeftForeArm", "left_wrist": "LeftHand", "left_hand": "LeftFingerBase", "left_hip": "LeftUpLeg",
    "left_knee": "LeftLeg", "left_ankle": "LeftFoot", "left_toe": "LeftToeBase",
})

# ODMO's UESTC release (18 joints, supplement Figure 1). Which side is "left", and the up axis,
# have not been checked against data (the release is not in our test data): sides are named a/b.
_UESTC18_NAMES = (
    "pelvis", "thorax", "shoulder_a", "elbow_a", "wrist_a", "shoulder_b", "elbow_b", "wrist_b",
    "neck", "hip_b", "knee_b", "ankle_b", "hip_a", "knee_a", "ankle_a", "foot_a", "foot_b", "head",
)

SKELETONS: dict[str, Skeleton] = {
    "humanact12": Skeleton(
        "humanact12", _SMPL_NAMES,
        ((0, 1, 4, 7, 10), (0, 2, 5, 8, 11), (0, 3, 6, 9, 12, 15),
         (9, 13, 16, 18, 20, 22), (9, 14, 17, 19, 21, 23)),
        up_axis="-y", bvh_names=tuple(_SMPL_BVH[n] for n in _SMPL_NAMES), legs=((1, 4, 7, 10), (2, 5, 8, 11)),
    ),
    "cmu20": Skeleton(
        "cmu20", _CMU20_NAMES,
        ((0, 1, 2, 3), (0, 12, 13, 14, 15), (0, 16, 17, 18, 19), (1, 4, 5, 6, 7), (1, 8, 9, 10, 11)),
        up_axis="+y", bvh_names=tuple(_CMU20_BVH[n] for n in _CMU20_NAMES),
        legs=((12, 13, 14, 15), (16, 17, 18, 19)),
    ),
    "uestc18": Skeleton(
        "uestc18", _UESTC18_NAMES,
        ((0, 12, 13, 14, 15), (0, 9, 10, 11, 16), (0, 1, 8, 17), (1, 5, 6, 7), (1, 2, 3, 4)),
        up_axis="-y", legs=((12, 13, 14, 15), (9, 10, 11, 16)),
    ),
}


def get_skeleton(name: str) -> Skeleton:
    try:
        return SKELETONS[name]
    except KeyError:
        raise UserError(f"unknown skeleton {name!r}; valid: {', '.join(SKELETONS)}") from None
