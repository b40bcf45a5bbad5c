"""Geometry core: triangle-mesh arrays in, arrays out.

Modules by concern: ``io`` (reading/writing through trimesh), ``topology`` (edges, adjacency),
``geometry`` (areas, normals, volume, hole capping), ``operators`` and ``solver`` (sparse).
"""
