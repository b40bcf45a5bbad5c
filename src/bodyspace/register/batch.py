"""A folder of raw scans registered (``bodyspace import SCANDIR --register``).

``register_files`` runs ``pipeline.register_scan`` on each scan (two at once on two cores) and
keeps, per scan, the registered body (template topology, metres, +Y up) or the reason it was refused: a file that
cannot be read, too few points (``prepare``), landmarks that cannot be used, or a fit whose
quality is under the threshold (``quality``: two people, an object, a partial scan). Nothing is
skipped silently: every refused scan comes back with its reason, and the caller lists them.

A scan's landmarks, when it has any, are a file beside it: ``NAME.lnd`` (CAESAR) or
``NAME.landmarks.json`` (``landmark_files.sidecar_landmarks``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bodyspace.data.template import Template
from bodyspace.errors import MeshError, RegistrationError
from bodyspace.measure.definitions import MeasurementSet
from bodyspace.parallel import cores, in_order
from bodyspace.register.landmark_files import read_scan_landmarks, sidecar_landmarks
from bodyspace.register.model_fit import ShapeBasis
from bodyspace.register.pipeline import DEFAULT_STEPS, register_scan
from bodyspace.register.prepare import read_scan
from bodyspace.register.quality import Quality
from bodyspace.rig.kinematics import matrix_to_rotvec

__all__ = ["ScanOutcome", "register_files"]


@dataclass
class ScanOutcome:
    """One scan of a batch.

    path: the scan file; accepted: registered and its quality accepted; reason: why not ('' if
    accepted); vertices: (V, 3) the registered body, metres, +Y up (None if refused); quality:
    the fit's ``Quality`` (None if it never got that far); mean_distance: metres, registered
    vertices to the scan; seconds: wall time; landmarks: the sidecar landmark file used, if any;
    notes: what was assumed (units, up axis) or read. units, up: the scan's length unit and up
    axis, given or found ('' if it never got that far). pose_degrees: the fit's largest joint turn
    from the template's rest pose (the root's turn left out), NaN if refused.
    """

    path: Path
    accepted: bool
    reason: str = ""
    vertices: np.ndarray | None = None
    quality: Quality | None = None
    mean_distance: float = float("nan")
    seconds: float = 0.0
    landmarks: Path | None = None
    notes: tuple = ()
    units: str = ""
    up: str = ""
    pose_degrees: float = float("nan")


def _largest_turn(rotations: np.ndarray, template: Template) -> float:
    """Degrees: the largest turn (B, 3, 3) ``rotations`` give a bone of the default rig, the root
    (the whole body's turn) left out."""
    nonroot = np.asarray(template.rigs["default"].parents) >= 0
    return float(np.degrees(np.linalg.norm(matrix_to_rotvec(np.asarray(rotations)[nonroot]), axis=-1)).max())


def register_files(paths: list[Path], *, template: Template, units: str | None = None, up: str | None = None,
                   basis: ShapeBasis | None = None, mset: MeasurementSet | None = None, steps: int = DEFAULT_STEPS,
                   progress=None, rng=0, workers: int | None = None) -> list[ScanOutcome]:
    """Register each scan of ``paths`` (module docstring); ``progress(message, fraction)`` is
    called before each scan and within it (with several workers: as each scan is done). Returns
    one ``ScanOutcome`` per path, in order.

    workers: scans registered at once, each in a forked process (``parallel.in_order``; default:
    the cores this process may use). A single registration keeps only part of a second core busy
    (its start fits and the NICP's halves), so two scans side by side finish a folder sooner. The
    fits do not depend on it: every scan runs with one BLAS thread either way.
    """
    report = progress or (lambda message, fraction: None)
    paths = [Path(p) for p in paths]
    n = len(paths)
    workers = max(1, min(cores() if workers is None else int(workers), n))
    _JOB.update(template=template, units=units, up=up, basis=basis, mset=mset, steps=steps, rng=rng, n=n,
                report=report if workers == 1 else None)
    out = []
    try:
        for i, outcome in enumerate(in_order(_register_one, ((i, p) for i, p in enumerate(paths)), workers, ahead=1,
                                             died="run the import again (or with fewer scans at once)")):
            if workers > 1:
                report(f"{outcome.path.name} ({i + 1}/{n}) {'registered' if outcome.accepted else 'refused'}",
                       (i + 1) / n)
            out.append(outcome)
    finally:
        _JOB.clear()
    report("done", 1.0)
    return out


# What the forked workers inherit (set before the pool forks: the template and the basis are not pickled).
_JOB: dict = {}


def _register_one(i: int, path: Path) -> ScanOutcome:
    """One scan of ``register_files``'s batch, as ``_JOB`` says: its outcome, refused with the
    reason when it cannot be read or fitted (the batch goes on)."""
    job = _JOB
    n, report = job["n"], job["report"] or (lambda message, fraction: None)
    start = time.perf_counter()
    head = f"{path.name} ({i + 1}/{n})"
    report(head, i / n)
    lm_path = sidecar_landmarks(path)
    try:
        points, faces = read_scan(path)
        lms, notes = (read_scan_landmarks(lm_path, flag="landmarks") if lm_path is not None else (None, []))

        def inner(message, fraction):
            report(f"{head}: {message}", (i + min(max(fraction, 0.0), 1.0)) / n)

        reg = register_scan(points, faces, template=job["template"], units=job["units"], up=job["up"], landmarks=lms,
                            basis=job["basis"], mset=job["mset"], steps=job["steps"], check=True, name=path.name,
                            progress=inner, rng=job["rng"], standing=False)
    except (MeshError, RegistrationError) as exc:
        return ScanOutcome(path, False, str(exc), seconds=time.perf_counter() - start, landmarks=lm_path)
    return ScanOutcome(path, True, "", reg.internal, reg.quality, float(np.mean(reg.distance)),
                       time.perf_counter() - start, lm_path, tuple(notes) + tuple(reg.assumed),
                       # found, not given: only the axis is (the fit finds which end is the head;
                       # the prepared sign is arbitrary and differed across one folder)
                       reg.units, reg.up if job["up"] is not None else reg.up.lstrip("-"),
                       _largest_turn(reg.pose.rotations, job["template"]))
