import matplotlib.pyplot as plt
import numpy as np

from moex import plotting


def _one_hot(winners: np.ndarray, K: int) -> np.ndarray:
    return np.eye(K)[winners]


def test_expert_panels_one_per_expert_and_spare_panels_blank():
    K, T = 3, 60
    winners = np.repeat([0, 2], T // 2)  # expert 1 never wins
    outputs = np.random.default_rng(0).uniform(-1, 1, (T, 2))
    axes = plotting.plot_expert_panels(outputs, _one_hot(winners, K))
    panels = list(axes.flat)
    assert len(panels) == 4  # a 2 x 2 grid for 3 experts
    assert [ax.get_title() for ax in panels[:K]] == ["expert 0", "expert 1", "expert 2"]
    assert [len(ax.collections) for ax in panels[:K]] == [1, 0, 1]
    assert len(panels[0].collections[0].get_offsets()) == T // 2
    assert not panels[K].axison and panels[K].get_title() == ""
    plt.close("all")


def test_gate_series_labels_every_step_of_a_short_window_and_each_run_of_a_long_one():
    K, names = 3, ["a", "b", "c"]
    symbols = np.repeat([0, 1, 0, 2], 13)[:50]
    axes = plotting.plot_gate_series(np.zeros((50, 2)), _one_hot(symbols, K), symbols, names)
    assert [text.get_text() for text in axes[1].texts] == [names[s] for s in symbols]
    symbols = np.repeat([0, 1, 2, 0, 1], [100, 2, 98, 50, 50])  # a 2-step flicker of "b"
    axes = plotting.plot_gate_series(np.zeros((300, 2)), _one_hot(symbols, K), symbols, names)
    labels = [(int(text.get_position()[0]), text.get_text()) for text in axes[1].texts]
    assert labels == [(50, "a"), (151, "c"), (225, "a"), (275, "b")]
    plt.close("all")
