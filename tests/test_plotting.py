import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from moex import plotting


def _one_hot(winners: np.ndarray, K: int) -> np.ndarray:
    return np.eye(K)[winners]


def test_expert_panels_one_per_winning_expert_and_the_others_named():
    K, T = 4, 60
    winners = np.repeat([0, 2, 3], T // 3)  # expert 1 never wins
    outputs = np.random.default_rng(0).uniform(-1, 1, (T, 2))
    axes = plotting.plot_expert_panels(outputs, _one_hot(winners, K), title="run 0")
    panels = list(axes.flat)
    assert len(panels) == 4  # a 2 x 2 grid for the 3 experts that win
    assert [ax.get_title() for ax in panels[:3]] == ["expert 0 (33%)", "expert 2 (33%)",
                                                     "expert 3 (33%)"]
    assert [len(ax.collections[0].get_offsets()) for ax in panels[:3]] == [T // 3] * 3
    assert not panels[3].get_visible()  # the spare panel is hidden
    assert panels[0].figure._suptitle.get_text() == "run 0\n1 of 4 experts never win: 1"
    plt.close("all")


def test_figures_state_facts_and_hide_what_is_empty():
    """Learning curves: one legend, symlog λ_max, labels from the metric table; a residence plot
    of a run that never switched says so; a fixed point is named in the phase portrait."""
    history = pd.DataFrame([{"run": r, "phase": phase, "step": s, "E": 1.0 / (s + 1),
                             "E_g": 0.1, "max_lyapunov": (-1) ** s * 1e-3}
                            for r in range(2) for phase in ("experts", "gating")
                            for s in range(5)])
    fig = plotting.plot_learning_curves(history)
    visible = [ax for ax in fig.axes if ax.get_visible()]
    assert [ax.get_title() for ax in visible] == [
        "phase 1: mixture error $E$", "phase 2: gating error $E^g$",
        r"phase 2: $\lambda_{\max}$"]
    assert visible[2].get_yscale() == "symlog" and visible[0].get_yscale() == "log"
    assert len(fig.legends) == 1 and all(ax.get_legend() is None for ax in visible)
    ax = plotting.plot_residence(np.zeros((2, 20)))
    assert "never completed" in ax.texts[0].get_text() and ax.get_legend() is None
    many_short = np.zeros((2, 20), dtype=int)
    many_short[0, 1], many_short[1, 5] = 1000, 1  # run 0: 1000 stays of 1 lap; run 1: one of 5
    ax = plotting.plot_residence(many_short, switch_prob=0.5)
    heights = {round(b.get_x() + b.get_width() / 2): b.get_height() for b in ax.patches}
    assert heights[1] == heights[5] == 0.5  # each run weighs the same (Fig. 9's average)
    ax = plotting.plot_phase_portrait(np.tile([[0.2, -0.3]], (100, 1)), title="run 0")
    assert "a fixed point at (0.2, -0.3)" in ax.get_title()
    plt.close("all")


def test_every_format_is_written(tmp_path):
    for fmt in plotting.FORMATS:
        fig = plt.figure()
        path = plotting.save_figure(fig, tmp_path / "x.png", fmt)
        assert path == tmp_path / f"x.{fmt}" and path.stat().st_size > 0


def test_gate_series_labels_every_step_of_a_short_window_and_each_run_of_a_long_one():
    K, names = 3, ["a", "b", "c"]
    symbols = np.repeat([0, 1, 0, 2], 13)[:50]
    axes = plotting.plot_gate_series(np.zeros((50, 2)), _one_hot(symbols, K), symbols, names)
    assert [text.get_text() for text in axes[1].texts] == [names[s] for s in symbols]
    symbols = np.repeat([0, 1, 2, 0, 1], [100, 2, 98, 50, 50])  # a 2-step flicker of "b"
    axes = plotting.plot_gate_series(np.zeros((300, 2)), _one_hot(symbols, K), symbols, names)
    labels = [(int(text.get_position()[0]), text.get_text()) for text in axes[1].texts]
    assert labels == [(50, "a"), (151, "c"), (225, "a"), (275, "b")]
    symbols = np.array([0, 3, 1])  # eval.symbol_rule=threshold: K is "no gate above 0.5"
    axes = plotting.plot_gate_series(np.zeros((3, 2)), _one_hot(symbols, K + 1)[:, :K], symbols,
                                     names)
    assert [text.get_text() for text in axes[1].texts] == ["a", "–", "b"]
    plt.close("all")


def test_scatter_draws_networks_that_belong_to_no_study_arm():
    """A run folder that is not a study arm has an empty `p05_arm` column: every network is still a
    point (in one group), and the legend does not call them a study arm."""
    runs = pd.DataFrame({"max_lyapunov": [1e-3, 2e-3, -1e-5], "switch_prob": [0.4, 0.5, 0.0],
                         "p05_arm": [np.nan] * 3})
    fig = plotting.plot_scatter_by(runs, "max_lyapunov", "switch_prob", "p05_arm")
    ax = fig.axes[0]
    assert sum(len(c.get_offsets()) for c in ax.collections) == 3
    assert ax.get_legend().get_title().get_text() == ""
    plt.close(fig)


def test_a_heatmap_writes_each_cell_and_names_the_cells_not_run():
    cells = pd.DataFrame({"num_series": [2, 2, 5], "length": [250, 500, 250],
                          "E_closed_mean": [0.01, 0.02, 0.03]})  # NT 5 / LT 500 not run
    fig = plotting.plot_heatmap(cells, "num_series", "length", "E_closed_mean",
                                limits=(0.005, 0.05))
    texts = {(t.get_position(), t.get_text()) for t in fig.axes[0].texts}
    assert texts == {((0, 0), "0.01"), ((0, 1), "0.02"), ((1, 0), "0.03"), ((1, 1), "not run")}
    assert len(fig.axes) == 2  # the panel and its colour bar
    fig = plotting.plot_heatmap(cells, "num_series", "length", "E_closed_mean",
                                limits=(0.005, 0.05), colorbar=False)
    assert len(fig.axes) == 1  # a panel in a row whose neighbour carries the bar
    plt.close("all")


def test_scatter_ticks_cover_exponents_that_all_lie_near_zero():
    """λ_max all within ±1e-5 (a run of limit cycles): a linear axis with 0 and ticks inside the
    data, not symlog's two labels at the axis ends (read as −2.94195×10⁻⁶ ... 3.01911×10⁻⁶)."""
    import numpy as np
    import pandas as pd

    from moex import plotting

    rng = np.random.default_rng(0)
    runs = pd.DataFrame({"max_lyapunov": rng.normal(0, 2e-6, 12),
                         "switch_prob": rng.uniform(0.2, 0.21, 12), "task.switch_prob": 0.5})
    fig = plotting.plot_scatter_by(runs, "max_lyapunov", "switch_prob", "task.switch_prob")
    ax = fig.axes[0]
    fig.canvas.draw()
    ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    assert ax.get_xscale() == "linear" and 0.0 in ticks and len(ticks) >= 4
    wide = runs.assign(max_lyapunov=runs["max_lyapunov"] * 1e3)  # past ±1e-4: symlog
    assert plotting.plot_scatter_by(wide, "max_lyapunov", "switch_prob",
                                    "task.switch_prob").axes[0].get_xscale() == "symlog"


def test_titles_count_in_words_a_reader_expects():
    """No "runs 0-0", "series 0-0 of 1" or "each of the 1 runs" in a title."""
    from moex.figures import numbered

    assert [numbered("run", 1), numbered("run", 5), numbered("series", 1, 1),
            numbered("series", 3, 10), numbered("series", 2, 2)] == [
        "run 0", "runs 0-4", "series 0", "series 0-2 of 10", "series 0-1"]


def test_reber_gates_title_caption_and_symbol_row_never_overprint():
    """A task without a signal (Reber) draws the gates alone: the figure's title, the symbols'
    caption and the row of symbols are three separate bands (rendered boxes do not overlap),
    and the gates are named by their symbols."""
    import matplotlib.pyplot as plt

    from moex.plotting import plot_gate_series

    names = ["T", "P", "S", "X", "V", "E", "B"]
    gates = np.full((100, 7), 1 / 7)
    symbols = np.arange(100) % 7
    axes = plot_gate_series(np.zeros((100, 0)), gates, symbols, names,
                            bad=np.arange(100) % 9 == 0)
    fig = axes[0].figure
    fig.suptitle("closed loop, run 0: gate openings and symbols")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    title, caption = fig._suptitle.get_window_extent(renderer), axes[1].title.get_window_extent(
        renderer)
    row = [t.get_window_extent(renderer) for t in axes[1].texts]
    assert not title.overlaps(caption)
    assert not any(caption.overlaps(box) or title.overlaps(box) for box in row)
    assert [t.get_text() for t in axes[1].get_yticklabels()][0] == "0 (T)"
    assert "red: a step the grammar forbids" in axes[1].get_title(loc="left")
    plt.close(fig)


def test_many_experts_keep_their_ticks_readable_and_expert_panels_have_axes():
    """24 experts: at most 12 expert ticks on gates.png; every panel of experts.png has ticks on
    the common [-1, 1] scale and the outer panels name y_1 and y_2."""
    import matplotlib.pyplot as plt

    from moex.plotting import plot_expert_panels, plot_gate_series

    rng = np.random.default_rng(0)
    gates = rng.dirichlet(np.ones(24), 200)
    outputs = rng.uniform(-1, 1, (200, 2))
    axes = plot_gate_series(outputs, gates, gates.argmax(1) % 9, [str(i) for i in range(9)])
    assert len(axes[1].get_yticks()) <= 12
    plt.close(axes[0].figure)
    panels = plot_expert_panels(outputs, gates)
    shown = [ax for ax in np.ravel(panels) if ax.get_visible()]
    assert all(list(ax.get_xticks()) == [-1, 0, 1] for ax in shown)
    assert any(ax.get_xlabel() == "$y_1$" for ax in shown)
    assert any(ax.get_ylabel() == "$y_2$" for ax in shown)
    plt.close(shown[0].figure)


def test_run_panels_keep_points_off_the_spine_and_list_only_winning_experts():
    """A fixed point near the edge of the data sits inside the common scale with a margin; the
    colour key lists the experts that win somewhere, not all K."""
    import matplotlib.pyplot as plt

    from moex.plotting import plot_run_trajectories

    outputs = np.tile([[0.01, -0.052]], (2, 50, 1))
    gates = np.zeros((2, 50, 24))
    gates[..., 11] = 1.0
    fig = plot_run_trajectories(outputs, gates, ["run 0", "run 1"], "the closed loop")
    low, high = fig.axes[0].get_ylim()
    assert low < -0.052 * 1.1 and high > 0.052
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["expert 11"]
    plt.close(fig)


def test_residence_panels_share_one_x_label_and_the_overflow_bar_is_visible():
    """Three P panels: one x label for the row (none overprint) and the last bin's bar (every
    stay at least 100 laps) at least 1/50 of the axis wide."""
    import matplotlib.pyplot as plt

    from moex.plotting import plot_residence_panels

    hist = np.zeros((1, 101), int)
    hist[0, 1:4], hist[0, 100] = (50, 20, 5), 2
    fig = plot_residence_panels({p: (hist, np.zeros_like(hist)) for p in (0.5, 0.25, 0.125)})
    assert [ax.get_xlabel() for ax in fig.axes] == ["", "", ""]
    assert "every stay at least as long" in fig.get_supxlabel()
    widths = [patch.get_width() for patch in fig.axes[0].patches]
    assert max(widths) >= 101 / 50
    plt.close(fig)
