"""The semantic-mapping forest (Rupprecht §3.2 / Rupprecht §4.2) against scikit-learn's forest.

Data: 10,000 synthetic bodies sampled as in Rupprecht §3.1.2 (25 PCA coefficients uniform in +-3 sigma)
and measured as in Rupprecht Figure 2: stature and leg length are vertical extents (linear in the
coefficients), chest, waist and hip girths are perimeters of horizontal rings of vertices that
every coefficient displaces linearly, and shoulder size is the length of an open arc over the
shoulders -- sums of norms of affine functions, so measurements are smooth, convex and nonlinear
in the coefficients, and the inverse map (6 numbers -> 25) is a conditional mean, not a function.
2,000 further bodies are held out.

Printed, all in the same run (the machine is shared; ratios are what to compare):
  * training time (best of 2) of the default forest (50 trees, depth 15, 13 trials, 30 per leaf)
    on 2 cores vs ``sklearn.ensemble.RandomForestRegressor`` (constant leaves, same trees / depth /
    leaf size, ``max_features=1.0``, no bootstrap, ``n_jobs=2``); target < 60 s. Also ours on
    1 core, and whether both give the identical forest.
  * prediction ms/request in a batch of 1,000 vs scikit-learn's; target < 1 ms.
  * held-out accuracy of both, and of the linear mapping (the related work's baseline):
    coefficient RMSE, and the paper's protocol (Rupprecht §4.2): build the body from the predicted
    coefficients, measure it, and compare with the requested measurements (cm).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time, report  # noqa: E402

from bodyspace.mapping import LinearLeafForest, LinearMapping  # noqa: E402

N_TRAIN, N_TEST, K = 10_000, 2_000, 25
NAMES = ("stature", "chest", "waist", "hip", "leg length", "shoulder")


class SyntheticBodies:
    """Rings of vertices moved linearly by K coefficients; measured like Rupprecht Figure 2.

    Every vertex of ring r sits at ``base_r + sum_i alpha_i * mode_ri`` (cm, horizontal plane),
    with modes smooth in the angle around the ring (low Fourier orders), weaker for later
    components as in a PCA (sigma_i ~ i^-0.8).
    """

    def __init__(self, seed: int = 7, n_ring: int = 48):
        rng = np.random.default_rng(seed)
        self.sigma = 1.0 / (1 + np.arange(K)) ** 0.8
        theta = np.linspace(0, 2 * np.pi, n_ring, endpoint=False)
        # (semi-axis x, semi-axis z) in cm: chest, waist, hip; an arc for the shoulders.
        axes = {"chest": (16.0, 11.0), "waist": (14.0, 10.0), "hip": (17.0, 12.0)}
        self.rings = {}
        for name, (a, b) in axes.items():
            base = np.stack([a * np.cos(theta), b * np.sin(theta)], axis=1)          # (V, 2)
            self.rings[name] = (base, self._modes(rng, theta, scale=0.06 * b))
        arc = np.linspace(-0.5 * np.pi, 0.5 * np.pi, 24)
        base = np.stack([20.0 * np.sin(arc), 8.0 * np.cos(arc)], axis=1)
        self.rings["shoulder"] = (base, self._modes(rng, arc, scale=1.0))
        # Stature and leg length: linear in the coefficients, the first one dominant (Rupprecht §4.2).
        self.height_w = rng.normal(0, 3.0, K) * self.sigma
        self.height_w[0] = 4.0
        self.leg_w = 0.45 * self.height_w + rng.normal(0, 3.0, K) * self.sigma
        # Taller bodies are also wider: the first component scales every ring a little.
        self.grow = 0.04

    def _modes(self, rng, angle, scale):
        order = np.arange(1, 5)
        c = rng.normal(size=(K, 2, 4, 2)) / order[None, None, :, None] ** 1.5
        basis = np.stack([np.cos(order[None] * angle[:, None]), np.sin(order[None] * angle[:, None])], -1)
        modes = np.einsum("kdos,vos->kvd", c, basis)                                 # (K, V, 2)
        modes /= np.sqrt(np.mean(modes ** 2, axis=(1, 2), keepdims=True))           # RMS 1 cm per unit
        return scale * modes * self.sigma[:, None, None]

    def sample(self, n: int, rng) -> np.ndarray:
        """Coefficients (n, K), uniform in +-3 sigma (Rupprecht §3.1.2)."""
        return rng.uniform(-3, 3, (n, K)) * self.sigma

    def measure(self, alpha: np.ndarray) -> np.ndarray:
        """Measurements (n, 6) in cm of bodies with coefficients (n, K)."""
        out = np.empty((alpha.shape[0], 6))
        out[:, 0] = 175.0 + alpha @ self.height_w
        out[:, 4] = 82.0 + alpha @ self.leg_w
        scale = 1.0 + self.grow * alpha[:, :1, None]
        for j, name in ((1, "chest"), (2, "waist"), (3, "hip"), (5, "shoulder")):
            base, modes = self.rings[name]
            v = (base[None] + np.einsum("nk,kvd->nvd", alpha, modes)) * scale
            if name == "shoulder":                                                   # open arc
                out[:, j] = np.linalg.norm(np.diff(v, axis=1), axis=2).sum(1)
            else:                                                                    # closed ring
                out[:, j] = np.linalg.norm(v - np.roll(v, 1, axis=1), axis=2).sum(1)
        return out


def rmse(a, b) -> float:
    """Root mean squared Euclidean error per sample."""
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))


def main() -> None:
    from sklearn.ensemble import RandomForestRegressor

    bodies = SyntheticBodies()
    rng = np.random.default_rng(0)
    y_train, y_test = bodies.sample(N_TRAIN, rng), bodies.sample(N_TEST, rng)
    x_train, x_test = bodies.measure(y_train), bodies.measure(y_test)
    print(f"data: {N_TRAIN:,} train / {N_TEST:,} test bodies, {x_train.shape[1]} measurements -> {K} coefficients")

    # ---- training, both on 2 cores, in the same run; best of 2 (the machine is shared)
    fitted = {}

    def fit(name, make):
        def run():
            fitted[name] = make().fit(x_train, y_train)
        return best_time(run, repeat=2)
    t_ours = fit("ours", lambda: LinearLeafForest(rng=0, n_jobs=2))
    t_sk = fit("sk", lambda: RandomForestRegressor(n_estimators=50, max_depth=15, min_samples_leaf=30,
                                                   max_features=1.0, bootstrap=False, random_state=0, n_jobs=2))
    t_sk_rnd = fit("sk_rnd", lambda: RandomForestRegressor(n_estimators=50, max_depth=15, min_samples_leaf=30,
                                                           max_features=1, bootstrap=False, random_state=0,
                                                           n_jobs=2))
    t_ours_1 = fit("ours_1", lambda: LinearLeafForest(rng=0, n_jobs=1))
    forest, sk, sk_rnd = fitted["ours"], fitted["sk"], fitted["sk_rnd"]
    same = all(np.array_equal(a, b) for a, b in zip(forest.to_arrays().values(), fitted["ours_1"].to_arrays().values()))
    linear = LinearMapping().fit(x_train, y_train)
    print(f"train default forest ({forest.n_trees_} trees, {forest.n_leaves_:,} leaves, depth {forest.max_depth_}): "
          f"{t_ours:.1f} s on 2 cores ({t_ours_1:.1f} s on 1: x{t_ours_1 / t_ours:.2f}; identical forest: {same}); "
          f"target < 60 s: {'PASS' if t_ours < 60 else 'FAIL'}")
    print(f"  sklearn RandomForestRegressor (constant leaves, best threshold of all 6 features): {t_sk:.1f} s; "
          f"max_features=1 (best threshold of one random feature): {t_sk_rnd:.1f} s")
    report("train (trees)", t_ours, t_sk, forest.n_trees_, "trees")

    # ---- prediction: a batch of 1,000 requests, best of 5
    batch = x_test[:1000]
    forest.predict(batch[:10])
    t_pred = best_time(lambda: forest.predict(batch), repeat=5)
    t_pred_sk = best_time(lambda: sk.predict(batch), repeat=5)
    t_pred_one = best_time(lambda: forest.predict(batch[0]), repeat=20)
    print(f"predict batch of 1,000: {1e3 * t_pred / 1000:.4f} ms/request "
          f"(sklearn {1e3 * t_pred_sk / 1000:.4f} ms/request); single request {1e3 * t_pred_one:.2f} ms; "
          f"target < 1 ms: {'PASS' if t_pred / 1000 < 1e-3 else 'FAIL'}")
    report("predict", t_pred, t_pred_sk, 1000, "requests")

    # ---- accuracy on held-out bodies
    models = {"linear-leaf forest (ours)": forest, "sklearn RF (constant leaves)": sk,
              "sklearn RF, max_features=1": sk_rnd, "linear mapping (baseline)": linear}
    spread = rmse(y_test, y_train.mean(0))
    print(f"held-out accuracy ({N_TEST:,} bodies); coefficient RMSE (prior spread {spread:.3f}); "
          "measurement error of the body built from the prediction, cm, mean +- sd (Rupprecht §4.2 protocol):")
    print(f"  {'model':32s} {'coef RMSE':>9s}  " + "  ".join(f"{n:>13s}" for n in NAMES))
    for name, m in models.items():
        pred = m.predict(x_test)
        err = bodies.measure(pred) - x_test
        cells = "  ".join(f"{e.mean():+6.2f}+-{e.std():5.2f}" for e in err.T)
        print(f"  {name:32s} {rmse(pred, y_test):9.4f}  {cells}")


if __name__ == "__main__":
    main()
