"""Foot contacts and the foot-skating measures (Rupprecht §3.3.3; the measures of the
character-animation literature).

Arrays in, arrays out: ``positions`` are (F, K, 3) tracks of K foot joints (ankles, toes) in
metres, our axes (+Y up), the floor at y = 0.

* **Contact** (``detect_contacts``): a foot joint is in contact in a frame when it is less than
  ``CONTACT_HEIGHT`` (5 cm) above its planted height and its horizontal speed is below
  ``CONTACT_SPEED`` (0.5 m/s; a swinging foot moves at 2-5 m/s in the CMU walks, a planted one
  at a few cm/s of marker noise). The planted height of a joint (its *clearance*: an ankle sits
  ~8 cm above the floor when the foot is flat) is its 5th-percentile height over the clip,
  unless given. Runs of contact shorter than ``MIN_RUN`` frames are dropped (single-frame
  flickers at the threshold).
* **Skating** (``skating``): over the contact frames, the share of frames in which the joint has
  slid more than ``SLIDE`` (2.5 cm) horizontally from where its contact run began, and the mean
  horizontal speed during contact (m/s).
* **Penetration** (``penetration``): how far below the floor a set of points goes (metres,
  0 when never below).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyspace.errors import MotionError

__all__ = ["CONTACT_HEIGHT", "CONTACT_SPEED", "SLIDE", "Skating", "contact_runs", "detect_contacts",
           "horizontal_speed", "penetration", "skating"]

CONTACT_HEIGHT = 0.05      # m above the joint's planted height
CONTACT_SPEED = 0.5        # m/s horizontal
SLIDE = 0.025              # m from where the contact began
MIN_RUN = 3                # frames
_CLEARANCE_PERCENTILE = 5.0


def _check_positions(positions) -> np.ndarray:
    p = np.asarray(positions, dtype=float)
    if p.ndim != 3 or p.shape[2] != 3:
        raise MotionError(f"positions: shape {p.shape}, expected (frames, joints, 3) in metres")
    if not np.isfinite(p).all():
        raise MotionError("positions: NaN or infinity found; expected finite joint positions")
    return p


def horizontal_speed(positions: np.ndarray, frame_time: float) -> np.ndarray:
    """(F, K) horizontal speed (m/s) of each track: central differences, one-sided at the ends
    (zero for a single frame)."""
    p = _check_positions(positions)[..., [0, 2]]
    if p.shape[0] < 2:
        return np.zeros(p.shape[:2])
    return np.linalg.norm(np.gradient(p, axis=0), axis=-1) / float(frame_time)


def contact_runs(contact: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) frame ranges where a (F,) boolean track is true."""
    c = np.asarray(contact, dtype=bool).astype(np.int8)
    edges = np.diff(np.r_[0, c, 0])
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def detect_contacts(positions: np.ndarray, frame_time: float, clearance: np.ndarray | None = None, *,
                    height: float = CONTACT_HEIGHT, speed: float = CONTACT_SPEED,
                    min_run: int = MIN_RUN) -> tuple[np.ndarray, np.ndarray]:
    """Contact frames of foot joints (module docstring).

    positions: (F, K, 3) metres, floor at y = 0; frame_time: seconds; clearance: (K,) each
    joint's planted height above the floor (default: its 5th-percentile height).
    Returns contacts (F, K) bool and the clearance (K,) used.
    """
    p = _check_positions(positions)
    if not (np.isfinite(frame_time) and frame_time > 0):
        raise MotionError(f"frame_time: {frame_time!r}, expected a positive number of seconds")
    y = p[..., 1]
    c = np.percentile(y, _CLEARANCE_PERCENTILE, axis=0) if clearance is None else np.asarray(clearance, float)
    if c.shape != (p.shape[1],):
        raise MotionError(f"clearance: shape {c.shape}, expected ({p.shape[1]},) one height per joint")
    contact = (y - c < height) & (horizontal_speed(p, frame_time) < speed)
    for k in range(contact.shape[1]):
        for a, b in contact_runs(contact[:, k]):
            if b - a < min_run:
                contact[a:b, k] = False
    return contact, c


@dataclass(frozen=True)
class Skating:
    """Foot skating over contact frames: ``share`` of contact frames slid more than ``SLIDE``
    from the run's start, ``mean_speed`` (m/s) in contact, ``max_slide`` (m), ``frames``
    (contact frames counted over all joints)."""

    share: float
    mean_speed: float
    max_slide: float
    frames: int

    def to_dict(self) -> dict:
        return {"share_sliding": self.share, "mean_speed_m_per_s": self.mean_speed,
                "max_slide_m": self.max_slide, "contact_frames": self.frames}


def skating(positions: np.ndarray, contacts: np.ndarray, frame_time: float, slide: float = SLIDE) -> Skating:
    """Skating of tracks (F, K, 3) over their contact frames (F, K) (module docstring)."""
    p = _check_positions(positions)
    c = np.asarray(contacts, dtype=bool)
    if c.shape != p.shape[:2]:
        raise MotionError(f"contacts: shape {c.shape}, expected {p.shape[:2]} (frames, joints) like the positions")
    speed = horizontal_speed(p, frame_time)
    slid, n, worst = 0, 0, 0.0
    for k in range(p.shape[1]):
        for a, b in contact_runs(c[:, k]):
            d = np.linalg.norm(p[a:b, k][:, [0, 2]] - p[a, k, [0, 2]], axis=1)
            slid += int((d > slide).sum())
            n += b - a
            worst = max(worst, float(d.max()))
    if n == 0:
        return Skating(0.0, 0.0, 0.0, 0)
    return Skating(slid / n, float(speed[c].mean()), worst, n)


def penetration(heights: np.ndarray) -> float:
    """Deepest point below the floor (metres, >= 0) of heights (any shape, y values)."""
    h = np.asarray(heights, dtype=float)
    return float(max(0.0, -h.min())) if h.size else 0.0
