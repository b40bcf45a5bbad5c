"""The BodyModel bundle: template, encoder statistics and PCA shape space in one versioned file.

``BodyModel.fit(db, encoding="rre", selection="rest")`` encodes a scan database and fits the
shape space (Hasler §4): on the rest-pose scans it is the shape-only model
(Hasler §5.2), on all scans the model of pose and shape together. The algorithms live in
their owners (``encoding``, ``shape.ShapeSpace``, ``mapping``); this module orchestrates them
and owns the file format. ``save(path)`` writes one ``.npz`` (numpy's zip of ``.npy`` arrays,
no pickle) whose ``header`` array is UTF-8 JSON (format name, ``format_version``, encoder kind
and parameters, selection, provenance, the expected name, shape and dtype of every array);
``load`` reads it with ``allow_pickle=False`` and checks all of it, so loading never executes
code from the file.

Array layout of a model file (``FORMAT_VERSION = 3``); each part writes its own arrays
(``to_arrays(prefix)``) and reads them back (``from_arrays``)::

    header                  (B,) uint8      UTF-8 JSON, see above
    template_vertices       (V, 3) float64  metres
    faces                   (F, 3) int64
    encoder_*               the encoder's state (``ENCODERS[encoding].to_arrays("encoder_")``):
                            ``encoder_mean_vertices`` (V, 3) (placement reference), and for
                            "rre" ``encoder_mean_rotvecs`` (F, 3, 3) rad, ``encoder_mean_stretch`` (F, 6)
    pca_*                   the shape space (``ShapeSpace.to_arrays("pca_")``): mean (D,),
                            components (K, D) float32, explained_variance(_ratio), singular_values
                            (K,), n_samples (); optional vertex_variance (K,) (basis "vertex"
                            or "refined") and refine_levels (L, 2) float64 whole numbers (basis "refined"; a
                            file without them loads as before: no version change)
    fitted_scans            (N,) int64      rows of the source database the model was fitted on
    measurement_set         optional (B,) uint8: UTF-8 JSON of the model's measurement set
                            (``MeasurementSet.to_dict``: landmarks of its topology, conditions,
                            definitions; read back by ``measurement_set_from_dict``, data only);
                            the header's "measurement_set" summarizes it
    mapping_*               optional: the measurements-to-shape mapping (``mapping.bundle``);
                            the header's "mapping" names it
    semantics_*             optional: the semantic regressors (``SemanticModel.to_arrays``: labels,
                            regressors, region masks); the header's "semantics" names them

Version 1 files (bodyspace before the parts stored themselves) differ only in names:
``rre_mean_rotvecs`` / ``rre_mean_stretch`` for ``encoder_mean_*``, and the sample count in
the header alone (``V1_RENAMES``); they load. Version 1 and 2 files carry no measurement set: a
model of the template's topology gets the shipped hm08 set on load, any other none (a command
that measures then says how to give it one: ``build --landmarks FILE``).

Components are kept at float32 precision in memory too (float64 values exactly representable in
float32), so a saved model loads bit-exactly; the PCA itself runs in float64 up to
``FULL_PCA_MAX_BYTES`` of codes and in float32 with a randomized block Krylov method beyond
(``ShapeSpace(solver=...)``), see ``fit``.

How the encoder is fitted on large databases: the relative rotation encoder's mean model (the
reference the codes are relative to, docs/encoding.md) is averaged over at most
``ENCODER_FIT_MAX_SCANS`` scans spread evenly over the selection, then every selected scan is
encoded once. Any reference gives an exact, invertible encoding; the PCA mean is always the
mean over all selected codes. Up to that many scans (the tests) the encoder is fitted on all of
them; the demo's 144 scans use 64 (it halves the fit's encoding work).
"""

from __future__ import annotations

import hashlib
import json
import numbers
import os
import tempfile
import time
import warnings
import zipfile
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from bodyspace.atomic import atomic_path
from bodyspace.data.database import rest_pose_name, rest_pose_rows
from bodyspace.data.template import load_template
from bodyspace.encoding import ENCODERS
from bodyspace.errors import BodyspaceError, MeasurementError, ModelError, ParameterError
from bodyspace.mapping.bundle import PREFIX as MAPPING_PREFIX
from bodyspace.mapping.bundle import MeasurementMapping, fit_mapping
from bodyspace.mapping.refine import refine
from bodyspace.measure import MeasurementSet, load_measurement_set, measurement_set_from_dict
from bodyspace.measure.definitions import with_standing_body
from bodyspace.measure.landmark_check import check_set_on_bodies, landmark_measurement_set
from bodyspace.semantics.model import PREFIX as SEMANTICS_PREFIX
from bodyspace.semantics.model import (
    TOLERANCES,
    GenerationResult,
    SemanticModel,
    TargetError,
    tolerance,
)
from bodyspace.shape import ShapeSpace
from bodyspace.shape.pca import (
    FULL_PCA_MAX_BYTES,
    MAX_DEFAULT_COMPONENTS,
    SOLVERS,
    resolve_solver,
)
from bodyspace.rowfile import CheckpointedRows
from bodyspace.shape.solvers import KRYLOV_DEPTH
from bodyspace.units import format_value
from bodyspace.validation import as_seed

FORMAT = "bodyspace.BodyModel"
FORMAT_VERSION = 3
READABLE_VERSIONS = (1, 2, 3)
# The array holding the model's measurement set (UTF-8 JSON of ``MeasurementSet.to_dict``).
MEASUREMENT_SET_ARRAY = "measurement_set"
# What a model without a measurement set tells the user to do.
GIVE_LANDMARKS = ("build it with the landmarks of its topology: bodyspace build DB --landmarks FILE (or a "
                  "landmarks.json in the database folder, e.g. from bodyspace import --landmarks FILE); API: "
                  "BodyModel.fit(db, landmarks=FILE)")
# Array names of format version 1 -> version 2 (the encoder's own names).
V1_RENAMES = {"rre_mean_rotvecs": "encoder_mean_rotvecs", "rre_mean_stretch": "encoder_mean_stretch"}
ENCODER_PREFIX = "encoder_"
PCA_PREFIX = "pca_"
ENCODINGS = tuple(ENCODERS)
SELECTIONS = ("rest", "all")
# What fit does with scans that fold triangles (the relative rotation encoder's policy).
ON_FLIPPED = ("accept", "warn", "raise", "ignore")
# Relative rotation encoder: the mean model is averaged over at most this many scans.
ENCODER_FIT_MAX_SCANS = 64
# Scans read and encoded per call while building (~1 MB of vertices a scan); the next batch is
# read while this one is encoded (ScanDatabase.iter_chunks). The codes go straight into the
# (N, D) matrix.
ENCODE_BATCH = 64
_ZIP_MAGIC = b"PK\x03\x04"
# The kind (numpy dtype.kind) of the arrays load reads itself: the integer ones; every other
# template_/encoder_/pca_ array is float ("f"). An integer or string array there is refused
# (it would be cast silently and give a different model).
_INTEGER_FIELDS = ("faces", "fitted_scans", PCA_PREFIX + "n_samples")
_FLOAT_PREFIXES = ("template_", ENCODER_PREFIX, PCA_PREFIX)
# Spectra of the shape space: variances and singular values are >= 0, the ratios in [0, 1].
_NON_NEGATIVE_FIELDS = (PCA_PREFIX + "explained_variance", PCA_PREFIX + "explained_variance_ratio",
                        PCA_PREFIX + "singular_values", "fitted_scans")
_SEMANTICS_REFIT = "refit them (CLI: --database DB --refit)"

# Requested lengths of the measurement set (waist_size, thigh_girth_l, ...) are met to this by the
# exact refinement after the semantic closed loop; labels keep their closed-loop tolerances
# (semantics.model.TOLERANCES: stature 4 mm, mass 0.5 kg).
EXACT_LENGTH_TOLERANCE = 0.001

__all__ = ["BodyModel", "ModelError", "FORMAT_VERSION", "FULL_PCA_MAX_BYTES", "MAX_DEFAULT_COMPONENTS",
           "EXACT_LENGTH_TOLERANCE", "request_tolerance"]


def request_tolerance(semantics, name: str) -> float:
    """Tolerance (SI) a generated or morphed body meets ``name`` to: 1 mm for a length of the
    measurement set that is not a label with its own tolerance (stature 4 mm), else the
    closed loop's (``semantics.model.tolerance``)."""
    by_name = {m["name"]: m for m in semantics.mset.measurements}
    if name in by_name and by_name[name]["unit"] == "m" and name not in TOLERANCES:
        return EXACT_LENGTH_TOLERANCE
    return tolerance(name)


def _float32_exact(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, dtype=np.float32).astype(np.float64)


def _codes_key(db, rows: np.ndarray, encoding: str, encoder) -> str:
    """What a build's codes are computed from, hashed: the database (its folder, meta and the
    size and time of its vertex file), the selected rows, the encoding and the fitted encoder's
    state. Equal keys: the codes of an interrupted build can be continued."""
    digest = hashlib.sha256()
    source = {"folder": None if db.folder is None else str(Path(db.folder).resolve()), "meta": db.meta,
              "encoding": encoding}
    if db.folder is not None:
        stat = (Path(db.folder) / "vertices.npy").stat()
        source["vertices"] = [stat.st_size, stat.st_mtime_ns]
    else:
        digest.update(np.ascontiguousarray(db.vertices[:: max(1, len(db.vertices) // 64)]).tobytes())
    digest.update(json.dumps(source, sort_keys=True, default=str).encode())
    digest.update(np.ascontiguousarray(rows, dtype=np.int64).tobytes())
    for name, array in sorted(encoder.to_arrays().items()):
        digest.update(name.encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


class BodyModel:
    """Template, fitted encoder and PCA shape space; fit from a ScanDatabase, save and load.

    Attributes:
        template_vertices: (V, 3) metres; faces: (F, 3).
        template_id: str, the template the scans are registered to.
        encoding: a key of ``encoding.ENCODERS`` ("rre" relative rotations, or "vertex").
        encoder: the fitted encoder; space: the fitted ``ShapeSpace``.
        selection: "rest", "all" or "indices": which scans the model was fitted on.
        fitted_scans: (N,) int64 rows of the source database.
        provenance: dict (source database, sizes, timings, flipped scans, versions).
        measurement_set: the ``MeasurementSet`` of the model's topology (what ``generate``,
            ``mapping`` and ``measure --model`` measure with); raises ``MeasurementError``
            saying how to give one when the model has none (``has_measurement_set``).
    """

    def __init__(self, template_vertices, faces, encoder, space: ShapeSpace, *, encoding: str,
                 template_id: str = "unknown", selection: str = "all", fitted_scans=None,
                 encoder_params: dict | None = None, provenance: dict | None = None, mapping=None,
                 semantics=None, measurement_set: MeasurementSet | None = None):
        if encoding not in ENCODINGS:
            raise ParameterError(f"encoding={encoding!r}, expected one of {', '.join(ENCODINGS)}")
        self.template_vertices = np.asarray(template_vertices, dtype=float)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.encoder = encoder
        self.space = space
        self.encoding = encoding
        self.template_id = str(template_id)
        self.selection = selection
        self.fitted_scans = np.asarray([] if fitted_scans is None else fitted_scans, dtype=np.int64)
        self.encoder_params = dict(encoder_params or {})
        self.provenance = dict(provenance or {})
        # The fitted measurements-to-shape mapping (``mapping.bundle.MeasurementMapping``), or
        # None; ``fit_mapping`` makes one, ``save`` stores it in the same file.
        self.mapping = mapping
        # The fitted semantic regressors (``semantics.model.SemanticModel`` of this model), or
        # None; ``save`` stores them in the same file, ``load`` restores them.
        self.semantics = semantics
        self._measurement_set = None
        if measurement_set is not None:
            self.measurement_set = measurement_set

    # ------------------------------------------------------------------ the measurement set
    @property
    def has_measurement_set(self) -> bool:
        return self._measurement_set is not None

    @property
    def measurement_set(self) -> MeasurementSet:
        """The measurement set of the model's topology (stored in the model file)."""
        if self._measurement_set is None:
            raise MeasurementError(f"this model ({len(self.template_vertices)} vertices, template "
                                   f"{self.template_id!r}) carries no measurement set, so nothing can be measured or "
                                   f"asked on its bodies; {GIVE_LANDMARKS}")
        return self._measurement_set

    @measurement_set.setter
    def measurement_set(self, mset: MeasurementSet) -> None:
        if not isinstance(mset, MeasurementSet):
            raise ParameterError(f"measurement_set: got {type(mset).__name__}, expected a MeasurementSet")
        nv = len(self.template_vertices)
        if (mset.n_vertices is not None and mset.n_vertices != nv) or mset.max_vertex_id() >= nv:
            raise MeasurementError(f"{mset.source}: made for meshes of {mset.n_vertices} vertices (ids up to "
                                   f"{mset.max_vertex_id()}), but the model's have {nv}; give the landmarks of "
                                   "the model's topology")
        self._measurement_set = mset

    # ------------------------------------------------------------------ fitting
    @classmethod
    def fit(cls, db, encoding: str = "rre", selection="rest", n_components: int | float | None = None, *,
            template=None, on_flipped: str = "accept", pca_solver: str = "auto", rng=0,
            n_jobs: int | None = None, template_id: str | None = None, landmarks=None,
            basis: str = "code", progress: Callable[[str, float], None] | None = None,
            scratch: str | os.PathLike | None = None, codes_on_disk: bool | None = None,
            log: Callable[[str], None] | None = None) -> "BodyModel":
        """Encode the selected scans of ``db`` (a ``ScanDatabase``) and fit the shape space.

        Args:
            db: the scan database (meshes registered to one template).
            encoding: "rre" or "vertex" (``encoding.ENCODERS``).
            selection: "rest" (the rest-pose scans: the shape-only model), "all" (pose and
                shape together), or a boolean mask / integer indices over the scans.
            n_components: ``ShapeSpace``'s rule: None keeps every component with variance (at
                most ``MAX_DEFAULT_COMPONENTS``), an int that many, a float in (0, 1) the fewest
                that explain that fraction of the variance (exact solver only).
            template: the template the scans are registered to (a ``Template`` or (V, 3)
                vertices); default: the installed template when ``db.meta['template']`` names it
                and the faces match, else the mean of (up to 64) rest-pose scans.
            on_flipped: scans with folded (flipped) triangles: "accept" (default: encoded, and
                the scans counted in ``provenance["flipped_scans"]``), "warn" (also a warning
                per scan), "raise" (refuse the database), "ignore" (not looked for). Real
                registered meshes fold a few triangles in almost every scan.
            pca_solver: ``ShapeSpace``'s solver: "auto" (exact up to ``FULL_PCA_MAX_BYTES`` of
                float64 codes, else Krylov), "full" or "krylov" (randomized block Krylov, float32
                codes; needs an int or None n_components).
            rng: seed of the Krylov solver's start block.
            n_jobs: encoder and PCA threads (default: all cores).
            template_id: recorded in the file (default ``db.meta['template']``).
            landmarks: the measurement set the model keeps (``measurement_set``): a landmark
                file of the scans' topology (``measure.load_landmarks``; the hm08 set re-pointed
                at it, ``with_landmarks``), or a ``MeasurementSet``; default: the database
                folder's ``landmarks.json`` if it has one, else the shipped hm08 set when the
                scans are of the template's topology, else none. Checked on the rest scans
                (``measure.landmark_check.check_set_on_bodies``): ids on the mesh, every
                measurement defined and of a human size.
            basis: ``ShapeSpace``'s component order: "code" (Hasler's PCA of the codes) or
                "vertex" (code directions ordered by the vertex variance they carry: with RRE
                the first components move whole limbs; exact solver only; the scans are read
                once more for it), or "refined" (the vertex order refined for the vertex fit of
                the scans, ``shape.refine``: a few vertex fits of every scan, docs/encoding.md).
            progress: ``progress(message, fraction)``.
            scratch: folder of the temporary code file of an out-of-core fit (default: the
                system's temporary folder, ``TMPDIR``); it needs N x D x 4 bytes free.
            codes_on_disk: where the codes of a Krylov fit are kept: None (default) or True on
                disk (``rowfile.CheckpointedRows``, read in blocks: memory does not grow with N;
                a killed fit continues encoding where it stopped), False in memory (N x D
                float32; faster when they fit). The exact solver keeps them in memory (it is
                chosen only up to ``FULL_PCA_MAX_BYTES``).
            log: ``log(line)`` gets what the user should read (the encoding resumed or started cleanly).
        """
        report = progress or (lambda msg, frac: None)
        say = log or (lambda line: None)
        if encoding not in ENCODINGS:
            raise ParameterError(f"encoding={encoding!r}, expected one of {', '.join(ENCODINGS)}")
        if on_flipped not in ON_FLIPPED:
            raise ParameterError(f"on_flipped={on_flipped!r}, expected one of {', '.join(ON_FLIPPED)}")
        if pca_solver not in SOLVERS:
            raise ParameterError(f"pca_solver={pca_solver!r}, expected one of {', '.join(SOLVERS)}")
        rows, sel_name = _selected_rows(db, selection)
        n = len(rows)
        if n < 2:
            raise ParameterError(f"selection {sel_name!r}: {n} scan(s), expected at least 2 to fit a shape space")
        if template is not None:
            template_id = template_id or getattr(template, "template_id", None)
            template_vertices = np.asarray(getattr(template, "vertices", template), dtype=float)
        else:
            template_vertices = None
        faces = np.asarray(db.faces, dtype=np.int64)
        report("checking the measurement set", 0.0)
        mset = measurement_set_for(db, landmarks)
        t0 = time.perf_counter()
        timings = {}

        # 1. the encoder: its mean model
        report(f"fitting the {encoding} encoder", 0.0)
        fit_rows = rows if n <= ENCODER_FIT_MAX_SCANS else rows[np.linspace(0, n - 1, ENCODER_FIT_MAX_SCANS).round()
                                                                .astype(int)]
        fit_scans = db.read(fit_rows)
        if template_vertices is None:
            template_vertices = _template_for(db, faces)
        encoder_cls = ENCODERS[encoding]
        options = {"rotation_solver": "exact", "on_flipped": on_flipped, "n_jobs": n_jobs}
        params = {key: options[key] for key in encoder_cls.PARAMS}
        runtime = {key: options[key] for key in encoder_cls.RUNTIME_PARAMS}
        encoder = encoder_cls(template_vertices, faces, **params, **runtime).fit(fit_scans)
        del fit_scans
        timings["encoder_fit_s"] = time.perf_counter() - t0

        # 2. codes of every selected scan, in float64 (exact PCA) or float32 (Krylov)
        d = encoder.n_features_
        space = ShapeSpace(encoder, n_components, solver=pca_solver, copy=False, rng=rng, n_jobs=n_jobs,
                           basis=basis)
        solver = resolve_solver(pca_solver, n, d, n_components)
        # Beyond the exact solver's size the codes go to a file (a RowFile in ``scratch``) that
        # the Krylov solver reads in blocks: memory stays bounded whatever the number of scans.
        out_of_core = solver == "krylov" and codes_on_disk is not False
        flipped = np.zeros(n, dtype=np.int64)
        done, store = 0, None
        if out_of_core:
            # The codes of every scan, checkpointed chunk by chunk: a killed build continues
            # encoding where it stopped (same database, selection and encoder), or starts cleanly.
            store = CheckpointedRows(scratch if scratch is not None else tempfile.gettempdir(), "bodyspace-codes",
                                     _codes_key(db, rows, encoding, encoder), (n, d), np.float32)
            done, extra, said = store.open()
            say(f"encoding: {said}")
            flipped[:done] = np.asarray(extra.get("flipped", []), dtype=np.int64)[:done]
            codes = store.rows
            buffer = np.empty((ENCODE_BATCH, d), dtype=np.float32)
        else:
            codes = np.empty((n, d), dtype=np.float64 if solver == "full" else np.float32)
        complete = False
        try:
            t = time.perf_counter()
            for s, x in db.iter_chunks(rows[done:], ENCODE_BATCH):
                s += done
                if out_of_core:
                    encoder.encode(x, out=buffer[:len(x)])
                    codes.write(s, buffer[:len(x)])
                else:
                    encoder.encode(x, out=codes[s:s + len(x)])
                if encoder.last_flipped_ is not None:
                    flipped[s:s + len(x)] = encoder.last_flipped_
                if store is not None:
                    store.commit(s + len(x), {"flipped": flipped[:s + len(x)].tolist()})
                report(f"encoded {s + len(x)}/{n} scans", 0.05 + 0.75 * (s + len(x)) / n)
            timings["encode_s"] = time.perf_counter() - t

            # 3. PCA
            t = time.perf_counter()
            report(f"PCA of {n} codes of length {d}" + (f" (on disk, {codes.path})" if out_of_core else ""), 0.82)
            space.fit(codes, vertices=db.read(rows) if basis != "code" and not encoder.is_linear else None)
            complete = True
        finally:
            del codes
            if store is not None:
                store.close(remove=complete)
        # float32-exact components: what the file keeps, so a saved model loads bit-exactly.
        space.components_ = _float32_exact(space.components_)
        timings["pca_s"] = time.perf_counter() - t
        timings["total_s"] = time.perf_counter() - t0
        report("done", 1.0)
        checked = encoder.last_flipped_ is not None and on_flipped != "ignore"
        provenance = {
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "generator": "bodyspace.model.BodyModel.fit",
            "database": {"template": db.meta.get("template"), "scans": int(db.n_scans),
                         "subjects": int(db.n_subjects), "provenance": db.meta.get("provenance")},
            "fitted_scans": n,
            "subjects": sorted(set(np.asarray(db.scans["subject"])[rows].tolist())),
            "encoder_fit_scans": int(len(fit_rows)),
            # Scans with at least one folded triangle (None: the encoding does not look).
            "flipped_scans": int(np.count_nonzero(flipped)) if checked else None,
            "flipped_triangles_max": int(flipped.max()) if checked else None,
            "pca_solver": space.solver_,
            "codes_on_disk": bool(out_of_core),
            "pca_method": "gram_eigh" if space.solver_ == "full" else f"block_krylov(depth={KRYLOV_DEPTH})",
            "total_variance": space.total_variance_,
            "timings_s": {key: round(v, 3) for key, v in timings.items()},
        }
        provenance["measurement_set"] = None if mset is None else mset.source
        if mset is not None:
            # Body parts per vertex and the neck's joints from the landmarks on the standing template
            # of the scans, kept in the file: a posed body of this topology is then cut by the parts
            # of a standing one, and its neck girth's plane leans with its neck.
            mset = with_standing_body(mset, template_vertices, faces)
        return cls(template_vertices, faces, encoder, space, encoding=encoding,
                   template_id=template_id or db.meta.get("template", "unknown"), selection=sel_name,
                   fitted_scans=rows, encoder_params=params, provenance=provenance, measurement_set=mset)

    # ------------------------------------------------------------------ bodies
    @property
    def n_components(self) -> int:
        return int(self.space.n_components_)

    @property
    def mean_vertices(self) -> np.ndarray:
        """(V, 3) the encoder's mean model: every decoded body is placed onto it."""
        return self.encoder.mean_vertices_

    def encode(self, vertices) -> np.ndarray:
        """Codes (N, D) of registered meshes (V, 3) or (N, V, 3)."""
        return self.encoder.encode(vertices)

    def decode(self, codes, constraints=None) -> np.ndarray:
        """Bodies (N, V, 3) of codes (N, D) or (D,), placed on the mean model."""
        return self.encoder.decode(codes, constraints=constraints)

    def project(self, vertices, method: str = "vertex") -> np.ndarray:
        """Coefficients (N, K) of registered meshes (V, 3) or (N, V, 3): fitted to the mesh in
        vertex space (``method="vertex"``) or the code projection (``"code"``), see
        ``ShapeSpace.project``."""
        return self.space.project(vertices, method=method)

    def reconstruct(self, coefficients, constraints=None) -> np.ndarray:
        """Bodies (N, V, 3) of coefficients (N, k) or (k,), k <= K (the rest are 0)."""
        return self.space.reconstruct(coefficients, constraints=constraints)

    def sample_coefficients(self, n: int, n_components: int | None = None, sigma_range=2.0, rng=None):
        """Random coefficients (n, K), see ``ShapeSpace.sample_coefficients``."""
        return self.space.sample_coefficients(n, n_components, sigma_range, rng)

    def sample(self, n: int, n_components: int | None = None, sigma_range=2.0, rng=None) -> np.ndarray:
        """Random bodies (n, V, 3): Gaussian coefficients on the first ``n_components``
        components, truncated to ``sigma_range`` standard deviations (s or (lo, hi))."""
        return self.space.sample(n, n_components, sigma_range, rng)

    def fit_mapping(self, samples: int | None = None, k: int = 25, rng=0, n_trees: int = 50,
                    progress=None) -> "BodyModel":
        """Fit the measurements-to-shape mapping (forest, linear baseline; Rupprecht et al.) on a
        training set drawn from this model, keep it as ``self.mapping`` (saved with the model);
        returns self. ``rng``: Generator, seed or None. See ``mapping.bundle.fit_mapping``."""
        self.mapping = fit_mapping(self, samples, k, rng=as_seed(rng), n_trees=n_trees, progress=progress)
        return self

    # ------------------------------------------------------------------ requests (semantics + exact refinement)
    def _semantics(self) -> SemanticModel:
        if self.semantics is None:
            raise ParameterError("this BodyModel has no semantic regressors; fit them with "
                                 "model.semantics = SemanticModel(model).fit(db) (CLI: --database DB)")
        return self.semantics

    def generate(self, targets: dict, rng=None, sigma_range: float = 2.0,
                 accept_misses: bool = False) -> GenerationResult:
        """A random body that measures ``targets`` (``SemanticModel.generate``: name -> SI value,
        (lo, hi) or ``Target``): the semantic closed loop meets the labels, then, when a length of
        the measurement set is asked (waist_size, ...), the exact refinement meets it to 1 mm
        jointly with the other requests (``_meet_exactly``)."""
        sm = self._semantics()
        result = sm.generate(targets, rng=rng, sigma_range=sigma_range, defer_misses=self._asks_lengths(targets))
        return self._meet_exactly(result, accept_misses=accept_misses)

    def morph(self, vertices, changes: dict, keep=(), mask=None, accept_misses: bool = False) -> GenerationResult:
        """``SemanticModel.morph``, then the exact refinement of asked lengths as in ``generate``
        (on the morphed mesh: the model's body plus the mesh's own detail, or, within a mask,
        the masked blend of the change)."""
        sm = self._semantics()
        asked = {**dict(changes), **{name: name for name in keep}}
        result = sm.morph(vertices, changes, keep=keep, mask=mask, defer_misses=self._asks_lengths(asked))
        x0 = np.asarray(vertices, dtype=float)
        d0 = np.asarray(self.reconstruct(sm.project_mesh(x0).reshape(-1)))[0]
        weights = sm.mask_weights(mask)
        if weights is None:
            return self._meet_exactly(result, offset=x0 - d0, accept_misses=accept_misses)
        blend = sm.masked_blend(weights)

        def bodies(z):
            return np.array([x0 + blend(v - d0) for v in np.asarray(self.reconstruct(z))])
        return self._meet_exactly(result, bodies=bodies, accept_misses=accept_misses)

    def crowd(self, n: int, targets: dict, rng=None, progress=None, accept_misses: bool = False) -> list:
        """``n`` bodies meeting ``targets`` (values or ranges) as ``generate`` does, the rest random."""
        return list(self.iter_crowd(n, targets, rng=rng, progress=progress, accept_misses=accept_misses))

    def iter_crowd(self, n: int, targets: dict, rng=None, progress=None, accept_misses: bool = False):
        """The bodies of ``crowd`` one at a time (a generator of ``GenerationResult``), so a crowd
        of any size is written as it is made; the same bodies as ``crowd`` for the same ``rng``."""
        gen = np.random.default_rng(rng)
        for i in range(int(n)):
            yield self.generate(targets, rng=gen, accept_misses=accept_misses)
            if progress:
                progress(f"body {i + 1}/{n}", (i + 1) / n)

    def _asks_lengths(self, targets) -> bool:
        """Does the request name a length the exact refinement meets (``request_tolerance``)?"""
        return isinstance(targets, dict) and any(
            request_tolerance(self.semantics, getattr(t, "name", n)) == EXACT_LENGTH_TOLERANCE
            for n, t in targets.items())

    def _meet_exactly(self, result: GenerationResult, offset=None, bodies=None,
                      accept_misses: bool = False) -> GenerationResult:
        """The closed loop's ``result`` refined (``mapping.refine.refine``, general path) until the
        asked lengths of the measurement set are within ``EXACT_LENGTH_TOLERANCE``, jointly with
        every other request at its own tolerance: measured labels (stature, mass) measured on the
        body, the others (sex, age, ...) as their regressors linearized at the body (exact for the
        linear regressors). Unchanged when no such length is asked. A miss raises ``TargetError``
        naming it, unless ``accept_misses`` or the semantic model clamps (then a warning)."""
        sm = self._semantics()
        exact = [n for n in result.targets if request_tolerance(sm, n) == EXACT_LENGTH_TOLERANCE]
        if not exact:
            return result
        by_name = {m["name"]: m for m in sm.mset.measurements}
        c = np.asarray(result.coefficients, dtype=float)
        names, goal, tols, scale, linear = [], [], [], [], {}
        for name, value in result.targets.items():
            f = 100.0 if name in by_name and by_name[name]["unit"] == "m" else 1.0
            if name not in by_name:
                reg = sm.regressor(name)
                g = np.asarray(reg.gradient(c), dtype=float)
                linear[name] = (g, float(reg.predict(c)) - float(g @ c))
            names.append(name)
            goal.append(value * f)
            tols.append(request_tolerance(sm, name) * f)
            scale.append(f)
        t0 = time.perf_counter()
        # the box admits every training subject (sigma_limit, or further where one lies further out)
        r = refine(self, c, np.array(goal), names, mset=sm.mset, k=self.n_components,
                   max_sigma=sm.coefficient_bound, tolerances=np.array(tols), linear=linear, offset=offset,
                   bodies=bodies)
        z = np.asarray(r.coefficients, dtype=float)
        if bodies is not None:
            v = np.asarray(bodies(z[None]))[0]
        else:
            v = np.asarray(self.reconstruct(z))[0] + (0.0 if offset is None else offset)
        values = {n: float(m / f) for n, m, f in zip(names, r.measured, scale)}
        messages = list(result.messages)
        timings = dict(result.timings)
        timings["refine"] = time.perf_counter() - t0
        converged = not r.misses[0]
        if not converged:
            miss = ", ".join(f"{n} {format_value(n, values[n])} (asked {format_value(n, result.targets[n])}, "
                             f"tolerance {format_value(n, request_tolerance(sm, n))})" for n in r.misses[0])
            msg = (f"not met by the exact refinement: {miss}; no body within {sm.coefficient_bound:.3g} SD measures "
                   "all of the request (ask for less, or fewer constraints)")
            if not (accept_misses or sm.on_infeasible == "clamp"):
                raise TargetError(msg)
            warnings.warn(msg, RuntimeWarning, stacklevel=3)
            messages.append(msg)
        measured = sm.measure_body(v, list(result.measurements)) if result.measurements else {}
        start = c if result.start is None else np.asarray(result.start, dtype=float)
        maha = float(np.sqrt(np.sum((z[:len(start)] - start) ** 2 / np.maximum(sm.variances, 1e-300))))
        return GenerationResult(z, v, values, dict(result.targets), converged,
                                result.iterations + int(r.iterations[0]), maha, timings, messages,
                                {k: float(val) for k, val in measured.items()}, start)

    def __repr__(self) -> str:
        return (f"BodyModel({self.encoding}, {self.n_components} components, fitted on {len(self.fitted_scans)} "
                f"{self.selection} scans, template={self.template_id!r}"
                + (f", mapping from {len(self.mapping.names)} measurements" if self.mapping is not None else "") + ")")

    # ------------------------------------------------------------------ files
    def _arrays(self) -> dict[str, np.ndarray]:
        """Every array of the file but the header: each part's own (``to_arrays(prefix)``)."""
        arrays = {"template_vertices": self.template_vertices.astype(np.float64),
                  "faces": self.faces.astype(np.int64)}
        arrays.update(self.encoder.to_arrays(ENCODER_PREFIX))
        arrays.update(self.space.to_arrays(PCA_PREFIX))
        arrays["fitted_scans"] = self.fitted_scans.astype(np.int64)
        if self.mapping is not None:
            arrays.update(self.mapping.to_arrays(MAPPING_PREFIX))
        if self.semantics is not None:
            arrays.update(self.semantics.to_arrays(SEMANTICS_PREFIX))
        if self._measurement_set is not None:
            text = json.dumps(self._measurement_set.to_dict(), allow_nan=False)
            arrays[MEASUREMENT_SET_ARRAY] = np.frombuffer(text.encode("utf-8"), dtype=np.uint8)
        return arrays

    def save(self, path) -> Path:
        """Write the model to one ``.npz`` file (atomically); returns the path."""
        path = Path(path)
        arrays = self._arrays()
        header = {
            "format": FORMAT, "format_version": FORMAT_VERSION, "encoding": self.encoding,
            "encoder_params": self.encoder_params, "template_id": self.template_id,
            "selection": self.selection, "n_samples": int(self.space.n_samples_),
            "n_components": self.n_components, "n_vertices": int(len(self.template_vertices)),
            "n_faces": int(len(self.faces)), "n_features": int(self.space.n_features_in_),
            "units": {"length": "m", "rre_code": "rotation vectors (rad) and stretch (1) per triangle",
                      "vertex_code": "m"},
            "provenance": self.provenance,
            "mapping": None if self.mapping is None else {"names": list(self.mapping.names), "k": self.mapping.k,
                                                          "samples": self.mapping.samples, "units": "cm"},
            "semantics": None if self.semantics is None else {"labels": list(self.semantics.labels_),
                                                              "lengths": len(self.semantics.lengths_)},
            "measurement_set": None if self._measurement_set is None else {
                "source": self._measurement_set.source, "landmarks": len(self._measurement_set.landmarks),
                "measurements": list(self._measurement_set.names)},
            "arrays": {name: {"shape": list(a.shape), "dtype": a.dtype.str} for name, a in arrays.items()},
        }
        arrays["header"] = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        return path

    @staticmethod
    def read_measurement_set(path) -> MeasurementSet | None:
        """The measurement set of a model file (None: it has none), without building its encoder
        and shape space (``measure --model``: an RRE model's encoder takes seconds to set up).
        The header, template and stored set are checked as ``load`` checks them."""
        path, archive = _open_archive(path)
        with archive:
            header = _read_header(path, _field(path, archive, "header"))
            v, f = _field(path, archive, "template_vertices"), _field(path, archive, "faces")
            _check_fields(path, {"template_vertices": v, "faces": f, "fitted_scans": np.zeros(0, dtype=np.int64)})
            raw = _field(path, archive, MEASUREMENT_SET_ARRAY) if MEASUREMENT_SET_ARRAY in header["arrays"] else None
        return _stored_measurement_set(path, raw, header["format_version"], v, f)

    @classmethod
    def load(cls, path, n_jobs: int | None = None, semantics: bool = True) -> "BodyModel":
        """Read a model file written by ``save`` (``allow_pickle=False``; every field checked).
        Files of format version 1 load too (``V1_RENAMES``). ``semantics=False`` leaves stored
        semantic regressors unread (to refit damaged ones)."""
        path, archive = _open_archive(path)
        with archive:
            def field(name: str) -> np.ndarray:
                return _field(path, archive, name)

            header = _read_header(path, field("header"))
            version, encoding = header["format_version"], header["encoding"]
            a = {}
            for name, spec in header["arrays"].items():
                if not semantics and name.startswith(SEMANTICS_PREFIX):
                    continue  # left unread: damaged regressors must not stop their refit
                try:
                    value = field(name)
                    if list(value.shape) != list(spec.get("shape", [])) or value.dtype.str != spec.get("dtype"):
                        raise ModelError(f"{path}: field '{name}' has shape {value.shape} and dtype "
                                         f"{value.dtype.str}, the header says {tuple(spec.get('shape', []))} and "
                                         f"{spec.get('dtype')}")
                except ModelError as exc:
                    if not name.startswith(SEMANTICS_PREFIX):
                        raise
                    raise ModelError(f"{exc}; the stored semantic regressors are damaged: "
                                     f"{_SEMANTICS_REFIT}") from None
                a[name] = value
            required = ["template_vertices", "faces", "fitted_scans", "encoder_mean_vertices"] + [
                PCA_PREFIX + s for s in ("mean", "components", "explained_variance", "explained_variance_ratio",
                                         "singular_values")]
            for name in required:
                if name not in a:
                    a[name] = field(name)  # raises when missing from the file
        if version == 1:
            a = {V1_RENAMES.get(name, name): value for name, value in a.items()}
            a[PCA_PREFIX + "n_samples"] = np.asarray(header.get("n_samples", 0), dtype=np.int64)
        _check_fields(path, a)
        v, f = a["template_vertices"], a["faces"]
        mapping = None
        if any(name.startswith(MAPPING_PREFIX) for name in a):
            try:
                mapping = MeasurementMapping.from_arrays(a, MAPPING_PREFIX)
            except BodyspaceError as exc:
                raise ModelError(f"{path}: the stored mapping does not load ({exc})") from None
        params = header["encoder_params"]
        encoder_cls = ENCODERS[encoding]
        runtime = {"n_jobs": n_jobs} if "n_jobs" in encoder_cls.RUNTIME_PARAMS else {}
        try:
            encoder = encoder_cls.from_arrays(a, ENCODER_PREFIX, v, f, **params, **runtime)
        except (BodyspaceError, TypeError, ValueError) as exc:
            raise ModelError(f"{path}: the stored template/encoder fields do not make an encoder ({exc})") from None
        try:
            space = ShapeSpace.from_arrays(a, PCA_PREFIX, encoder)
        except BodyspaceError as exc:
            raise ModelError(f"{path}: the stored shape space does not load ({exc})") from None
        model = cls(v, f, encoder, space, encoding=encoding, template_id=header.get("template_id", "unknown"),
                    selection=header.get("selection", "all"), fitted_scans=a["fitted_scans"],
                    encoder_params=params, provenance=header.get("provenance"), mapping=mapping)
        model._measurement_set = _stored_measurement_set(path, a.get(MEASUREMENT_SET_ARRAY), version, v, f)
        if semantics and any(name.startswith(SEMANTICS_PREFIX) for name in a):
            try:
                model.semantics = SemanticModel.from_arrays(a, model, SEMANTICS_PREFIX)
            except BodyspaceError as exc:
                raise ModelError(f"{path}: the stored semantic regressors do not load ({exc}); "
                                 f"{_SEMANTICS_REFIT}") from None
        return model


# ----------------------------------------------------------------------------------- helpers

def _open_archive(path) -> tuple[Path, "np.lib.npyio.NpzFile"]:
    """(path, the open .npz) of a model file; ``ModelError`` for a bad path, a file that is not a
    zip archive (model files are never pickles) or one numpy cannot open."""
    if not isinstance(path, (str, os.PathLike)) or str(path) == "":
        raise ModelError(f"model path {path!r}: expected the path (str or Path) of a BodyModel .npz written by "
                         "BodyModel.save (CLI: bodyspace build)")
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: no such file; expected a BodyModel .npz written by BodyModel.save "
                         "(CLI: bodyspace build)")
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic != _ZIP_MAGIC:
        raise ModelError(f"{path}: not a BodyModel file (starts with {magic!r}, expected an .npz zip archive "
                         "written by BodyModel.save); model files are never pickles")
    try:
        return path, np.load(path, allow_pickle=False)
    except (ValueError, OSError, zipfile.BadZipFile) as exc:
        raise ModelError(f"{path}: cannot be read as an .npz archive ({exc})") from None


def _field(path, archive, name: str) -> np.ndarray:
    """One array of an open model file; ``ModelError`` when missing, pickled or damaged."""
    if name not in archive.files:
        raise ModelError(f"{path}: field '{name}' is missing; the file has "
                         f"{', '.join(sorted(archive.files)) or 'no arrays'}")
    try:
        return archive[name]
    except ValueError as exc:  # object arrays: pickled data, refused
        raise ModelError(f"{path}: field '{name}' cannot be loaded without pickle ({exc}); "
                         "expected a plain numeric array") from None
    except (OSError, zipfile.BadZipFile, EOFError) as exc:
        raise ModelError(f"{path}: field '{name}' is damaged ({exc})") from None


def _read_header(path, raw: np.ndarray) -> dict:
    """The header JSON of a model file, every field the loader relies on checked for its type."""
    if raw.dtype != np.uint8 or raw.ndim != 1:
        raise ModelError(f"{path}: field 'header' has dtype {raw.dtype} and shape {raw.shape}, expected "
                         "(B,) uint8 JSON")
    try:
        header = json.loads(raw.tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelError(f"{path}: field 'header' is not UTF-8 JSON ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        found = header.get("format") if isinstance(header, dict) else type(header).__name__
        raise ModelError(f"{path}: header format {found!r}, expected {FORMAT!r}")
    version = header.get("format_version")
    if version not in READABLE_VERSIONS or isinstance(version, bool):
        newer = isinstance(version, int) and version > FORMAT_VERSION
        raise ModelError(f"{path}: format_version {version!r}, this bodyspace reads versions "
                         f"{', '.join(map(str, READABLE_VERSIONS))}{' (a newer bodyspace wrote it; upgrade)' if newer else ''}")
    encoding = header.get("encoding")
    if encoding not in ENCODINGS:
        raise ModelError(f"{path}: header field 'encoding' is {encoding!r}, expected one of "
                         f"{', '.join(ENCODINGS)}")
    arrays = header.get("arrays")
    if not isinstance(arrays, dict) or not all(
            isinstance(spec, dict) and isinstance(spec.get("shape"), list) and isinstance(spec.get("dtype"), str)
            for spec in arrays.values()):
        raise ModelError(f"{path}: header field 'arrays' is {type(arrays).__name__ if not isinstance(arrays, dict) else 'malformed'}, "
                         "expected {name: {\"shape\": [...], \"dtype\": \"<f8\"}} for every array")
    n_samples = header.get("n_samples", 0)
    if not isinstance(n_samples, numbers.Integral) or isinstance(n_samples, bool) or n_samples < 0:
        raise ModelError(f"{path}: header field 'n_samples' is {n_samples!r}, expected a count (int >= 0)")
    params = header.get("encoder_params") or {}
    if not isinstance(params, dict):
        raise ModelError(f"{path}: header field 'encoder_params' is {params!r}, expected an object")
    header["encoder_params"] = dict(params)
    for key in ("template_id", "selection"):
        if key in header and not isinstance(header[key], str):
            raise ModelError(f"{path}: header field '{key}' is {header[key]!r}, expected a string")
    if header.get("provenance") is not None and not isinstance(header["provenance"], dict):
        raise ModelError(f"{path}: header field 'provenance' is {header['provenance']!r}, expected an object")
    return header


def _check_field(path, name, ok, found, expected) -> None:
    if not ok:
        raise ModelError(f"{path}: field '{name}' has shape {tuple(found)}, expected {expected}")


def _check_fields(path, a: dict[str, np.ndarray]) -> None:
    """Kinds, shapes and values of the arrays load reads itself (``a``: name -> array); the
    parts (encoder, shape space, mapping, semantics) check theirs when they are built."""
    for name, value in a.items():
        if name in _INTEGER_FIELDS:
            if value.dtype.kind not in "iu":
                raise ModelError(f"{path}: field '{name}' has dtype {value.dtype}, expected integers (int64)")
        elif name.startswith(_FLOAT_PREFIXES) and value.dtype.kind != "f":
            raise ModelError(f"{path}: field '{name}' has dtype {value.dtype}, expected floating point numbers "
                             "(float32/float64)")
        if value.dtype.kind == "f" and not np.isfinite(value).all():
            hint = (f"; the stored semantic regressors are damaged: {_SEMANTICS_REFIT}"
                    if name.startswith(SEMANTICS_PREFIX) else "")
            raise ModelError(f"{path}: field '{name}' contains NaN or infinity{hint}")
    for name in _NON_NEGATIVE_FIELDS:
        if name in a and a[name].size and a[name].min() < 0:
            raise ModelError(f"{path}: field '{name}' has negative values (min {a[name].min():.6g}), expected "
                             "values >= 0")
    ratio = a.get(PCA_PREFIX + "explained_variance_ratio")
    if ratio is not None and ratio.size and ratio.max() > 1 + 1e-6:
        raise ModelError(f"{path}: field '{PCA_PREFIX}explained_variance_ratio' has values above 1 (max "
                         f"{ratio.max():.6g}), expected fractions of the variance in [0, 1]")
    v, f, scans = a["template_vertices"], a["faces"], a["fitted_scans"]
    _check_field(path, "template_vertices", v.ndim == 2 and v.shape[1] == 3, v.shape, "(V, 3)")
    _check_field(path, "faces", f.ndim == 2 and f.shape[1] == 3, f.shape, "(F, 3) int")
    _check_field(path, "fitted_scans", scans.ndim == 1, scans.shape, "(N,) int")


def _selected_rows(db, selection) -> tuple[np.ndarray, str]:
    if isinstance(selection, str):
        if selection == "all":
            return np.arange(db.n_scans), "all"
        if selection == "rest":
            # The database's own rest-pose rule (meta 'rest_pose', set by `bodyspace import`).
            rows = rest_pose_rows(db.scans, db.meta)
            if len(rows) == 0:
                raise ParameterError(f"selection 'rest': no scan has pose '{rest_pose_name(db.meta)}'")
            return rows, "rest"
        raise ParameterError(f"selection={selection!r}, expected 'rest', 'all', a boolean mask or scan indices")
    sel = np.asarray(selection)
    rows = np.flatnonzero(sel) if sel.dtype == bool else sel.astype(np.int64).ravel()
    if sel.dtype == bool and sel.shape != (db.n_scans,):
        raise ParameterError(f"selection: mask of shape {sel.shape}, expected ({db.n_scans},)")
    if len(rows) and (rows.min() < 0 or rows.max() >= db.n_scans):
        raise ParameterError(f"selection: indices {rows.min()}..{rows.max()}, expected 0..{db.n_scans - 1}")
    return rows, "indices"


def _template_for(db, faces: np.ndarray) -> np.ndarray:
    """The template mesh of a database: the installed template when the database names it
    (``meta['template']``) and the topology matches, else the mean of its rest-pose scans."""
    try:
        template = load_template()
        if template.template_id == db.meta.get("template") and np.array_equal(template.faces, faces):
            return np.asarray(template.vertices, dtype=float)
    except BodyspaceError:
        pass
    rows = rest_pose_rows(db.scans, db.meta)
    rows = rows if len(rows) else np.arange(db.n_scans)
    return db.read(rows[:64]).mean(axis=0)


def _is_template_topology(n_vertices: int, faces: np.ndarray) -> bool:
    """Are meshes of ``n_vertices`` and ``faces`` the installed template's topology (the one the
    shipped hm08 measurement set is made for)? Without the assets: by the vertex count."""
    default_n = load_measurement_set().n_vertices
    if n_vertices != default_n:
        return False
    try:
        return bool(np.array_equal(load_template().faces, faces))
    except BodyspaceError:
        return True


def measurement_set_for(db, landmarks=None) -> MeasurementSet | None:
    """The measurement set a model of ``db`` keeps (see ``BodyModel.fit``'s ``landmarks``):
    checked on (up to 16 of) the database's rest scans, None for scans of another topology
    without a landmark file."""
    if isinstance(landmarks, MeasurementSet):
        mset = landmarks
    else:
        path = landmarks if landmarks is not None else getattr(db, "landmarks_path", None)
        if path is None:
            if _is_template_topology(db.n_vertices, np.asarray(db.faces)):
                return load_measurement_set()
            return None
        mset = landmark_measurement_set(path, db.n_vertices)
    rows = rest_pose_rows(db.scans, db.meta)
    rows = rows if len(rows) else np.arange(db.n_scans)
    rows = rows[np.linspace(0, len(rows) - 1, min(len(rows), 16)).round().astype(int)]
    check = check_set_on_bodies(mset, db.read(rows), db.faces, f"the rest scans of the database ({len(rows)} checked)")
    grouped: dict = {}
    for name, (count, why) in check.partly_undefined.items():
        grouped.setdefault((count, why), []).append(name)
    for (count, why), names in grouped.items():
        warnings.warn(f"{mset.source}: {', '.join(names)} undefined on {count} of {check.n_bodies} rest scans checked "
                      f"({why}); kept: defined on the others", RuntimeWarning, stacklevel=3)
    return mset


def check_landmark_file(path, db) -> str:
    """The text of landmark file ``path`` once it is checked against database ``db`` (its vertex
    count, ids on faces, every measurement of the set it gives defined on the rest scans and of
    a human size: ``measurement_set_for``), for a copy into the database folder."""
    measurement_set_for(db, Path(path))
    return Path(path).read_text(encoding="utf-8")


def _stored_measurement_set(path, raw, version: int, vertices: np.ndarray, faces: np.ndarray):
    """The measurement set of a model file: the stored one (version 3; ``raw`` its UTF-8 JSON
    array, or None: the model has none), or for version 1 and 2 files the shipped hm08 set when
    the model is of the template's topology, else None."""
    if raw is None:
        return load_measurement_set() if version < 3 and _is_template_topology(len(vertices), faces) else None
    if raw.dtype != np.uint8 or raw.ndim != 1:
        raise ModelError(f"{path}: field '{MEASUREMENT_SET_ARRAY}' has dtype {raw.dtype} and shape {raw.shape}, "
                         "expected (B,) uint8 JSON")
    try:
        doc = json.loads(raw.tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelError(f"{path}: field '{MEASUREMENT_SET_ARRAY}' is not UTF-8 JSON ({exc})") from None
    source = doc.get("source") if isinstance(doc, dict) else None
    try:
        mset = measurement_set_from_dict(doc, f"{path}: measurement set"
                                              + (f" (from {source})" if isinstance(source, str) else ""))
    except MeasurementError as exc:
        raise ModelError(f"{path}: the stored measurement set does not load ({exc})") from None
    if (mset.n_vertices is not None and mset.n_vertices != len(vertices)) or mset.max_vertex_id() >= len(vertices):
        raise ModelError(f"{path}: the stored measurement set is for meshes of {mset.n_vertices} vertices (ids up to "
                         f"{mset.max_vertex_id()}), but the model's template has {len(vertices)}")
    if isinstance(source, str):
        mset = replace(mset, source=source)
    return mset
