"""Analytic Jacobians of body measurements with respect to shape coefficients.

With the vertex encoding a body is ``v(z) = base + sum_k z_k C_k`` (``base`` (V, 3) the mean
body, ``C`` (K, V, 3) the principal components reshaped), so ``dv/dz = C`` exactly. The
measurements of Rupprecht §3.1.2 and the ISO lengths are piecewise smooth functions of
a few vertices; their derivatives with respect to those vertices are written out here (pure,
batched functions), then chained with ``C``:

- **loop** (ordered ring of vertices projected on the plane normal to ``axis``):
  ``L = sum_i |P (r_{i+1} - r_i)|`` with ``P = I - a a^T``, so
  ``dL/dr_i = u_{i-1} - u_i``, ``u_i`` the projected unit edge vectors.
- **distance** (``|b - a|`` or ``|(b - a) . axis|``; ``axis`` fixed or a landmark pair; ``to`` may be
  the floor, the lowest vertex: its gradient goes to that vertex's y).
- **path** (sum of segment lengths through landmark points): unit segment vectors.
- **top** (the highest vertex of a body part over the lowest vertex: stature): +1 on the
  highest vertex's y, -1 on the lowest's.

Landmarks are sparse linear combinations of vertices (``L @ v``), so their gradients go back to
vertices through ``L^T``.

With the RRE encoding bodies are not linear in z: ``LinearBodyMeasures.measure_bodies`` measures
the truly decoded bodies (exact values) and chains the exact vertex gradients with a fitted
linearization of the decoder (``encoding.linearize.DecoderLinearization``) for dv/dz.

Slices (plane cross-sections, convex-hull girths) are not differentiated yet:
``LinearBodyMeasures`` refuses them with a message, and ``training.make_training_set`` measures
them with ``measure.evaluate`` instead.
Conditions (``requires``: upright etc.) are not checked here: rest-pose shape-space bodies meet them.

Shapes: N bodies, R ring points, K coefficients, M measurements. Values in metres.
"""

from __future__ import annotations

import dataclasses
import weakref

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.measure.definitions import MeasurementSet
from bodyspace.measure.parts import PART_INDEX

RUPPRECHT_SIX = ("height", "breast_size", "waist_size", "hip_size", "leg_length", "shoulder_size")
# Four of Rupprecht's six are vertex loops of the template (Rupprecht §3.1.2), which a set of
# another topology does not have (``with_landmarks`` drops them). Each input then stands in by
# the first of these the set has: the same body dimension measured the ISO 8559-1 way (a tape
# round the chest for the breast loop, the biacromial breadth for the loop round both shoulders).
SUBSTITUTES = {"height": ("stature",), "breast_size": ("chest_girth",), "waist_size": ("waist_girth",),
               "hip_size": ("hip_girth",), "leg_length": ("inside_leg_length", "crotch_height"),
               "shoulder_size": ("shoulder_width",)}
# Measurements of one quantity under two names (Rupprecht's and ISO 8559-1's): a request of
# one fixes the mapping's input of the other (height: the head-top landmark over the floor,
# stature: the head's highest vertex, equal on a level head; the three leg lengths are one
# definition, crotch to floor).
SAME_QUANTITY = {"height": ("stature",), "leg_length": ("inside_leg_length", "crotch_height"),
                 "stature": ("height",), "inside_leg_length": ("leg_length", "crotch_height"),
                 "crotch_height": ("leg_length", "inside_leg_length")}
# A mapping from fewer measurements than this is refused (two numbers do not pin a body shape).
MIN_INPUTS = 3
UP = np.array([0.0, 1.0, 0.0])
DIFFERENTIABLE = ("loop", "distance", "path", "top")
_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


# ---------------------------------------------------------------------- vertex-level Jacobians
def loop_length_grad(ring: np.ndarray, axis: np.ndarray = UP) -> tuple[np.ndarray, np.ndarray]:
    """Length of closed rings projected on the plane normal to ``axis``, and its gradient.

    Args:
        ring: (N, R, 3) ordered ring points; axis: (3,) unit vector.
    Returns:
        length (N,), d length / d ring (N, R, 3).
    """
    a = np.asarray(axis, dtype=float)
    flat = ring - (ring @ a)[..., None] * a
    e = np.roll(flat, -1, axis=1) - flat                       # edge i: r_i -> r_{i+1}
    n = np.linalg.norm(e, axis=-1)
    u = e / np.maximum(n, 1e-15)[..., None]
    return n.sum(axis=1), np.roll(u, 1, axis=1) - u            # u_{i-1} - u_i (already in the plane)


def distance_grad(a: np.ndarray, b: np.ndarray, axis: np.ndarray | None = None):
    """``|b - a|`` (axis None) or ``|(b - a) . axis|``, and gradients w.r.t. a, b and axis.

    a, b: (N, 3); axis: (N, 3) unit vectors or None. Returns value (N,), ga, gb, gaxis (N, 3)
    (gaxis is zeros without an axis; for a unit axis from a landmark pair chain it with
    ``unit_vector_grad``).
    """
    d = b - a
    if axis is None:
        val = np.linalg.norm(d, axis=-1)
        gd = d / np.maximum(val, 1e-15)[:, None]
        return val, -gd, gd, np.zeros_like(d)
    p = np.sum(d * axis, axis=-1)
    s = np.where(p >= 0, 1.0, -1.0)[:, None]
    return np.abs(p), -s * axis, s * axis, s * d


def unit_vector_grad(p: np.ndarray, q: np.ndarray, g_axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Chain ``g_axis`` (N, 3) through ``axis = (q - p) / |q - p|``: gradients w.r.t. p and q."""
    d = q - p
    n = np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-15)
    ax = d / n
    gq = (g_axis - np.sum(g_axis * ax, axis=-1, keepdims=True) * ax) / n
    return -gq, gq


def path_length_grad(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Length of open polylines (N, K, 3) and its gradient (N, K, 3)."""
    e = np.diff(points, axis=1)
    n = np.linalg.norm(e, axis=-1)
    u = e / np.maximum(n, 1e-15)[..., None]
    g = np.zeros_like(points)
    g[:, :-1] -= u
    g[:, 1:] += u
    return n.sum(axis=1), g


def mapping_inputs(mset: MeasurementSet) -> tuple[str, ...]:
    """The mapping's input measurements for a measurement set: Rupprecht's six where the set has
    them (the template's set), else each one's first ``SUBSTITUTES`` entry the set has, in the
    order of ``RUPPRECHT_SIX``; an input with neither is left out. Raises ``ParameterError``
    when fewer than ``MIN_INPUTS`` remain, naming what is missing."""
    have = set(mset.names)
    out, missing = [], []
    for name in RUPPRECHT_SIX:
        found = next((n for n in (name,) + SUBSTITUTES[name] if n in have), None)
        (out if found else missing).append(found or name)
    if len(out) < MIN_INPUTS:
        raise ParameterError(f"measurement set {mset.source}: only {len(out)} of the mapping's inputs "
                             f"({', '.join(out) or 'none'}) can be measured, expected at least {MIN_INPUTS}; missing "
                             + "; ".join(f"{n} (or {' / '.join(SUBSTITUTES[n])})" for n in missing)
                             + ": give the landmarks they need (docs/measurements.md)")
    return tuple(out)


# ---------------------------------------------------------------------- measurements of linear bodies
def subset(mset: MeasurementSet, names) -> MeasurementSet:
    """The measurement set restricted to ``names`` (in that order; dependencies kept)."""
    by_name = {m["name"]: m for m in mset.measurements}
    missing = [n for n in names if n not in by_name]
    if missing:
        raise ParameterError(f"measurement names {missing}: not in {mset.source} (it has {', '.join(by_name)})")
    need = list(names)
    for n in names:                                   # mass/bmi need their stature/mass entries
        for key in ("stature", "mass"):
            dep = by_name[n].get(key)
            if isinstance(dep, str) and dep not in need:
                need.insert(0, dep)
    return dataclasses.replace(mset, measurements=tuple(by_name[n] for n in need))


class LinearBodyMeasures:
    """Measurements (N, M) and their Jacobians (N, M, K) for bodies ``v = base + z @ C``.

    Only the vertices the measurements touch are reconstructed (the loops' rings and the
    landmarks' vertices), plus every vertex's height when a distance goes to the floor.

    Args:
        base: (V, 3) body at z = 0; basis: (K, V, 3) d v / d z_k.
        mset: measurement set; names: which of its measurements (loop, distance or path;
            default ``mapping_inputs(mset)``).
    """

    def __init__(self, base: np.ndarray, basis: np.ndarray, mset: MeasurementSet, names=None):
        self.names = mapping_inputs(mset) if names is None else tuple(names)
        by_name = {m["name"]: m for m in mset.measurements}
        self.defs = []
        for n in self.names:
            if n not in by_name:
                raise ParameterError(f"measurement {n!r}: not in {mset.source} (it has {', '.join(by_name)})")
            m = by_name[n]
            if m["method"] not in DIFFERENTIABLE:
                raise ParameterError(f"measurement {n!r}: method {m['method']!r} has no analytic Jacobian yet "
                                     f"(expected one of {', '.join(DIFFERENTIABLE)})")
            if m["method"] == "loop" and m.get("axis", "up") != "up":
                raise ParameterError(f"measurement {n!r}: loops are differentiated about the fixed 'up' axis only")
            self.defs.append(m)
        V = base.shape[0]
        lm_names = list(mset.landmarks)
        used = set()
        for m in self.defs:
            if m["method"] == "loop":
                used.update(int(i) for i in m["vertices"])
        for ids, _ in mset.landmarks.values():
            used.update(int(i) for i in ids)
        self.ids = np.array(sorted(used), dtype=np.int64)
        pos = {v: i for i, v in enumerate(self.ids)}
        self.lm_index = {n: i for i, n in enumerate(lm_names)}
        L = np.zeros((len(lm_names), len(self.ids)))
        for r, (ids, w) in enumerate(mset.landmarks.values()):
            for i, wi in zip(ids, w):
                L[r, pos[int(i)]] += wi
        self.L = L
        self.loop_pos = {m["name"]: np.array([pos[int(i)] for i in m["vertices"]]) for m in self.defs
                         if m["method"] == "loop"}
        base_u, basis_u = base[self.ids], basis[:, self.ids]                # (U, 3), (K, U, 3)
        self.lm_base = L @ base_u                                             # (Lm, 3)
        self.lm_basis = np.ascontiguousarray(np.einsum("lu,kud->kld", L, basis_u))   # (K, Lm, 3)
        self.rings = {name: (base_u[idx], np.ascontiguousarray(basis_u[:, idx]))
                      for name, idx in self.loop_pos.items()}
        self.needs_floor = any((m["method"] == "distance" and m["to"] == "floor") or m["method"] == "top"
                               for m in self.defs)
        # "top": the highest vertex of the part (the set's labels; without labels: of the body).
        self.top_ids = None
        tops = [m for m in self.defs if m["method"] == "top"]
        if tops:
            parts = tops[0]["part"]
            if mset.vertex_parts is not None:
                names = [parts] if isinstance(parts, str) else list(parts)
                self.top_ids = np.flatnonzero(np.isin(mset.vertex_parts, [PART_INDEX[p] for p in names]))
            else:
                self.top_ids = np.arange(V)
            if len({repr(m["part"]) for m in tops}) > 1:
                raise ParameterError("measurements of the method 'top' on different parts have no analytic "
                                     "Jacobian yet (expected one part)")
            self.top_base = np.ascontiguousarray(base[self.top_ids, 1])
            self.top_basis = np.ascontiguousarray(basis[:, self.top_ids, 1])
        if self.needs_floor:
            self.base_y = np.ascontiguousarray(base[:, 1])
            self.basis_y = np.ascontiguousarray(basis[:, :, 1])           # (K, V)
        self.n_vertices = V
        self.n_coefficients = basis.shape[0]
        self.box = None

    def restrict_floor(self, box: np.ndarray) -> "LinearBodyMeasures":
        """Speed-up, exact: for coefficients with ``|z_k| <= box[k]`` only vertices that can be
        the lowest somewhere in that box are searched for the floor (a vertex whose lowest
        possible height is above another's highest possible one never is). Outside the box all
        vertices are searched."""
        if not self.needs_floor:
            return self
        box = np.asarray(box, dtype=float)
        spread = np.abs(self.basis_y).T @ box                                 # (V,)
        cand = np.flatnonzero(self.base_y - spread <= np.min(self.base_y + spread))
        self.box, self.floor_ids = box, cand
        self.floor_base, self.floor_basis = self.base_y[cand], np.ascontiguousarray(self.basis_y[:, cand])
        return self

    @classmethod
    def from_model(cls, model, mset: MeasurementSet | None = None, names=None, k: int | None = None,
                   linearization=None):
        """For a ``BodyModel`` and its first ``k`` components (default all; 25 at most for RRE),
        with its measurement set (``model.measurement_set``) unless ``mset`` is given.

        The basis of ``model.encoder.linearize(space, k)``: exact for a linear encoding (vertex);
        for RRE the given ``linearization`` (an ``encoding.linearize.DecoderLinearization`` fitted
        on a training set) or by default the encoder's forward differences at the mean body
        (``k + 1`` decodes, cached), so ``measure_bodies`` gives exact values of
        decoded bodies with approximate Jacobians, and ``__call__`` measures the linearized bodies.
        Cached per model (weakly) and arguments: a second call for one request costs nothing.
        """
        mset = model.measurement_set if mset is None else mset
        names = mapping_inputs(mset) if names is None else tuple(names)
        key = (id(mset), names, k, id(linearization))
        try:
            per_model = _CACHE.setdefault(model, {})
        except TypeError:
            per_model = {}
        hit = per_model.get(key)
        if hit is not None and hit[0] is mset and hit[1] is model.space.components_ and hit[3] is linearization:
            return hit[2]
        out = cls._from_model(model, mset, names, k, linearization)
        per_model[key] = (mset, model.space.components_, out, linearization)
        return out

    @classmethod
    def _from_model(cls, model, mset, names, k, linearization=None):
        sp = model.space
        # The encoder's own linearization of its decoder (exact for a linear encoding, which a
        # fitted one could only approximate), unless a fitted one is given.
        if linearization is None or model.encoder.is_linear:
            linearization = model.encoder.linearize(sp, k)
        elif k is not None and linearization.k < min(int(k), sp.n_components_):
            raise ParameterError(f"linearization: covers {linearization.k} coefficients, expected at least k={k}")
        k = linearization.k if k is None else min(int(k), linearization.k)
        base, basis = linearization.base_, linearization.basis_[:k]
        return cls(base, basis, mset, names).restrict_floor(4.0 * np.sqrt(sp.explained_variance_[:k]))

    # ------------------------------------------------------------------ evaluation
    def _points(self, z, lm, spec):
        if isinstance(spec, str):
            return lm[:, self.lm_index[spec]]
        return np.mean([lm[:, self.lm_index[s]] for s in spec], axis=0)

    def _add_point(self, glm, spec, g):
        if isinstance(spec, str):
            glm[:, self.lm_index[spec]] += g
        else:
            for s in spec:
                glm[:, self.lm_index[s]] += g / len(spec)

    def _axis(self, lm, spec, n):
        if spec is None:
            return None
        if spec == "up":
            return np.broadcast_to(UP, (n, 3))
        d = self._points(None, lm, spec[1]) - self._points(None, lm, spec[0])
        return d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-15)

    def __call__(self, z: np.ndarray, jacobian: bool = False):
        """Measurements (N, M) in metres of coefficients z (N, k) or (k,); with ``jacobian`` also
        d measurement / d z (N, M, K)."""
        z = np.asarray(z, dtype=float)
        single = z.ndim == 1
        z = np.atleast_2d(z)
        K = self.n_coefficients
        if z.shape[1] < K:
            z = np.pad(z, ((0, 0), (0, K - z.shape[1])))
        elif z.shape[1] > K:
            z = z[:, :K]
        n = len(z)
        lm = self.lm_base + (z @ self.lm_basis.reshape(K, -1)).reshape(n, -1, 3)   # (N, Lm, 3)
        floor_y = low = None
        if self.needs_floor:
            if self.box is not None and np.all(np.abs(z) <= self.box):
                y = self.floor_base + z @ self.floor_basis
                low = np.argmin(y, axis=1)
                floor_y = y[np.arange(n), low]
                low = self.floor_ids[low]
            else:
                y = self.base_y + z @ self.basis_y
                low = np.argmin(y, axis=1)
                floor_y = y[np.arange(n), low]
        rings = {name: rb + (z @ rc.reshape(K, -1)).reshape(n, -1, 3) for name, (rb, rc) in self.rings.items()}
        top = None
        if self.top_ids is not None:
            y = self.top_base + z @ self.top_basis
            hi = np.argmax(y, axis=1)
            top = (y[np.arange(n), hi], self.top_ids[hi])
        out = self._measure(lm, rings, floor_y, low, jacobian, top)
        if single:
            return (out[0][0], out[1][0]) if jacobian else out[0]
        return out

    def measure_bodies(self, vertices: np.ndarray, jacobian: bool = False):
        """Measurements (N, M) in metres of given bodies ``vertices`` (N, V, 3) (e.g. truly decoded
        RRE bodies); with ``jacobian`` also d measurement / d z (N, M, K): the exact gradients with
        respect to those bodies' vertices, chained with this object's ``basis`` as dv/dz (for a
        non-linear decoder, its linearization: see ``encoding.linearize.DecoderLinearization``). The values
        are exact whatever the basis; the floor is searched over all vertices."""
        v = np.asarray(vertices, dtype=float)
        if v.ndim != 3 or v.shape[1:] != (self.n_vertices, 3):
            raise ParameterError(f"vertices: shape {v.shape}, expected (N, {self.n_vertices}, 3)")
        n = len(v)
        lm = np.einsum("lu,nud->nld", self.L, v[:, self.ids])
        rings = {name: v[:, self.ids[idx]] for name, idx in self.loop_pos.items()}
        floor_y = low = None
        if self.needs_floor:
            low = np.argmin(v[:, :, 1], axis=1)
            floor_y = v[np.arange(n), low, 1]
        top = None
        if self.top_ids is not None:
            hi = self.top_ids[np.argmax(v[:, self.top_ids, 1], axis=1)]
            top = (v[np.arange(n), hi, 1], hi)
        return self._measure(lm, rings, floor_y, low, jacobian, top)

    def _measure(self, lm, rings, floor_y, low, jacobian, top=None):
        """Values (N, M) and (with ``jacobian``) d/dz (N, M, K) from the touched points: landmarks
        lm (N, Lm, 3), loop rings (name -> (N, R, 3)), floor height (N,) and lowest vertex (N,),
        and ``top``: the part's highest height (N,) and vertex (N,)."""
        n, K = len(lm), self.n_coefficients
        vals = np.empty((n, len(self.defs)))
        J = np.empty((n, len(self.defs), K)) if jacobian else None
        for j, m in enumerate(self.defs):
            glm = np.zeros_like(lm) if jacobian else None
            gfloor = None
            meth = m["method"]
            if meth == "top":
                vals[:, j] = top[0] - floor_y
                if jacobian:
                    J[:, j] = self.basis_y[:, top[1]].T - self.basis_y[:, low].T
                continue
            if meth == "loop":
                rc = self.rings[m["name"]][1]
                val, g = loop_length_grad(rings[m["name"]], UP)
                if jacobian:
                    J[:, j] = g.reshape(n, -1) @ rc.reshape(K, -1).T
            elif meth == "path":
                pts = np.stack([self._points(None, lm, p) for p in m["through"]], axis=1)
                val, g = path_length_grad(pts)
                if jacobian:
                    for i, p in enumerate(m["through"]):
                        self._add_point(glm, p, g[:, i])
            else:  # distance
                a = self._points(None, lm, m["from"])
                if m["to"] == "floor":
                    b = a.copy()
                    b[:, 1] = floor_y
                else:
                    b = self._points(None, lm, m["to"])
                ax = self._axis(lm, m.get("axis"), n)
                val, ga, gb, gax = distance_grad(a, b, ax)
                if jacobian:
                    if m["to"] == "floor":      # b = a with y replaced by the floor height
                        ga = ga + gb * np.array([1.0, 0.0, 1.0])
                        gfloor = gb[:, 1]
                    else:
                        self._add_point(glm, m["to"], gb)
                    self._add_point(glm, m["from"], ga)
                    spec = m.get("axis")
                    if spec not in (None, "up"):
                        p0, p1 = self._points(None, lm, spec[0]), self._points(None, lm, spec[1])
                        g0, g1 = unit_vector_grad(p0, p1, gax)
                        self._add_point(glm, spec[0], g0)
                        self._add_point(glm, spec[1], g1)
            vals[:, j] = val
            if jacobian and meth != "loop":
                J[:, j] = glm.reshape(n, -1) @ self.lm_basis.reshape(K, -1).T
                if gfloor is not None:
                    J[:, j] += gfloor[:, None] * self.basis_y[:, low].T
        return (vals, J) if jacobian else vals
