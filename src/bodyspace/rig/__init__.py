"""Skeletons: forward kinematics, linear blend skinning, Blender bone frames and the pose library.

``kinematics`` holds the pure batched maths; ``poses`` the shipped pose library and the
function that poses bodies of the template topology with a ``Rig``.
"""

from bodyspace.rig.kinematics import (bone_rest_frames, forward_kinematics, linear_blend_skinning,
                                      matrix_to_quaternion, matrix_to_rotvec, rotvec_to_matrix,
                                      topological_order)

__all__ = ["bone_rest_frames", "forward_kinematics", "linear_blend_skinning", "matrix_to_quaternion",
           "matrix_to_rotvec", "rotvec_to_matrix", "topological_order"]
