"""Switching statistics of symbol sequences (paper Table 2, Fig. 9, Sec. 4.3): run-length
encoding, transition matrices, residence times and periodicity."""

import numpy as np


def rle(seq) -> tuple[np.ndarray, np.ndarray]:
    """Run-length encoding: `rle([0, 0, 1, 1, 1, 0])` -> values [0, 1, 0], lengths [2, 3, 1]."""
    seq = np.asarray(seq)
    if len(seq) == 0:
        return seq[:0], np.zeros(0, dtype=np.int64)
    starts = np.flatnonzero(np.r_[True, seq[1:] != seq[:-1]])
    return seq[starts], np.diff(np.r_[starts, len(seq)])


def segment_symbols(symbols, period: float) -> np.ndarray:
    """Per-step symbols -> one symbol per completed primitive (a curve lasting `period` steps).

    Runs shorter than half a period (jitter where curves meet) are dropped and their neighbours
    merged; a run of L steps counts round(L / period) repetitions.
    """
    values, lengths = rle(symbols)
    reps = np.rint(lengths / period).astype(np.int64)
    keep = reps > 0
    values, reps = rle(np.repeat(values[keep], reps[keep]))
    return np.repeat(values, reps)


def switch_probability(segments) -> float:
    """Share of completed primitives followed by a different one (the paper's Table 2), pooled
    over sequences of `segment_symbols`; NaN without a completed pair."""
    changes = sum(int((s[1:] != s[:-1]).sum()) for s in segments)
    total = sum(max(len(s) - 1, 0) for s in segments)
    return changes / total if total else float("nan")


def switch_rate(sequences, period: float) -> float:
    """Changes of primitive per `period` steps of time, pooled over per-step symbol sequences,
    after runs shorter than half a period (jitter where curves meet) are merged away: the
    switching probability counted per switch instead of per completed lap. The two agree when
    every primitive lasts whole periods."""
    changes = steps = 0
    for seq in sequences:
        values, lengths = rle(seq)
        values = rle(values[lengths >= period / 2])[0]
        changes += max(len(values) - 1, 0)
        steps += len(seq)
    return changes * period / steps if steps else float("nan")


def transition_matrix(seq, num_symbols: int) -> np.ndarray:
    """Row-normalised counts of consecutive pairs (NaN rows for symbols never left)."""
    seq = np.asarray(seq)
    counts = np.zeros((num_symbols, num_symbols))
    np.add.at(counts, (seq[:-1], seq[1:]), 1)
    with np.errstate(invalid="ignore"):
        return counts / counts.sum(1, keepdims=True)


def residence_times(seq, censored: bool = False) -> dict[int, np.ndarray]:
    """Lengths of the stays of each symbol. By default the completed stays, entered and left
    within `seq`: for a Markov source that stays with probability p they are geometric with mean
    1/(1 - p). With `censored`, the stays cut off by an end of `seq` instead (the first and the
    last; a sequence that never switches is one such stay): their true lengths are at least
    these. Dropping them silently would drop exactly the longest stays."""
    values, lengths = rle(seq)
    cut = np.zeros(len(values), bool)
    cut[[0, -1] if len(values) else []] = True
    keep = cut if censored else ~cut
    values, lengths = values[keep], lengths[keep]
    return {int(v): lengths[values == v] for v in np.unique(values)}


def is_periodic(seq, max_period: int = 100) -> bool:
    """Whether seq[i] == seq[i + p] for all i, for some p <= max_period (paper Sec. 4.3).

    Every candidate period is tested only in a sequence longer than max_period
    (`nonperiodic_share` leaves shorter ones out); the longer the sequence, the firmer the answer.
    """
    seq = np.asarray(seq)
    return any(np.array_equal(seq[p:], seq[:-p]) for p in range(1, min(max_period, len(seq) - 1)
                                                                   + 1))


def nonperiodic_share(sequences, max_period: int = 100) -> tuple[float, int]:
    """Share of the sequences with no period <= max_period (`is_periodic`), among those longer
    than max_period (so that every candidate period is tested), and how many those are. Shorter
    ones (an orbit that rarely completes a lap of a curve) cannot be judged and are left out;
    NaN when none can be judged."""
    judged = [s for s in sequences if len(s) > max_period]
    if not judged:
        return float("nan"), 0
    return float(np.mean([not is_periodic(s, max_period) for s in judged])), len(judged)
