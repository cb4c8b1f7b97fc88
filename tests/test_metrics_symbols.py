import math
from collections import Counter

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from moex.metrics.symbols import block_distribution, block_kl, symbolize_argmax, symbolize_nearest


def test_block_kl_of_a_sequence_with_itself_is_zero():
    seq = np.random.default_rng(0).integers(0, 3, 5000)
    assert block_kl(seq, seq, 3) == 0.0


def test_block_kl_matches_closed_form_for_iid_sources(n=400_000, m=2):
    rng = np.random.default_rng(1)
    p, q = np.array([0.7, 0.3]), np.array([0.4, 0.6])
    a, b = rng.choice(2, n, p=p), rng.choice(2, n, p=q)
    # blocks of i.i.d. symbols: D_KL^(m) = m · D_KL(p ‖ q)
    expected = m * float((p * np.log(p / q)).sum())
    assert abs(block_kl(a, b, m) - expected) < 0.01


def test_missing_blocks_get_the_floor():
    data, model = np.array([0, 1, 0, 1, 0]), np.array([0, 0, 0, 0])
    # data 1-blocks: p(0) = 3/5, p(1) = 2/5; model: q(0) = 1, q(1) missing -> floor, and q
    # renormalised over both: q = (1, 1e-3) / 1.001
    expected = 0.6 * math.log(0.6 * 1.001) + 0.4 * math.log(0.4 * 1.001 / 1e-3)
    assert abs(block_kl(data, model, 1, floor=1e-3) - expected) < 1e-12


@given(st.lists(st.integers(0, 9), min_size=6, max_size=300),
       st.lists(st.integers(0, 9), min_size=6, max_size=300), st.integers(1, 4),
       st.sampled_from([1e-6, 1e-3, 0.1]))
def test_block_kl_is_never_negative(data, model, m, floor):
    """Gibbs' inequality holds for the floored model distribution: a model stuck in one block
    against data with many rare blocks (the case that scored -1.7 before the floor was
    renormalised, on a 10-expert recording) included."""
    assert block_kl(np.array(data), np.array(model), m, floor) >= -1e-12


def test_a_model_stuck_in_one_block_scores_above_zero_against_many_rare_blocks():
    data = np.random.default_rng(5).integers(0, 10, 50_000)  # 10^4 blocks of p about 1e-4
    model = np.zeros(5000, dtype=int)
    assert block_kl(data, model, 4) > 0  # the unrenormalised floor gave about -2.3


def test_block_distribution_counts_overlapping_windows_over_series():
    dist = block_distribution(np.array([[0, 1, 1], [1, 1, 0]]), 2)
    assert dist == {(0, 1): 0.25, (1, 1): 0.5, (1, 0): 0.25}


def test_symbolizers():
    gates = np.array([[0.1, 0.9], [0.7, 0.3]])
    assert symbolize_argmax(gates).tolist() == [1, 0]
    protos, labels = np.array([[-0.4, 0.0], [0.4, 0.0]]), np.array([0, 1])
    assert symbolize_nearest(np.array([[-0.3, 0.2], [0.5, -0.1]]), protos, labels).tolist() == [
        0, 1]


@given(st.lists(st.lists(st.integers(0, 6), max_size=30), min_size=1, max_size=4),
       st.integers(1, 4))
def test_block_distribution_equals_counting_tuples(sequences, m):
    counts = Counter(tuple(s[i:i + m]) for s in sequences for i in range(len(s) - m + 1))
    total = sum(counts.values())
    dist = block_distribution([np.array(s, dtype=np.int64) for s in sequences], m)
    assert dist.keys() == counts.keys()
    for block, c in counts.items():
        assert math.isclose(dist[block], c / total)


def test_nearest_prototype_equals_brute_force():
    rng = np.random.default_rng(2)
    points, protos = rng.uniform(-1, 1, (3, 500, 2)), rng.uniform(-1, 1, (40, 2))
    labels = rng.integers(0, 5, 40)
    brute = labels[((points[..., None, :] - protos) ** 2).sum(-1).argmin(-1)]
    assert np.array_equal(symbolize_nearest(points, protos, labels), brute)


def test_threshold_rule_is_argmax_where_a_gate_exceeds_one_half_else_a_symbol_of_its_own():
    from moex.metrics.symbols import symbolize_threshold

    gates = np.array([[0.9, 0.05, 0.05], [0.4, 0.35, 0.25], [0.2, 0.7, 0.1], [0.5, 0.5, 0.0]])
    np.testing.assert_array_equal(symbolize_threshold(gates), [0, 3, 1, 3])
    confident = np.eye(3)[[2, 0, 1]] * 0.98 + 0.01
    np.testing.assert_array_equal(symbolize_threshold(confident), confident.argmax(-1))


def test_bad_symbol_rule_is_refused():
    import pytest

    from moex.config.evaluation import EvalConfig
    from moex.errors import ConfigError

    with pytest.raises(ConfigError, match="eval.symbol_rule='vote'; choose argmax or threshold"):
        EvalConfig(symbol_rule="vote")


def test_mregn_kl_is_zero_for_the_same_distribution_and_charges_missing_blocks_per_count():
    """The authors' C formula: 0 for a sequence against itself or against itself repeated (the
    ln(L_y/L_x) term); a block the model lacks costs ln(p/(0.001/L_y)) in place of ln(p/floor)."""
    from moex.metrics.symbols import block_kl_mregn

    data = np.random.default_rng(0).integers(0, 3, 400)
    assert block_kl_mregn(data, data, 2) == 0.0
    assert abs(block_kl_mregn(data, [data, data], 2)) < 1e-12
    data, model = np.array([0, 1, 0, 1, 0]), np.array([0, 0, 0, 0, 0])  # blocks 01, 10 missing
    x, y = 4, 4  # blocks of length 2
    expected = 2 * 2 * (np.log(2 / 1e-3) + np.log(y / x)) / x + 1e-3 * (
        np.log(1e-3 / 4) + np.log(y / x)) / x
    assert math.isclose(block_kl_mregn(data, model, 2), expected, rel_tol=1e-12)
