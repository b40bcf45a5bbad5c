"""Small synthetic meshes shared by the geometry tests."""

import numpy as np


def open_tube(rings: int, around: int, length: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Open cylinder along +y with two boundary loops: vertices (rings*around, 3), faces (F, 3)."""
    t = 2 * np.pi * np.arange(around) / around
    y = np.linspace(0, length, rings)
    v = np.stack([radius * np.cos(t)[None].repeat(rings, 0), y[:, None].repeat(around, 1),
                  radius * np.sin(t)[None].repeat(rings, 0)], -1).reshape(-1, 3)
    f = []
    for r in range(rings - 1):
        for a in range(around):
            i, j = r * around + a, r * around + (a + 1) % around
            f += [[i, i + around, j], [j, i + around, j + around]]
    return v, np.array(f)
