"""Motion capture: BVH files in and out, and matching a clip's skeleton to a rig (Rupprecht §3.3.2).

``bvh``: the ``Motion`` data model (skeleton, channel values, frame time, unit), reader and writer.
``matching``: which joint of one skeleton is which bone of another, by structure, with name hints.
"""
