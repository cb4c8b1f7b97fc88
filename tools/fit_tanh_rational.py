"""Fit the float32 tanh's rational (moex/kernels/cpu/simd.py, `_TANH_P` and `_TANH_Q`).

simd's float32 tanh x takes y = x / 2 and t = tanh y ≈ y + y³ P(y²) / Q(y²) on 0 <= y <= 4.75, P
and Q of degree 2 in y², Q(0) = 1, then tanh x = 2t / (1 + t²). An error δ in t leaves δ / cosh x
in tanh x (relative), so the fit minimises the largest |y³ (P/Q - g)| / (tanh y cosh 2y), g = (tanh
y - y) / y³: the linearised problem P - g Q ≈ 0, weighted by that factor over Q_previous, solved
by least squares and reweighted toward the points of largest error (Lawson's iteration), 300
rounds, in the variable s = (y / 4.75)² and then rescaled to y². Prints the largest such error at
the fitting points and the coefficients.

    python tools/fit_tanh_rational.py
"""

import numpy as np

C, M, N, POINTS, ROUNDS = 4.75, 2, 2, 4000, 300


def fit() -> tuple[float, np.ndarray, np.ndarray]:
    y = np.concatenate([np.linspace(1e-3, C, POINTS),
                        C * (1 - np.cos(np.linspace(0, np.pi / 2, POINTS)))])
    y = np.unique(y[y > 1e-3])
    z = y * y
    g = (np.tanh(y) - y) / y**3
    near = y < 0.05  # tanh's series there: the difference above cancels
    g[near] = -1 / 3 + 2 * z[near] / 15 - 17 * z[near] ** 2 / 315 + 62 * z[near] ** 3 / 2835
    s, effect = z / C**2, y**3 / (np.tanh(y) * np.cosh(2 * y))
    numerator = np.stack([s**k for k in range(M + 1)], 1)
    denominator = np.stack([s**k for k in range(1, N + 1)], 1)
    q_previous, weight = np.ones_like(y), np.ones_like(y) / len(y)
    best = (np.inf, None, None)
    for _ in range(ROUNDS):
        scale = np.sqrt(weight) * effect / q_previous
        A = np.hstack([numerator, -g[:, None] * denominator]) * scale[:, None]
        solution = np.linalg.lstsq(A, g * scale, rcond=None)[0]
        p, q = solution[:M + 1], np.concatenate([[1.0], solution[M + 1:]])
        Q = np.polyval(q[::-1], s)
        error = np.abs((np.polyval(p[::-1], s) / Q - g) * effect)
        if error.max() < best[0]:
            best = (error.max(), p, q)
        weight = weight * (error / error.max()) + 1e-30
        weight /= weight.sum()
        q_previous = Q
    largest, p, q = best
    return (largest, np.array([p[k] / C ** (2 * k) for k in range(M + 1)]),
            np.array([q[k] / C ** (2 * k) for k in range(N + 1)]))


if __name__ == "__main__":
    largest, p, q = fit()
    print(f"largest relative error left in tanh x {largest:.3g}")
    print("_TANH_P =", tuple(float(v) for v in p))
    print("_TANH_Q =", tuple(float(v) for v in q))
