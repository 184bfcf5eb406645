"""The canonical 22-joint skeleton of HumanML3D (SMPL joint order), as plain data.

Coordinates are metres, Y up; a body facing +Z has its left side on +X.
Everything here is a constant: no functions that need torch or numpy beyond building arrays.
"""

from __future__ import annotations

import numpy as np

FPS = 20
FEATURE_DIM = 263
NUM_JOINTS = 22

JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee",
    "spine2", "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot",
    "neck", "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)

# Chains from a branching joint to a leaf, as HumanML3D's t2m_kinematic_chain (right leg, left leg,
# spine + head, right arm, left arm). HumanML3D's IK and FK walk these chains; the arm chains start at
# spine3 (9) but HumanML3D composes their rotations from the ROOT rotation, not spine3's.
KINEMATIC_CHAINS = (
    (0, 2, 5, 8, 11),
    (0, 1, 4, 7, 10),
    (0, 3, 6, 9, 12, 15),
    (9, 14, 17, 19, 21),
    (9, 13, 16, 18, 20),
)

PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)

# Unit direction of each joint's incoming bone in the rest pose (HumanML3D's t2m_raw_offsets):
# hips sideways, legs down, feet forward, spine up, collars sideways, head forward, arms hanging down.
RAW_OFFSETS = np.array(
    [
        [0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0],
        [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1],
        [0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, -1, 0], [0, -1, 0],
        [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0],
    ],
    dtype=np.float64,
)  # (22, 3)

# Bone lengths (metres) of HumanML3D's target skeleton (its "uniform skeleton" step rescales every clip
# to the bones of its example clip 000021, which we do not have). Derived from the golden sample
# new_joints_012314.npy, which was written after that step: |joint - parent| per frame is constant over
# its 170 frames to <= 2e-6 m; these are the per-bone means, rounded to 1e-7 m.
REFERENCE_BONE_LENGTHS = np.array(
    [
        0.0, 0.1030740, 0.1098834, 0.1315682, 0.3936232, 0.3901882,
        0.1431902, 0.4324330, 0.4256434, 0.0573647, 0.1433818, 0.1494191,
        0.2193600, 0.1374868, 0.1433828, 0.1030392, 0.1316140, 0.1229844,
        0.2568399, 0.2630919, 0.2660118, 0.2698763,
    ],
    dtype=np.float64,
)  # (22,)

# Rest-pose offset of each joint from its parent: RAW_OFFSETS direction * reference length (metres),
# exactly how HumanML3D builds the target offsets it applies in the uniform-skeleton step.
REFERENCE_OFFSETS = RAW_OFFSETS * REFERENCE_BONE_LENGTHS[:, None]  # (22, 3)

# The canonical rig's rest pose for joint ROTATIONS (mld_core.motion.rotations, BVH export, the Blender
# rig): REFERENCE_OFFSETS, except the bones out of the two branching joints. With one rotation per joint
# the pelvis cannot bend its hips away from the spine (nor spine3 its collars away from the neck), so the
# rest pose must already have the shape of the data: REFERENCE_OFFSETS' hips straight out sideways and
# collars straight out would leave the legs 3-4 cm off. These directions are the pelvis and chest shape
# of the Bandai Namco training data (identical to 6e-6 in 40 random clips; rotations.rest_offsets_from_joints
# on canonical_joints of each clip): hips 18.7 degrees below horizontal, collars steeply up; spine1 and
# neck stay straight up. (HumanML3D/SMPL bodies differ: hips about 53 degrees down and back.)
REST_DIRECTIONS = RAW_OFFSETS.copy()
REST_DIRECTIONS[1] = (0.94708938, -0.32096994, 0.0)  # left hip
REST_DIRECTIONS[2] = (-0.94708743, -0.32097570, 0.0)  # right hip
REST_DIRECTIONS[13] = (0.35781443, 0.93362296, -0.01780452)  # left collar
REST_DIRECTIONS[14] = (-0.35784279, 0.93362577, -0.01707239)  # right collar
REST_DIRECTIONS /= np.maximum(np.linalg.norm(REST_DIRECTIONS, axis=1, keepdims=True), 1e-12)
REST_OFFSETS = REST_DIRECTIONS * REFERENCE_BONE_LENGTHS[:, None]  # (22, 3)

# (right hip, left hip, right shoulder, left shoulder): the joints that define the facing direction.
FACE_JOINTS = (2, 1, 17, 16)
FOOT_LEFT = (7, 10)   # left ankle, left foot
FOOT_RIGHT = (8, 11)  # right ankle, right foot
# Joints whose incoming bones give the leg length used for scaling (right knee = thigh, right ankle = shin).
LEG_JOINTS = (5, 8)

# Index of each joint's left/right counterpart (itself for the centre line).
MIRROR_INDEX = (0, 2, 1, 3, 5, 4, 6, 8, 7, 9, 11, 10, 12, 14, 13, 15, 17, 16, 19, 18, 21, 20)


def _check() -> None:
    assert len(JOINT_NAMES) == len(PARENTS) == len(MIRROR_INDEX) == NUM_JOINTS
    for chain in KINEMATIC_CHAINS:
        for parent, child in zip(chain[:-1], chain[1:]):
            assert PARENTS[child] == parent
    for j, m in enumerate(MIRROR_INDEX):
        assert MIRROR_INDEX[m] == j


_check()
