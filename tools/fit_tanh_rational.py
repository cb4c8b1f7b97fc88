"""Fit the float32 tanh's rational (moex/kernels/cpu/simd.py, `_TANH_P` and `_TANH_Q`).

tanh x ≈ x P(x²) / Q(x²) on 0 < x <= 9, P of degree 5 and Q of degree 4 in x², Q(0) = 1, for the
smallest largest relative error: the linearised problem x P - tanh(x) Q ≈ 0, weighted by
1 / (tanh(x) Q_previous), solved by least squares and reweighted toward the points of largest
error (Lawson's iteration), 400 rounds, in the variable t = (x / 9)² and then rescaled to x².
Prints the coefficients and the largest relative error at the fitting points.

    python tools/fit_tanh_rational.py
"""

import numpy as np

C, M, N, POINTS, ROUNDS = 9.0, 5, 4, 4000, 400


def fit() -> tuple[float, np.ndarray, np.ndarray]:
    x = np.concatenate([np.linspace(1e-3, C, POINTS),
                        C * (1 - np.cos(np.linspace(0, np.pi / 2, POINTS)))])
    x = np.unique(x[x > 1e-4])
    f, t = np.tanh(x), (x / C) ** 2
    numerator = np.stack([x * t**k for k in range(M + 1)], 1)
    denominator = np.stack([t**k for k in range(1, N + 1)], 1)
    q_previous, weight = np.ones_like(x), np.ones_like(x) / len(x)
    best = (np.inf, None, None)
    for _ in range(ROUNDS):
        scale = np.sqrt(weight) / (f * q_previous)
        A = np.hstack([numerator, -f[:, None] * denominator]) * scale[:, None]
        solution = np.linalg.lstsq(A, f * scale, rcond=None)[0]
        p, q = solution[:M + 1], np.concatenate([[1.0], solution[M + 1:]])
        Q = np.polyval(q[::-1], t)
        error = np.abs(x * np.polyval(p[::-1], t) / Q / f - 1)
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
    print(f"largest relative error {largest:.3g}")
    print("_TANH_P =", tuple(float(v) for v in p))
    print("_TANH_Q =", tuple(float(v) for v in q))
