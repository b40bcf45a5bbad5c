"""Skeletons: forward kinematics, linear blend skinning, Blender bone frames and the pose library.

``kinematics`` holds the pure batched maths (rotations, FK, LBS, Blender rest frames);
``poses`` the shipped pose library (data/poses/library.json) and ``pose_bodies``, which poses
bodies of the template topology with a ``Rig``. The convention is in docs/poses.md.
"""

from bodyspace.rig.kinematics import (bone_rest_frames, forward_kinematics, linear_blend_skinning,
                                      matrix_to_quaternion, matrix_to_rotvec, rotvec_to_matrix,
                                      topological_order)
from bodyspace.rig.poses import (Pose, PoseLibrary, ground_offset, load_pose_library, place_on_ground,
                                 pose_bodies, root_bone)

__all__ = ["bone_rest_frames", "forward_kinematics", "linear_blend_skinning", "matrix_to_quaternion",
           "matrix_to_rotvec", "rotvec_to_matrix", "topological_order",
           "Pose", "PoseLibrary", "ground_offset", "load_pose_library", "place_on_ground", "pose_bodies",
           "root_bone"]
