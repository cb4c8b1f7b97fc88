"""Symbolic dynamics (paper Sec. 3): outputs to symbols, m-blocks and D_KL^(m)(ŝ ‖ s) (Eq. 21)."""

import numpy as np


def symbolize_argmax(gates: np.ndarray) -> np.ndarray:
    """s_n = argmax_k g^k_n (Eq. 22): (..., T, K) -> (..., T)."""
    return np.asarray(gates).argmax(-1)


def symbolize_threshold(gates: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """The authors' C rule (gn-learn's `f2symbol` with two bins): each gate is 1 above
    `threshold`; with gates on the simplex at most one is, so the symbol is that gate's index,
    and a step with none above it is a symbol of its own, K: (..., T, K) -> (..., T)."""
    gates = np.asarray(gates)
    return np.where(gates.max(-1) > threshold, gates.argmax(-1), gates.shape[-1])


def symbolize_nearest(points: np.ndarray, prototypes: np.ndarray,
                      prototype_symbols: np.ndarray) -> np.ndarray:
    """Symbol of the nearest prototype point: (..., T, D) -> (..., T)."""
    points = np.asarray(points)
    flat = points.reshape(-1, points.shape[-1])
    # |x - p|² = |x|² - 2 x·p + |p|²; |x|² is the same for every p, so one matmul decides
    offset = (prototypes**2).sum(-1)
    nearest = np.empty(len(flat), dtype=np.int64)
    for start in range(0, len(flat), 65536):  # bounded memory for long samples
        chunk = flat[start:start + 65536]
        nearest[start:start + 65536] = (offset - 2 * chunk @ prototypes.T).argmin(1)
    return np.asarray(prototype_symbols)[nearest].reshape(points.shape[:-1])


def block_counts(sequences, m: int) -> tuple[dict[tuple, int], int]:
    """Counts of the overlapping length-m blocks of one or more symbol sequences, and the number
    of blocks (windows) in all."""
    single = np.ndim(sequences[0]) == 0 if len(sequences) else True  # one flat sequence
    sequences = [np.asarray(s, dtype=np.int64) for s in
                 ([sequences] if single else sequences)]
    base = 1 + max((int(s.max()) for s in sequences if len(s)), default=0)
    weights = base ** np.arange(m - 1, -1, -1, dtype=np.int64)  # a block as one integer
    codes = [np.lib.stride_tricks.sliding_window_view(s, m) @ weights
             for s in sequences if len(s) >= m]
    if not codes:
        return {}, 0
    codes = np.concatenate(codes)
    if base**m <= 1 << 24:  # few possible blocks: count them directly (linear, no sort)
        counts = np.bincount(codes, minlength=base**m)
        unique = np.flatnonzero(counts)
        counts = counts[unique]
    else:
        unique, counts = np.unique(codes, return_counts=True)
    blocks = (unique[:, None] // weights) % base
    return dict(zip(map(tuple, blocks.tolist()), counts.tolist(), strict=True)), len(codes)


def block_distribution(sequences, m: int) -> dict[tuple, float]:
    """Probabilities of the overlapping length-m blocks of one or more symbol sequences."""
    counts, total = block_counts(sequences, m)
    return {b: c / total for b, c in counts.items()}


def block_kl(data, model, m: int, floor: float = 1e-3) -> float:
    """D_KL^(m)(ŝ ‖ s) = Σ_b p(b | ŝ) ln(p(b | ŝ) / p(b | s)) (Eq. 21), data ŝ first.

    Blocks the data has and the model never produced get the model probability `floor`, and
    the model's probabilities are then divided by 1 + floor × (the number of such blocks), so
    that q is again a distribution: the divergence stays finite, is never negative (Gibbs'
    inequality), and a model that misses a block pays about ln(p/floor) for it. (Before
    2026-12-04 the floor was not renormalised, and a model that missed many rare blocks of a
    many-symbol recording could score below 0.) Blocks only the model produced do not enter
    Eq. 21.
    """
    p, q = block_distribution(data, m), block_distribution(model, m)
    z = 1.0 + floor * sum(b not in q for b in p)
    return float(sum(pb * np.log(pb * z / q.get(b, floor)) for b, pb in p.items()))


def block_kl_mregn(data, model, m: int, floor_count: float = 1e-3) -> float:
    """The authors' C formula (their `kullback_leibler_divergence`), data x first, with raw
    counts c and numbers of blocks L:
    (1/L_x) [Σ_{b∈x} c_x(b) (ln(c_x(b)/c̃_y(b)) + r) + Σ_{b∈y, b∉x} f (ln(f/c_y(b)) + r)],
    r = ln(L_y/L_x), c̃_y(b) = c_y(b), or the count f = 0.001 where the model lacks b. Against
    Eq. 21 with a probability floor, a missing block costs ln(p/(f/L_y)): far more for long model
    samples; the second sum is small and negative."""
    cx, nx = block_counts(data, m)
    cy, ny = block_counts(model, m)
    r = np.log(ny / nx)
    first = sum(c * (np.log(c / cy.get(b, floor_count)) + r) for b, c in cx.items())
    second = sum(floor_count * (np.log(floor_count / c) + r) for b, c in cy.items()
                 if b not in cx)
    return float((first + second) / nx)
