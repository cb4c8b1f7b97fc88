"""How well a segmentation (the winning expert at each step) matches true labels: the adjusted
Rand index, normalised mutual information and the accuracy after the best one-to-one matching
of experts to labels. Steps labelled < 0 (unknown) are left out of every score."""

import numpy as np


def contingency(truth: np.ndarray, found: np.ndarray, experts: int = 0) -> np.ndarray:
    """(L, K) counts of steps with label l and expert k; L = the largest label + 1, K = the
    largest expert + 1 or `experts` if more (experts that never win: columns of zeros)."""
    truth, found = np.asarray(truth).ravel(), np.asarray(found).ravel()
    table = np.zeros((truth.max() + 1, max(found.max() + 1, experts)), dtype=np.int64)
    np.add.at(table, (truth, found), 1)
    return table


def _pairs(counts: np.ndarray) -> float:
    return float((counts * (counts - 1) / 2).sum())


def adjusted_rand(table: np.ndarray) -> float:
    """Hubert & Arabie's adjusted Rand index of a contingency table: 1 for identical partitions
    (up to renaming), 0 in expectation for independent ones."""
    total = _pairs(np.array([table.sum()]))
    rows, cols = _pairs(table.sum(1)), _pairs(table.sum(0))
    expected = rows * cols / total if total else 0.0
    top = (rows + cols) / 2 - expected
    return (_pairs(table) - expected) / top if top else 1.0


def normalized_mutual_info(table: np.ndarray) -> float:
    """I(labels; experts) / ((H(labels) + H(experts)) / 2), in [0, 1]; 1 where both are one
    class (nothing to tell apart)."""
    p = table / table.sum()
    rows, cols = p.sum(1), p.sum(0)
    nz = p > 0
    mutual = float((p[nz] * np.log(p[nz] / np.outer(rows, cols)[nz])).sum())

    def entropy(q):
        q = q[q > 0]
        return float(-(q * np.log(q)).sum())

    mean = (entropy(rows) + entropy(cols)) / 2
    return mutual / mean if mean > 0 else 1.0


def best_matching(table: np.ndarray) -> np.ndarray:
    """The one-to-one matching of experts (columns) to labels (rows) that agrees on the most
    steps (the Hungarian method): label of each expert, -1 for an expert left unmatched (more
    experts than labels)."""
    L, K = table.shape
    by_expert = L > K  # the method below assigns each row of an n x m cost matrix, n <= m
    cost = -(table.T if by_expert else table).astype(float)
    n, m = cost.shape
    u, v = np.zeros(n + 1), np.zeros(m + 1)
    owner, way = np.zeros(m + 1, dtype=int), np.zeros(m + 1, dtype=int)
    for i in range(1, n + 1):
        owner[0], j0 = i, 0
        least, used = np.full(m + 1, np.inf), np.zeros(m + 1, dtype=bool)
        while owner[j0]:
            used[j0] = True
            i0 = owner[j0]
            free = ~used[1:]
            reduced = cost[i0 - 1] - u[i0] - v[1:]
            better = free & (reduced < least[1:])
            least[1:][better] = reduced[better]
            way[1:][better] = j0
            j1 = 1 + int(np.argmin(np.where(free, least[1:], np.inf)))
            delta = least[j1]
            u[owner[used]] += delta
            v[used] -= delta
            least[1:][free] -= delta
            j0 = j1
        while j0:
            j1 = way[j0]
            owner[j0] = owner[j1]
            j0 = j1
    pairs = [(owner[j] - 1, j - 1) for j in range(1, m + 1) if owner[j]]  # (row, column)
    label_of = np.full(K, -1)
    for row, col in pairs:
        expert, label = (row, col) if by_expert else (col, row)
        label_of[expert] = label
    return label_of


def scores(truth: np.ndarray, found: np.ndarray, experts: int = 0) -> dict[str, float]:
    """ARI, NMI and matched accuracy of the winning experts `found` against labels `truth`
    (same shape; steps with truth < 0 left out), and the matching itself (label of expert k,
    for every one of `experts` where given: experts that never win among them, -1 unless a
    label is left for them)."""
    truth, found = np.asarray(truth).ravel(), np.asarray(found).ravel()
    known = truth >= 0
    if not known.any():
        return {}
    table = contingency(truth[known], found[known], experts)
    label_of = best_matching(table)
    hits = sum(table[label, k] for k, label in enumerate(label_of) if label >= 0)
    return {"segment_ari": adjusted_rand(table), "segment_nmi": normalized_mutual_info(table),
            "segment_accuracy": hits / table.sum(), "label_of_expert": label_of}
