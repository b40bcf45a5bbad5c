"""Pose spread study: how far each measurement of a posed body is from the same body's rest value,
measured as posed and measured after unposing (issue 12, "What it must show").

Subjects are drawn like the synthetic database's (``synth.population.sample_subjects``: survey
statures and BMIs, the other phenotype parameters at random), each is posed in the library's
poses by linear blend skinning on the ground (as ``build_population`` poses them), and every
measurement of the set is taken three ways: on the rest body (the reference), on the posed mesh
as it is (the tape on the posed body, ``measure.evaluate``, whatever that does today), and on
the body ``rig.unpose.unpose`` brings back from the posed mesh alone. The target for the
unposed values: within 1 cm of the rest value in every pose.

Data only; ``report.pose_spread_report`` writes the Markdown table. Cost: one measurement of
every body three times and one unposing per posed body (about a minute for 4 subjects x 39
poses on two loaded cores).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from bodyspace.data.template import Template
from bodyspace.errors import ParameterError
from bodyspace.measure import evaluate, load_measurement_set
from bodyspace.measure.evaluate import Measurement
from bodyspace.rig.posing import pose_bodies
from bodyspace.rig.unpose import unpose
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.population import sample_subjects
from bodyspace.synth.poses import load_pose_library

__all__ = ["PoseSpread", "pose_spread_study"]


@dataclass
class PoseSpread:
    """Measurements of S subjects in P poses, M measurements (display units: cm, kg, m^3, ...).

    rest: (S, M) on the rest bodies; posed, unposed: (S, P, M) measured as posed and after
    unposing (NaN where undefined; ``posed_notes`` / ``unposed_notes`` (S, P, M) say why).
    unpose_error_mm: (S, P) mean vertex distance of the unposed body from the true rest body
    (after removing the mean offset). unpose_seconds: wall time of unposing all bodies.
    """

    names: list[str]
    units: list[str]
    methods: list[str]
    poses: list[str]
    subjects: np.ndarray            # (S, 11) phenotypes
    rest: np.ndarray
    posed: np.ndarray
    unposed: np.ndarray
    posed_notes: np.ndarray
    unposed_notes: np.ndarray
    unpose_error_mm: np.ndarray
    unpose_seconds: float

    def change(self, which: str) -> np.ndarray:
        """(S, P, M) value minus the subject's rest value, ``which`` = "posed" or "unposed"."""
        return getattr(self, which) - self.rest[:, None, :]

    def summary(self) -> list[dict]:
        """Per measurement: for "posed" and "unposed", the median and worst |change| over subjects and
        poses, the pose of the worst, how many values are undefined, and how many poses keep every
        subject within ``tolerance`` (1 cm for lengths, 1 kg, 1 % of the rest value otherwise)."""
        out = []
        for m, name in enumerate(self.names):
            row = {"name": name, "unit": self.units[m], "method": self.methods[m],
                   "rest_median": float(np.nanmedian(self.rest[:, m]))}
            tol = _tolerance(self.units[m], row["rest_median"])
            row["tolerance"] = tol
            for which in ("posed", "unposed"):
                d = np.abs(self.change(which)[:, :, m])
                undefined = int(np.isnan(d).sum())
                finite = np.where(np.isnan(d), -np.inf, d)
                worst = np.unravel_index(int(np.argmax(finite)), d.shape)
                row[which] = {
                    "median": float(np.nanmedian(d)) if undefined < d.size else float("nan"),
                    "worst": float(finite[worst]) if undefined < d.size else float("nan"),
                    "worst_pose": self.poses[worst[1]],
                    "undefined": undefined,
                    "poses_within": int(np.sum(np.all(d <= tol, axis=0))),
                }
            out.append(row)
        return out


def _tolerance(unit: str, rest: float) -> float:
    """The change still counted as "the same" in a display unit: 1 cm, 1 kg, else 1 %."""
    return {"cm": 1.0, "kg": 1.0}.get(unit, 0.01 * abs(rest))


def _values(measured: dict[str, Measurement], n: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, M) display values and (N, M) notes (object) of a batch evaluation."""
    vals = np.empty((n, len(measured)))
    notes = np.empty((n, len(measured)), dtype=object)
    for j, m in enumerate(measured.values()):
        v, _ = m.display()
        vals[:, j] = np.asarray(v, dtype=float).reshape(n)
        notes[:, j] = list(m.note) if isinstance(m.note, list) else [m.note] * n
    return vals, notes


def pose_spread_study(template: Template, n_subjects: int = 4, poses: Sequence[str] | None = None, rng=0,
                      rig: str = "default", progress: Callable[[str, float], None] | None = None) -> PoseSpread:
    """Measure ``n_subjects`` drawn subjects in ``poses`` (default: every library pose) three ways.

    template: the ``Template``; rig: the rig that poses and unposes them; rng: for the subjects.
    Returns a ``PoseSpread``.
    """
    report = progress or (lambda m, f: None)
    library = load_pose_library()
    poses = list(library.names) if poses is None else list(poses)
    if not poses or n_subjects < 1:
        raise ParameterError(f"pose_spread_study: {n_subjects} subjects, poses {poses!r}; expected at least one "
                             "of each")
    skeleton = template.rigs[rig]
    model = PhenotypeModel(template)
    report("drawing subjects", 0.0)
    subjects = sample_subjects(model, n_subjects, rng)
    rest = model.vertices(subjects.phenotypes)
    rest -= rest[..., 1].min(axis=1)[:, None, None] * np.array([0.0, 1.0, 0.0])
    mset = load_measurement_set()
    # Mass from volume with the set's default age and sex for every body: the study compares a body
    # with itself.
    measured = evaluate(mset, rest, template.faces)
    names = list(measured)
    units = [m.display()[1] for m in measured.values()]
    methods = [m.method for m in measured.values()]
    rest_vals, _ = _values(measured, n_subjects)

    R = library.stack(poses, skeleton)
    S, P, M = n_subjects, len(poses), len(names)
    posed_v, unposed_v = np.empty((S, P, M)), np.empty((S, P, M))
    posed_n, unposed_n = np.empty((S, P, M), dtype=object), np.empty((S, P, M), dtype=object)
    error = np.empty((S, P))
    seconds = 0.0
    for s in range(S):
        report(f"subject {s + 1}/{S}: posing, measuring, unposing", 0.1 + 0.9 * s / S)
        bodies = pose_bodies(np.repeat(rest[s:s + 1], P, axis=0), skeleton, R, on_ground=True)
        # A posed body's bounding box can exceed a standing one's (arms overhead): no scale check.
        got = evaluate(mset, bodies, template.faces, check_scale=False)
        posed_v[s], posed_n[s] = _values(got, P)
        t = time.perf_counter()
        back, _, _ = unpose(bodies, skeleton)
        seconds += time.perf_counter() - t
        d = back - rest[s]
        d -= d.mean(axis=1, keepdims=True)
        error[s] = 1000 * np.linalg.norm(d, axis=2).mean(axis=1)
        got = evaluate(mset, back, template.faces)
        unposed_v[s], unposed_n[s] = _values(got, P)
    report("done", 1.0)
    return PoseSpread(names, units, methods, poses, subjects.phenotypes, rest_vals, posed_v, unposed_v,
                      posed_n, unposed_n, error, seconds)
