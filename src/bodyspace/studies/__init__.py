"""Studies: evaluations that return data (dicts and dataclasses of arrays and numbers).

One module per study: ``generalization`` (leave-one-subject-out error against the number of
components), ``interpolation`` (halfway meshes between scans, Hasler Figure 5), ``requests``
(random semantic requests), ``mapping`` (Rupprecht's measurements-to-shape mapping, Rupprecht §4.2).
Their tables and pictures are written by ``bodyspace.report``.
"""
