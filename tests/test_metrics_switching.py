import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from moex.metrics.switching import (
    is_periodic,
    residence_times,
    rle,
    segment_symbols,
    transition_matrix,
)
from moex.metrics.symbols import block_kl


def test_rle_worked_example():
    values, lengths = rle([0, 0, 1, 1, 1, 0])
    assert values.tolist() == [0, 1, 0] and lengths.tolist() == [2, 3, 1]


@pytest.mark.parametrize("stay", [0.5, 0.75, 0.875])
def test_markov_residence_mean_is_one_over_one_minus_p(stay, n=200_000):
    rng = np.random.default_rng(0)
    flips = rng.random(n) > stay
    seq = np.cumsum(flips) % 2
    times = np.concatenate(list(residence_times(seq).values()))
    assert abs(times.mean() - 1 / (1 - stay)) < 0.03 / (1 - stay)
    tm = transition_matrix(seq, 2)
    assert abs(tm[0, 0] - stay) < 0.01 and abs(tm[1, 1] - stay) < 0.01


def test_segment_symbols_counts_repetitions_and_drops_jitter():
    per_step = np.array([0] * 50 + [1] * 2 + [0] * 25 + [1] * 24)  # P = 25; 2 steps of jitter
    assert segment_symbols(per_step, 25).tolist() == [0, 0, 0, 1]


def test_periodicity():
    assert is_periodic(np.tile([0, 1, 1, 0, 1], 100), 100)
    assert not is_periodic(np.random.default_rng(0).integers(0, 2, 1000), 100)
    assert not is_periodic(np.tile(np.arange(150) % 2 + (np.arange(150) > 70), 4), 100)


symbol_lists = st.lists(st.integers(0, 3), min_size=2, max_size=200)


@given(symbol_lists)
def test_rle_round_trip_and_run_lengths_sum_to_length(seq):
    values, lengths = rle(seq)
    assert np.repeat(values, lengths).tolist() == seq
    assert lengths.sum() == len(seq) and (values[1:] != values[:-1]).all()


@given(symbol_lists)
def test_transition_rows_are_distributions(seq):
    tm = transition_matrix(seq, 4)
    visited = ~np.isnan(tm).any(1)
    assert np.allclose(tm[visited].sum(1), 1) and (tm[visited] >= 0).all()


@given(symbol_lists, st.integers(1, 4))
def test_block_kl_of_a_sequence_with_itself_is_zero(seq, m):
    assert abs(block_kl(np.array(seq), np.array(seq), m)) < 1e-12


def test_switch_probability_and_rate_agree_on_whole_laps_and_differ_on_partial_ones():
    from moex.metrics.switching import segment_symbols, switch_probability, switch_rate

    laps = np.repeat([0, 1, 1, 0, 1, 0, 0, 0], 25)  # 8 whole laps of 25 steps, 4 switches
    assert switch_probability([segment_symbols(laps, 25)]) == pytest.approx(4 / 7)
    assert switch_rate([laps], 25) == pytest.approx(4 / 8)
    jitter = laps.copy()
    jitter[100:103] = 1  # a 3-step flicker is not a switch
    assert switch_rate([jitter], 25) == pytest.approx(4 / 8)
    half = np.repeat([0, 1, 0, 1], [25, 13, 25, 13])  # half laps: 3 switches in 3.04 periods
    assert switch_rate([half], 25) == pytest.approx(3 * 25 / 76)


def test_nonperiodic_share_leaves_out_sequences_too_short_to_judge():
    from moex.metrics.switching import nonperiodic_share

    periodic = np.tile([0, 1, 1], 100)  # 300 laps, period 3
    random = np.random.default_rng(1).integers(0, 2, 300)
    short = np.array([0, 1])  # two laps: no period can be tested
    assert nonperiodic_share([periodic, random, short], 100) == (0.5, 2)
    assert nonperiodic_share([periodic[:101]], 100) == (0.0, 1)
    share, judged = nonperiodic_share([short, periodic[:100]], 100)
    assert np.isnan(share) and judged == 0


def test_residence_times_keep_the_stays_cut_off_by_the_sample_ends():
    never = np.zeros(50, dtype=int)  # one stay longer than the sample: nothing completed
    assert residence_times(never) == {}
    assert residence_times(never, censored=True)[0].tolist() == [50]
    seq = [0] * 3 + [1] * 4 + [0] * 2 + [1] * 6  # first (3) and last (6) stays are cut off
    done, cut = residence_times(seq), residence_times(seq, censored=True)
    assert {k: v.tolist() for k, v in done.items()} == {0: [2], 1: [4]}
    assert {k: v.tolist() for k, v in cut.items()} == {0: [3], 1: [6]}


def test_a_network_that_never_switches_has_long_stays_not_short_ones():
    """Stays longer than the sample were once dropped: a network that stayed on one curve had
    mean_residence 1 (its few jitter stays). Every stay now counts, the cut-off ones flagged."""
    from types import SimpleNamespace

    from moex.config.evaluation import EvalConfig
    from moex.evaluation import _switching_columns

    period, laps = 25, 40
    stay = np.zeros((3, period * laps), dtype=int)  # 3 samples, each on curve 0 throughout
    columns, _, done, cut = _switching_columns(stay, stay, SimpleNamespace(period=period),
                                               EvalConfig(max_period=10))
    assert columns["switch_prob"] == 0 and len(done) == 0
    assert columns["mean_residence"] == laps and columns["censored_stays"] == 3
    assert cut.tolist() == [laps] * 3
