"""The BodyModel bundle: template, encoder statistics and PCA shape space in one versioned file.

``BodyModel.fit(db, encoding="rre", selection="rest")`` encodes a scan database and fits the
shape space (Hasler et al. 2009, Sec. 4): on the rest-pose scans it is the shape-only model
(their Sec. 5.2), on all scans the model of pose and shape together. ``save(path)`` writes one
``.npz`` (numpy's zip of ``.npy`` arrays, no pickle) whose ``header`` array is UTF-8 JSON
(format name, ``format_version``, encoder kind and parameters, selection, provenance, the
expected name, shape and dtype of every array); ``load`` reads it with ``allow_pickle=False``
and checks all of it, so loading never executes code from the file.

Array layout of a model file (``FORMAT_VERSION = 1``)::

    header                  (B,) uint8      UTF-8 JSON, see above
    template_vertices       (V, 3) float64  metres
    faces                   (F, 3) int64
    encoder_mean_vertices   (V, 3) float64  the encoder's mean model (placement reference)
    rre_mean_rotvecs        (F, 3, 3) float64  radians   (encoding "rre" only)
    rre_mean_stretch        (F, 6) float64             (encoding "rre" only)
    pca_mean                (D,) float64    mean code
    pca_components          (K, D) float32  principal directions, by decreasing variance
    pca_explained_variance  (K,) float64
    pca_explained_variance_ratio (K,) float64
    pca_singular_values     (K,) float64
    fitted_scans            (N,) int64      rows of the source database the model was fitted on
    mapping_*               optional: the measurements-to-shape mapping (``mapping.bundle``:
                            names, k, the forest's and the linear map's flat arrays, the RRE
                            decoder linearization); the header's "mapping" names it
    semantics_*             optional: the semantic regressors (``SemanticModel.to_arrays``: labels,
                            regressors, region masks); the header's "semantics" names them

Components are kept at float32 precision in memory too (float64 values exactly representable in
float32), so a saved model loads bit-exactly; the PCA itself runs in float64 up to
``FULL_PCA_MAX_BYTES`` of codes and in float32 with a randomized block Krylov method beyond
(``pca_solver``), see ``fit``.

How the encoder is fitted on large databases: the relative rotation encoder's mean model (the
reference the codes are relative to, docs/encoding.md) is averaged over at most
``ENCODER_FIT_MAX_SCANS`` scans spread evenly over the selection, then every selected scan is
encoded once. Any reference gives an exact, invertible encoding; the PCA mean is always the
mean over all selected codes. Up to that many scans (the tests) the encoder is fitted on all of
them; the demo's 144 scans use 64 (it halves the fit's encoding work).
"""

from __future__ import annotations

import json
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

import numpy as np

from bodyspace.atomic import atomic_path
from bodyspace.encoding import RelativeRotationEncoder, VertexEncoder
from bodyspace.encoding.rotations import quaternion_exp
from bodyspace.errors import BodyspaceError, ParameterError
from bodyspace.mapping.bundle import PREFIX as MAPPING_PREFIX
from bodyspace.mapping.bundle import MeasurementMapping
from bodyspace.semantics.model import PREFIX as SEMANTICS_PREFIX
from bodyspace.semantics.model import SemanticModel
from bodyspace.shape import ShapeSpace
from bodyspace.shape.solvers import (
    KRYLOV_DEPTH,
    mean_and_scatter,
    pca_block_krylov,
    pca_full,
)

FORMAT = "bodyspace.BodyModel"
FORMAT_VERSION = 1
ENCODINGS = ("rre", "vertex")
SELECTIONS = ("rest", "all")
# Relative rotation encoder: the mean model is averaged over at most this many scans.
ENCODER_FIT_MAX_SCANS = 64
# Scans read and encoded per call while building (~1 MB of vertices a scan); the next batch is
# read while this one is encoded. The codes go straight into the (N, D) matrix.
ENCODE_BATCH = 64
# Up to this many bytes of float64 codes, the PCA is exact (Gram matrix, float64); beyond, the
# codes are held in float32 and the leading components found by a randomized block Krylov
# method (pca_block_krylov).
FULL_PCA_MAX_BYTES = 2_000_000_000
# n_components=None keeps every component with variance, at most this many.
MAX_DEFAULT_COMPONENTS = 100
_ZIP_MAGIC = b"PK\x03\x04"


class ModelError(BodyspaceError):
    """A BodyModel file is not one, has another format version, or misses or garbles a field."""


# ----------------------------------------------------------------------------------- encoders

def rre_from_state(template_vertices, faces, mean_rotvecs, mean_stretch, mean_vertices,
                   **params) -> RelativeRotationEncoder:
    """A fitted ``RelativeRotationEncoder`` from stored statistics, without refitting.

    Args:
        template_vertices: (V, 3); faces: (F, 3).
        mean_rotvecs: (F, 3, 3) mean rotation vector per face and edge slot (radians).
        mean_stretch: (F, 6) mean stretch per face.
        mean_vertices: (V, 3) the mean model's mesh.
        params: constructor keywords (rotation_solver, on_flipped, n_jobs).
    """
    # Files written while the default decoder was iterative also carry its step settings.
    params = {k: v for k, v in params.items() if k not in ("tol", "max_iter")}
    enc = RelativeRotationEncoder(template_vertices, faces, **params)
    rot = np.asarray(mean_rotvecs, dtype=float)
    stretch = np.asarray(mean_stretch, dtype=float)
    if rot.shape != (enc.n_faces, 3, 3) or stretch.shape != (enc.n_faces, 6):
        raise ModelError(f"encoder statistics: rotvecs {rot.shape} and stretch {stretch.shape}, expected "
                         f"({enc.n_faces}, 3, 3) and ({enc.n_faces}, 6) for this template")
    enc.mean_rotvecs_ = rot
    enc.mean_stretch_ = stretch
    # The encoder keeps the mean rotations as component-first quaternions (4, F, 3), what its
    # own fit derives from mean_rotvecs_ (rre.py: ``_qexp(_planar(mean_rotvecs_, 3))``).
    enc._mean_q = np.ascontiguousarray(np.moveaxis(quaternion_exp(rot), -1, 0))
    enc.mean_vertices_ = np.asarray(mean_vertices, dtype=float)
    return enc


def vertex_from_state(template_vertices, faces, mean_vertices) -> VertexEncoder:
    """A fitted ``VertexEncoder`` whose generalized-Procrustes mean is ``mean_vertices`` (V, 3)."""
    enc = VertexEncoder(template_vertices, faces)
    enc.mean_vertices_ = np.asarray(mean_vertices, dtype=float)
    return enc


def shape_space_from_state(encoder, mean, components, explained_variance, explained_variance_ratio,
                           singular_values, n_samples: int) -> ShapeSpace:
    """A fitted ``ShapeSpace`` from its learned arrays (``mean_`` (D,), ``components_`` (K, D) ...)."""
    space = ShapeSpace(encoder, n_components=len(components))
    space.mean_ = np.asarray(mean, dtype=float)
    space.components_ = np.asarray(components, dtype=float)
    space.explained_variance_ = np.asarray(explained_variance, dtype=float)
    space.explained_variance_ratio_ = np.asarray(explained_variance_ratio, dtype=float)
    space.singular_values_ = np.asarray(singular_values, dtype=float)
    space.n_components_ = int(len(components))
    space.n_samples_ = int(n_samples)
    space.n_features_in_ = int(space.mean_.shape[0])
    return space


# ----------------------------------------------------------------------------------- PCA

# ----------------------------------------------------------------------------------- the bundle

def _float32_exact(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, dtype=np.float32).astype(np.float64)


class BodyModel:
    """Template, fitted encoder and PCA shape space; fit from a ScanDatabase, save and load.

    Attributes:
        template_vertices: (V, 3) metres; faces: (F, 3).
        template_id: str, the template the scans are registered to.
        encoding: "rre" (relative rotation encoding) or "vertex".
        encoder: the fitted encoder; space: the fitted ``ShapeSpace``.
        selection: "rest", "all" or "indices": which scans the model was fitted on.
        fitted_scans: (N,) int64 rows of the source database.
        provenance: dict (source database, sizes, timings, versions).
    """

    def __init__(self, template_vertices, faces, encoder, space: ShapeSpace, *, encoding: str,
                 template_id: str = "unknown", selection: str = "all", fitted_scans=None,
                 encoder_params: dict | None = None, provenance: dict | None = None, mapping=None,
                 semantics=None):
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

    # ------------------------------------------------------------------ fitting
    @classmethod
    def fit(cls, db, encoding: str = "rre", selection="rest", n_components: int | float | None = None, *,
            template=None, on_flipped: str = "raise", pca_solver: str = "auto", rng=0,
            n_jobs: int | None = None, template_id: str | None = None, progress: Callable[[str, float], None] | None = None) -> "BodyModel":
        """Encode the selected scans of ``db`` (a ``ScanDatabase``) and fit the shape space.

        Args:
            db: the scan database (meshes registered to one template).
            encoding: "rre" or "vertex".
            selection: "rest" (the rest-pose scans: the shape-only model), "all" (pose and
                shape together), or a boolean mask / integer indices over the scans.
            n_components: None keeps every component with variance (at most
                ``MAX_DEFAULT_COMPONENTS``), an int that many, a float in (0, 1) the fewest that
                explain that fraction of the variance (exact PCA only).
            template: the template the scans are registered to (a ``Template`` or (V, 3)
                vertices); default: the installed template when ``db.meta['template']`` names it
                and the faces match, else the mean of (up to 64) rest-pose scans.
            on_flipped: the relative rotation encoder's policy for folded triangles ("raise",
                "warn", "ignore"; the LBS-posed synthetic population needs "warn"/"ignore").
            pca_solver: "auto" (exact up to ``FULL_PCA_MAX_BYTES`` of float64 codes), "full" or
                "randomized" (needs an int n_components).
            rng: seed of the randomized PCA's start block.
            n_jobs: encoder and PCA threads (default: all cores).
            template_id: recorded in the file (default ``db.meta['template']``).
            progress: ``progress(message, fraction)``.
        """
        report = progress or (lambda msg, frac: None)
        if encoding not in ENCODINGS:
            raise ParameterError(f"encoding={encoding!r}, expected one of {', '.join(ENCODINGS)}")
        if pca_solver not in ("auto", "full", "randomized"):
            raise ParameterError(f"pca_solver={pca_solver!r}, expected 'auto', 'full' or 'randomized'")
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
        t0 = time.perf_counter()
        timings = {}

        # 1. the encoder: its mean model
        report(f"fitting the {encoding} encoder", 0.0)
        fit_rows = rows if n <= ENCODER_FIT_MAX_SCANS else rows[np.linspace(0, n - 1, ENCODER_FIT_MAX_SCANS).round()
                                                                .astype(int)]
        fit_scans = _read(db, fit_rows)
        if template_vertices is None:
            template_vertices = _template_for(db, faces)
        if encoding == "rre":
            params = {"rotation_solver": "exact", "on_flipped": on_flipped}
            encoder = RelativeRotationEncoder(template_vertices, faces, n_jobs=n_jobs, **params).fit(fit_scans)
        else:
            params = {}
            encoder = VertexEncoder(template_vertices, faces).fit(fit_scans)
        del fit_scans
        timings["encoder_fit_s"] = time.perf_counter() - t0

        # 2. codes of every selected scan, in float64 or (large) float32
        d = encoder.n_features_
        full = pca_solver == "full" or (pca_solver == "auto" and n * d * 8 <= FULL_PCA_MAX_BYTES)
        if not full and not (isinstance(n_components, (int, np.integer)) or n_components is None):
            raise ParameterError(f"n_components={n_components!r}: a variance fraction needs the exact PCA; for "
                                 f"{n} scans (> {FULL_PCA_MAX_BYTES / 1e9:.0f} GB of codes) pass an int")
        codes = np.empty((n, d), dtype=np.float64 if full else np.float32)
        t = time.perf_counter()
        starts = range(0, n, ENCODE_BATCH)
        with ThreadPoolExecutor(1) as reader:
            batch = reader.submit(_read, db, rows[:ENCODE_BATCH])
            for s in starts:
                x = batch.result()
                if s + ENCODE_BATCH < n:
                    batch = reader.submit(_read, db, rows[s + ENCODE_BATCH:s + 2 * ENCODE_BATCH])
                if encoding == "rre":
                    encoder.encode(x, out=codes[s:s + len(x)])
                else:
                    codes[s:s + len(x)] = encoder.encode(x)
                report(f"encoded {s + len(x)}/{n} scans", 0.05 + 0.75 * (s + len(x)) / n)
        timings["encode_s"] = time.perf_counter() - t
        # Mean and total variance (for explained_variance_ratio_), in float64 whatever the storage.
        t = time.perf_counter()
        mean, ss = mean_and_scatter(codes)
        timings["statistics_s"] = time.perf_counter() - t

        # 3. PCA
        t = time.perf_counter()
        report(f"PCA of {n} codes of length {d}", 0.82)
        if full:
            sv, comps = pca_full(codes, mean)
        else:
            k = min(n - 1, MAX_DEFAULT_COMPONENTS) if n_components is None else int(n_components)
            if not 1 <= k < n:
                raise ParameterError(f"n_components={n_components}, expected 1..{n - 1} for {n} scans")
            sv, comps = pca_block_krylov(codes, mean, k, rng=rng, n_jobs=n_jobs)
        del codes
        var = sv ** 2 / (n - 1)
        ratio = var / (ss / (n - 1)) if ss > 0 else np.zeros_like(var)
        k = _n_keep(n_components, var, ratio, n) if full else len(var)
        timings["pca_s"] = time.perf_counter() - t
        space = shape_space_from_state(encoder, mean, _float32_exact(comps[:k]), var[:k], ratio[:k], sv[:k], n)
        timings["total_s"] = time.perf_counter() - t0
        report("done", 1.0)
        provenance = {
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "generator": "bodyspace.model.BodyModel.fit",
            "database": {"template": db.meta.get("template"), "scans": int(db.n_scans),
                         "subjects": int(db.n_subjects), "provenance": db.meta.get("provenance")},
            "fitted_scans": n,
            "subjects": sorted(set(np.asarray(db.scans["subject"])[rows].tolist())),
            "encoder_fit_scans": int(len(fit_rows)),
            "pca_solver": "full" if full else "randomized",
            "pca_method": "gram_eigh" if full else f"block_krylov(depth={KRYLOV_DEPTH})",
            "total_variance": ss / (n - 1),
            "timings_s": {key: round(v, 3) for key, v in timings.items()},
        }
        return cls(template_vertices, faces, encoder, space, encoding=encoding,
                   template_id=template_id or db.meta.get("template", "unknown"), selection=sel_name,
                   fitted_scans=rows, encoder_params=params, provenance=provenance)

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

    def project(self, vertices) -> np.ndarray:
        """Coefficients (N, K) of registered meshes (V, 3) or (N, V, 3)."""
        return self.space.project(vertices)

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

    def fit_mapping(self, samples: int | None = None, k: int = 25, seed: int = 0, n_trees: int = 50,
                    progress=None) -> "BodyModel":
        """Fit the measurements-to-shape mapping (forest, linear baseline; Rupprecht et al.) on a
        training set drawn from this model, keep it as ``self.mapping`` (saved with the model);
        returns self. See ``mapping.bundle.fit_mapping``."""
        from bodyspace.mapping.bundle import fit_mapping
        self.mapping = fit_mapping(self, samples, k, seed=seed, n_trees=n_trees, progress=progress)
        return self

    def __repr__(self) -> str:
        return (f"BodyModel({self.encoding}, {self.n_components} components, fitted on {len(self.fitted_scans)} "
                f"{self.selection} scans, template={self.template_id!r}"
                + (f", mapping from {len(self.mapping.names)} measurements" if self.mapping is not None else "") + ")")

    # ------------------------------------------------------------------ files
    def _arrays(self) -> dict[str, np.ndarray]:
        sp = self.space
        arrays = {
            "template_vertices": self.template_vertices.astype(np.float64),
            "faces": self.faces.astype(np.int64),
            "encoder_mean_vertices": np.asarray(self.encoder.mean_vertices_, dtype=np.float64),
            "pca_mean": np.asarray(sp.mean_, dtype=np.float64),
            "pca_components": np.asarray(sp.components_, dtype=np.float32),
            "pca_explained_variance": np.asarray(sp.explained_variance_, dtype=np.float64),
            "pca_explained_variance_ratio": np.asarray(sp.explained_variance_ratio_, dtype=np.float64),
            "pca_singular_values": np.asarray(sp.singular_values_, dtype=np.float64),
            "fitted_scans": self.fitted_scans.astype(np.int64),
        }
        if self.encoding == "rre":
            arrays["rre_mean_rotvecs"] = np.asarray(self.encoder.mean_rotvecs_, dtype=np.float64)
            arrays["rre_mean_stretch"] = np.asarray(self.encoder.mean_stretch_, dtype=np.float64)
        if self.mapping is not None:
            arrays.update(self.mapping.to_arrays(MAPPING_PREFIX))
        if self.semantics is not None:
            arrays.update(self.semantics.to_arrays(SEMANTICS_PREFIX))
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
            "arrays": {name: {"shape": list(a.shape), "dtype": a.dtype.str} for name, a in arrays.items()},
        }
        arrays["header"] = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        return path

    @classmethod
    def load(cls, path, n_jobs: int | None = None, semantics: bool = True) -> "BodyModel":
        """Read a model file written by ``save`` (``allow_pickle=False``; every field checked).
        ``semantics=False`` leaves stored semantic regressors unread (to refit damaged ones)."""
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
            archive = np.load(path, allow_pickle=False)
        except (ValueError, OSError, zipfile.BadZipFile) as exc:
            raise ModelError(f"{path}: cannot be read as an .npz archive ({exc})") from None
        with archive:
            def field(name: str) -> np.ndarray:
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

            raw = field("header")
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
            if version != FORMAT_VERSION:
                raise ModelError(f"{path}: format_version {version!r}, this bodyspace reads version {FORMAT_VERSION}"
                                 f"{' (a newer bodyspace wrote it; upgrade)' if isinstance(version, int) and version > FORMAT_VERSION else ''}")
            encoding = header.get("encoding")
            if encoding not in ENCODINGS:
                raise ModelError(f"{path}: header field 'encoding' is {encoding!r}, expected one of "
                                 f"{', '.join(ENCODINGS)}")
            expected = header.get("arrays")
            if not isinstance(expected, dict):
                raise ModelError(f"{path}: header field 'arrays' is missing")
            a = {}
            for name, spec in expected.items():
                value = field(name)
                if list(value.shape) != list(spec.get("shape", [])) or value.dtype.str != spec.get("dtype"):
                    raise ModelError(f"{path}: field '{name}' has shape {value.shape} and dtype {value.dtype.str}, "
                                     f"the header says {tuple(spec.get('shape', []))} and {spec.get('dtype')}")
                a[name] = value
            required = ["template_vertices", "faces", "encoder_mean_vertices", "pca_mean", "pca_components",
                        "pca_explained_variance", "pca_explained_variance_ratio", "pca_singular_values",
                        "fitted_scans"] + (["rre_mean_rotvecs", "rre_mean_stretch"] if encoding == "rre" else [])
            for name in required:
                if name not in a:
                    a[name] = field(name)  # raises when missing from the file
        v, f = a["template_vertices"], a["faces"]
        k, d = a["pca_components"].shape
        _check_field(path, "template_vertices", v.ndim == 2 and v.shape[1] == 3, v.shape, "(V, 3)")
        _check_field(path, "faces", f.ndim == 2 and f.shape[1] == 3 and f.dtype.kind in "iu", f.shape, "(F, 3) int")
        _check_field(path, "encoder_mean_vertices", a["encoder_mean_vertices"].shape == v.shape,
                     a["encoder_mean_vertices"].shape, str(v.shape))
        _check_field(path, "pca_mean", a["pca_mean"].shape == (d,), a["pca_mean"].shape, f"({d},)")
        for name in ("pca_explained_variance", "pca_explained_variance_ratio", "pca_singular_values"):
            _check_field(path, name, a[name].shape == (k,), a[name].shape, f"({k},)")
        for name, value in a.items():
            if value.dtype.kind == "f" and not np.isfinite(value).all():
                raise ModelError(f"{path}: field '{name}' contains NaN or infinity")
        mapping = None
        if any(name.startswith(MAPPING_PREFIX) for name in a):
            try:
                mapping = MeasurementMapping.from_arrays(a, MAPPING_PREFIX)
            except BodyspaceError as exc:
                raise ModelError(f"{path}: the stored mapping does not load ({exc})") from None
        params = dict(header.get("encoder_params") or {})
        try:
            if encoding == "rre":
                encoder = rre_from_state(v, f, a["rre_mean_rotvecs"], a["rre_mean_stretch"],
                                         a["encoder_mean_vertices"], n_jobs=n_jobs, **params)
            else:
                encoder = vertex_from_state(v, f, a["encoder_mean_vertices"])
        except (BodyspaceError, TypeError, ValueError) as exc:
            raise ModelError(f"{path}: the stored template/encoder fields do not make an encoder ({exc})") from None
        _check_field(path, "pca_mean", d == encoder.n_features_, (d,), f"({encoder.n_features_},) for this template")
        space = shape_space_from_state(encoder, a["pca_mean"], a["pca_components"].astype(np.float64),
                                       a["pca_explained_variance"], a["pca_explained_variance_ratio"],
                                       a["pca_singular_values"], header.get("n_samples", 0))
        model = cls(v, f, encoder, space, encoding=encoding, template_id=header.get("template_id", "unknown"),
                    selection=header.get("selection", "all"), fitted_scans=a["fitted_scans"],
                    encoder_params=params, provenance=header.get("provenance"), mapping=mapping)
        if semantics and any(name.startswith(SEMANTICS_PREFIX) for name in a):
            try:
                model.semantics = SemanticModel.from_arrays(a, model, SEMANTICS_PREFIX)
            except BodyspaceError as exc:
                raise ModelError(f"{path}: the stored semantic regressors do not load ({exc}); refit them "
                                 "(CLI: --database DB --refit)") from None
        return model


# ----------------------------------------------------------------------------------- helpers

def _check_field(path, name, ok, found, expected) -> None:
    if not ok:
        raise ModelError(f"{path}: field '{name}' has shape {tuple(found)}, expected {expected}")


def _n_keep(n_components, var, ratio, n) -> int:
    if n_components is None:
        return int(min(len(var), MAX_DEFAULT_COMPONENTS))
    if isinstance(n_components, (int, np.integer)) and not isinstance(n_components, bool):
        if not 1 <= n_components <= len(var):
            raise ParameterError(f"n_components={n_components}, expected 1..{len(var)} (components with variance "
                                 f"among {n} scans)")
        return int(n_components)
    if isinstance(n_components, float) and 0 < n_components < 1:
        return int(min(np.searchsorted(np.cumsum(ratio), n_components) + 1, len(var)))
    raise ParameterError(f"n_components={n_components!r}, expected None, an int or a float in (0, 1)")


def _selected_rows(db, selection) -> tuple[np.ndarray, str]:
    if isinstance(selection, str):
        if selection == "all":
            return np.arange(db.n_scans), "all"
        if selection == "rest":
            from bodyspace.data.database import REST_POSE
            rows = np.flatnonzero(np.asarray(db.scans["pose"]) == REST_POSE)
            if len(rows) == 0:
                raise ParameterError(f"selection 'rest': no scan has pose '{REST_POSE}'")
            return rows, "rest"
        raise ParameterError(f"selection={selection!r}, expected 'rest', 'all', a boolean mask or scan indices")
    sel = np.asarray(selection)
    rows = np.flatnonzero(sel) if sel.dtype == bool else sel.astype(np.int64).ravel()
    if sel.dtype == bool and sel.shape != (db.n_scans,):
        raise ParameterError(f"selection: mask of shape {sel.shape}, expected ({db.n_scans},)")
    if len(rows) and (rows.min() < 0 or rows.max() >= db.n_scans):
        raise ParameterError(f"selection: indices {rows.min()}..{rows.max()}, expected 0..{db.n_scans - 1}")
    return rows, "indices"


def _read(db, rows: np.ndarray) -> np.ndarray:
    """(n, V, 3) float64 scans ``rows`` of a (memory-mapped) database, read in index order."""
    order = np.argsort(rows, kind="stable")
    out = np.empty((len(rows),) + tuple(db.vertices.shape[1:]))
    out[order] = db.vertices[rows[order]]
    return out


def _template_for(db, faces: np.ndarray) -> np.ndarray:
    """The template mesh of a database: the installed template when the database names it
    (``meta['template']``) and the topology matches, else the mean of its rest-pose scans."""
    try:
        from bodyspace.data.template import load_template
        template = load_template()
        if template.template_id == db.meta.get("template") and np.array_equal(template.faces, faces):
            return np.asarray(template.vertices, dtype=float)
    except BodyspaceError:
        pass
    rows, _ = _selected_rows(db, "rest") if (np.asarray(db.scans["pose"]) == "rest").any() else (np.arange(db.n_scans), "")
    return _read(db, rows[:64]).mean(axis=0)
