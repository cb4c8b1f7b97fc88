"""examples/activity.py: its Markov chain over activities draws the stated transition
probabilities, and docs/activity.md quotes the table its scores give (the run needs the
`compare` extra; this test does not)."""

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parent.parent


def _example():
    spec = importlib.util.spec_from_file_location("activity", ROOT / "examples" / "activity.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_chain_stays_with_the_stated_probability_and_moves_uniformly():
    activity = _example()
    exemplars = {c: np.full((3, 5, 1), float(c)) for c in range(4)}  # 5 steps, value = class
    series, labels = activity.chain(exemplars, 200, 50, np.random.default_rng(0))
    assert series.shape == (200, 250, 1) and labels.shape == (200, 250)
    np.testing.assert_array_equal(series[..., 0], labels)  # each exemplar under its own label
    blocks = labels[:, ::5]
    moves = np.zeros((4, 4))
    np.add.at(moves, (blocks[:, :-1].ravel(), blocks[:, 1:].ravel()), 1)
    rates = moves / moves.sum(1, keepdims=True)
    n = moves.sum(1)[:, None]
    expected = np.where(np.eye(4, dtype=bool), activity.STAY, (1 - activity.STAY) / 3)
    assert (np.abs(rates - expected) < 4 * np.sqrt(expected * (1 - expected) / n)).all()


def test_the_tutorial_page_quotes_the_table_its_scores_give():
    activity = _example()
    variants = {**activity.VARIANTS, **activity.ABLATION}  # one run folder each
    assert len({activity.folder_name(method) for method in variants}) == len(variants)
    frame = pd.read_csv(ROOT / "docs" / "activity_scores.csv")
    assert {"moex", "moex, ς = 1", "Gaussian HMM", "k-means"} <= set(frame["method"])
    page = (ROOT / "docs" / "activity.md").read_text()
    assert activity.summary(frame) in page
    assert (ROOT / "docs" / "activity_summary.md").read_text().strip() in page
