"""Body composition from geometry: body fat, density, mass, BMI.

Part of the measure layer: the ``mass`` measurement method (``measure/methods.py``) and the
synthetic population (``synth/population.py``, a layer above) both turn a body's volume into
mass here. Arrays in, arrays out: any broadcastable shapes, SI units (m³, m, kg, kg/m³).

Published formulas, each with its source (docs/population.md, docs/measurements.md):

- Body fat percent from BMI, age and sex, Deurenberg, Weststrate & Seidell (1991), Br J Nutr
  65:105-114: ``BF% = 1.2 BMI + 0.23 age - 10.8 sex - 5.4`` (sex = 1 male, 0 female).
- Whole-body density from body fat, the two-compartment model of Siri (1961) inverted:
  ``BF% = 495 / D - 450``  →  ``D = 495 / (BF% + 450)`` g/cm³ (fat 0.9, fat-free 1.1 g/cm³).
- Mass = volume × density. Because density depends on BMI, which depends on mass, mass is the
  fixed point of ``m = V · D(BF(m / h², age, sex))``; the map is a strong contraction
  (dm/dm ≈ 1e-3), so a few iterations converge to machine precision.
"""

from __future__ import annotations

import numpy as np


def body_fat_percent(bmi: np.ndarray, age_years: np.ndarray, male: np.ndarray) -> np.ndarray:
    """Deurenberg et al. (1991) body fat percent (adults), clipped to a physiological 3..60 %."""
    bf = 1.2 * np.asarray(bmi) + 0.23 * np.asarray(age_years) - 10.8 * np.asarray(male, dtype=float) - 5.4
    return np.clip(bf, 3.0, 60.0)


def body_density(body_fat: np.ndarray) -> np.ndarray:
    """Whole-body density in kg/m³ from body fat percent (Siri 1961, inverted)."""
    return 495.0 / (np.asarray(body_fat) + 450.0) * 1000.0


def mass_from_volume(volume_m3: np.ndarray, stature_m: np.ndarray, age_years: np.ndarray,
                     male: np.ndarray, iterations: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mass (kg), BMI (kg/m²) and body fat (%) of bodies of given volume and stature.

    Solves ``mass = volume · density(body_fat(BMI(mass)))`` by fixed-point iteration, starting
    from the density of water-like tissue (1000 kg/m³).
    """
    volume = np.asarray(volume_m3, dtype=float)
    h2 = np.asarray(stature_m, dtype=float) ** 2
    mass = volume * 1000.0
    for _ in range(iterations):
        bf = body_fat_percent(mass / h2, age_years, male)
        mass = volume * body_density(bf)
    bmi = mass / h2
    return mass, bmi, body_fat_percent(bmi, age_years, male)
