"""Motion capture: BVH files in and out, matching a clip's skeleton to a rig (Rupprecht §3.3.2),
retargeting with feet that stay put (Rupprecht §3.3.3).

``bvh``: the ``Motion`` data model (skeleton, channel values, frame time, unit), reader and writer.
``matching``: which joint of one skeleton is which bone of another, by structure, with name hints.
``retarget``: a clip on a body's skeleton (rest-pose alignment, rotations in our axes, root path
scaled by leg length). ``contacts``: foot contacts and the skating / penetration measures.
``ik``: analytic two-bone IK keeping planted feet still. ``intersection``: arms in the torso.
"""
