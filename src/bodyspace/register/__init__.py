"""Registration of raw scans and of meshes of other topologies (Hasler §2.2–2.3).

One module per stage, each usable alone: ``prepare`` (read, units, up, normals), ``align``
(initial alignment), ``pose_fit`` (skeleton pose by twist ICP), ``model_fit`` (shape
coefficients), ``nicp`` (per-vertex affine non-rigid ICP), ``quality`` (fit quality and
refusal); ``correspondences`` holds the matching they share, ``pipeline`` runs them in order
(``register_scan``) and ``landmarks`` carries the measurement set's landmarks (and the template's
body parts and skin weights) to a mesh of another topology. ``detail`` keeps a scan's relief as
normal offsets on the subdivided fit and re-adds it after a morph (Hasler §3); ``user_model``
makes a user's BodyModel the shape space; ``caesar`` and ``landmark_files`` read landmark files
(JSON, CAESAR .lnd); ``batch`` registers a folder of scans. docs/registration.md.
"""
