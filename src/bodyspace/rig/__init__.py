"""Skeletons: forward kinematics, linear blend skinning, Blender bone frames, posing bodies.

``kinematics`` holds the pure batched maths (rotations, FK, LBS, Blender rest frames);
``weights`` computes bone-heat skin weights for any mesh and skeleton; ``volume`` corrects skinned
frames so each keeps its rest volume (``pose_bodies(..., preserve_volume=True)``); ``posing`` poses bodies of the template topology with a ``Rig`` (``pose_bodies``). Which
rotations make a named pose is data of the synthesis layer (``bodyspace.synth.poses``). The
convention is in docs/poses.md.
"""

from bodyspace.rig.kinematics import (
                                      bone_rest_frames,
                                      forward_kinematics,
                                      linear_blend_skinning,
                                      matrix_to_quaternion,
                                      matrix_to_rotvec,
                                      rotvec_to_matrix,
                                      topological_order,
)
from bodyspace.rig.posing import ground_offset, place_on_ground, pose_bodies, root_bone
from bodyspace.rig.weights import bone_heat_weights

__all__ = ["bone_rest_frames", "forward_kinematics", "linear_blend_skinning", "matrix_to_quaternion",
           "matrix_to_rotvec", "rotvec_to_matrix", "topological_order",
           "ground_offset", "place_on_ground", "pose_bodies", "root_bone", "bone_heat_weights"]
