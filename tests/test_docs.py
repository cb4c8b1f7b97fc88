"""REPRODUCTION.md and its pages (docs/reproduction/, docs/verdicts.md) quote the tables that
scripts in docs/ recompute from the CSVs; the report stays short enough to read."""

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

ROOT = Path(__file__).resolve().parent.parent
PAGES = ROOT / "docs" / "reproduction"


def _page(name: str) -> str:
    return (PAGES / f"{name}.md").read_text()


def _script(name):
    """A study of the reproduction (`studies/`), imported as the package's module."""
    return importlib.import_module(f"studies.{name}")


def test_the_verdict_table_is_the_one_the_csvs_give():
    verdicts = _script("verdicts")
    table = verdicts.markdown(verdicts.verdicts())
    assert len(table.splitlines()) == 2 + 4 * 5 + 3 * 3
    assert table in (ROOT / "REPRODUCTION.md").read_text()
    assert verdicts.tally(verdicts.verdicts()) in (ROOT / "REPRODUCTION.md").read_text()
    full = verdicts.markdown(verdicts.verdicts(), evidence=True)
    assert full in (ROOT / "docs" / "verdicts.md").read_text()


def test_the_report_is_short_its_verdicts_terse_and_every_page_linked():
    """REPRODUCTION.md: at most 150 lines (a 10-minute read), its verdict table at most 5
    columns, verdict cells of at most 25 words, a link to every
    page under docs/reproduction/, and no link to a page or anchor that does not exist."""
    import re

    text = (ROOT / "REPRODUCTION.md").read_text()
    assert len(text.splitlines()) <= 150
    header = next(line for line in text.splitlines() if line.startswith("| result | quantity"))
    assert header.count("|") - 1 <= 5
    for term in ("**NT**", "**NC**", "**E^g**", "**R**", "**u₀ attraction**",
                 "**soft phase-2 targets**"):  # every term defined before the tables
        assert text.index(term) < text.index("## In brief"), term
    verdicts = _script("verdicts")
    assert all(len(cell.split()) <= 25 for cell in verdicts.verdicts()["verdict"])
    for page in PAGES.glob("*.md"):
        assert f"docs/reproduction/{page.name}" in text, page.name
    for source in [ROOT / "REPRODUCTION.md", ROOT / "README.md", ROOT / "docs" / "verdicts.md",
                   *PAGES.glob("*.md")]:
        for target, anchor in re.findall(r"\]\(([^)#:]+\.md)(?:#([^)]+))?\)",
                                         source.read_text()):
            path = (source.parent / target).resolve()
            assert path.is_file(), f"{source.name} links to {target}"
            if anchor:
                heads = [re.sub(r"[^\w\- ]", "", h.lstrip("#").strip().lower()).replace(" ", "-")
                         for h in path.read_text().splitlines() if h.startswith("#")]
                assert anchor in heads, f"{source.name} links to {target}#{anchor}"


def test_the_tally_counts_each_kind_of_verdict_once():
    verdicts = _script("verdicts")
    frame = pd.DataFrame({"verdict": ["reproduced", "reproduced (1 network carries it)",
                                      "differs, cause found: y", "differs, candidate cause: v",
                                      "differs, cause open", "inconclusive",
                                      "inconclusive (2 networks carry it)"]})
    assert verdicts.tally(frame) == (
        "Of the table's 7 rows, by one rule (studies/verdicts.py): 2 reproduced; 3 differ, 1 with "
        "the cause found, 1 with a candidate cause and 1 with the cause open; 2 inconclusive; 2 "
        "of them rest on one or two networks.")


def test_sentences_that_went_stale_are_computed_now():
    """Question 4's answer is the one docs/lyapunov_crosscheck.csv gives (it said 20 networks,
    r 0.26 and "in all 20" after the control grew to 40); the sentences the audit found stale
    are gone from every page."""
    v = _script("verdicts")
    assert v.tool_question() in (ROOT / "docs" / "verdicts.md").read_text()
    pages = [ROOT / "REPRODUCTION.md", ROOT / "docs" / "verdicts.md"]
    for stale in ("(r 0.26)", "in all 20", "the end of training was not checked",
                  "into agreement", "initial network up\nto 55 %", "(below, \"How much"):
        for page in pages:
            assert stale not in page.read_text(), (stale, page.name)


def test_the_verdict_rule_on_cases_with_known_answers():
    """`decide`: an interval inside the margin around 0 is reproduced, one that excludes 0
    differs, a wide one is inconclusive; `needed` finds the n at which the interval's half-width
    equals the room left; Newcombe's interval of two equal shares is centred on 0 and those of
    100 % against 100 % stay inside [-100, 100]; a verdict resting on one outlier is flagged."""
    v = _script("verdicts")
    assert v.decide(-0.1, 0.1, 0.2) == "reproduced"
    assert v.decide(0.01, 0.05, 0.2) == "differs" and v.decide(-0.5, -0.01, 1) == "differs"
    assert v.decide(-0.3, 0.1, 0.2) == "inconclusive"
    # d = 0, sd = spread = 1, margin 0.5, the paper's n huge: (0.5/1.96)² = 1/n -> n = 15.4
    assert v.needed(0.0, 1.0, 1.0, 10**9, 0.5) == "about 16 networks would decide it"
    assert "no number" in v.needed(0.0, 1.0, 1.0, 10, 0.5)  # the paper's error alone is wider
    diff, low, high = v.share_interval(15, 30, 50, 30)
    assert diff == 0 and low == pytest.approx(-high)
    diff, low, high = v.share_interval(50, 50, 100, 50)
    assert diff == 0 and -100 <= low < 0 < high <= 100
    rng = np.random.default_rng(0)
    values = rng.normal(0, 1, 50)
    assert v.robust_sd(values) == pytest.approx(1, abs=0.3)
    mean = _row_word(v, values, 0.0)
    assert mean == "reproduced"
    outlier = np.append(values[:-1], 60.0)  # one network far out: the interval widens
    assert _row_word(v, outlier, 0.0) == "inconclusive"
    assert v._carried(outlier, "inconclusive", lambda x: _row_word(v, x, 0.0)) == \
        " (1 network carries it)"


def _row_word(v, values, paper, paper_n=10**6):
    return v.decide(*v._mean_interval(np.asarray(values), paper, paper_n)[1:4])


def test_every_verdict_is_the_rules_word_for_its_own_interval():
    """Each row of the table: the verdict's first word is `decide` of the interval and margin the
    row prints (so no row's word is set by hand)."""
    import re

    v = _script("verdicts")
    for row in v.verdicts().itertuples():
        cell = row[list(v.verdicts().columns).index("moex − paper [95 %] (margin)") + 1]
        low, high, margin = map(float, re.findall(r"\[(\S+), (\S+)\].*± ([\d.e+-]+)\)",
                                                  cell)[0])
        word = v.decide(low, high, margin)
        assert row.verdict.startswith(word), (row.result, row.quantity, cell, row.verdict)


def test_the_one_hot_tables_are_the_ones_the_csvs_give():
    onehot = _script("table2_onehot")
    rows, pairs = onehot.table()
    assert len(rows) == 2 * len(pairs) and set(rows["targets"]) == {"soft", "one-hot"}
    text = _page("table2_onehot")
    assert onehot.markdown(rows) in text and onehot.markdown(pairs) in text


def test_the_data_seed_overview_is_the_one_the_csvs_give():
    seeds = _script("data_seeds")
    table = seeds.overview()
    assert set(table["experiment"]) == set(seeds.EXPERIMENTS)  # every experiment's CSV is there
    assert seeds.to_markdown(table) in _page("data_seeds")


def test_the_two_way_split_recovers_a_known_data_effect():
    """A crossed table made of a data-set effect, a network effect and noise of known variances:
    the components come back near them, and the restricted permutation test sees the data."""
    seeds = _script("data_seeds")
    rng = np.random.default_rng(1)
    data, nets = rng.normal(0, 2.0, (40, 1)), rng.normal(0, 1.0, (1, 30))
    table = data + nets + rng.normal(0, 0.5, (40, 30))
    var_data, var_net, var_rest = seeds.components(table)
    assert abs(var_data / 4.0 - 1) < 0.5 and abs(var_net / 1.0 - 1) < 0.5
    assert abs(var_rest / 0.25 - 1) < 0.15
    runs = pd.DataFrame([{"task.data_seed": d, "run": r, "x": table[d, r]}
                         for d in range(8) for r in range(5)])
    assert seeds.two_way(runs, "x", permutations=2000)["data set p"] < 0.01
    flat = runs.assign(x=nets[0, runs["run"]] + rng.normal(0, 0.5, len(runs)))
    assert seeds.two_way(flat, "x", permutations=2000)["data set p"] > 0.01


def test_the_design_comparison_is_the_one_the_csvs_give():
    designs = _script("table2_designs")
    rows, tests = designs.table()
    assert len(rows) == 2 * len(tests) and len(tests) >= 1
    text = _page("table2_own_data")
    assert designs.markdown(rows) in text and designs.markdown(tests) in text


def test_the_capacity_grid_tables_are_the_ones_the_csv_gives():
    cells = _script("capacity_cells")
    table = pd.read_csv(ROOT / "docs" / "capacity_grid_summary.csv")
    text = _page("capacity")
    assert cells.cell_tables(table) in text
    assert f"{cells.zero_band(table):.2g}" in text
    assert cells.to_markdown(cells.replication(table)) in text
    window = pd.read_csv(ROOT / "docs" / "capacity_window10k_summary.csv")
    assert cells.to_markdown(cells.window_table(window, table)) in text
    assert cells.to_markdown(cells.embedding(table)) in text
    assert cells.to_markdown(cells.chaos_against_data(table)) in text
    arms = pd.read_csv(ROOT / "docs" / "fig16_arms.csv")
    assert cells.to_markdown(_script("fig16_arms").table(arms)) in text
    rows = cells.to_markdown(cells.figure_rows(table, arms)).splitlines()[2:]
    assert [row.split(" | ")[0] for row in rows] == ["| Fig. 14a", "| Fig. 14b", "| Fig. 16"]
    full = (ROOT / "docs" / "verdicts.md").read_text().splitlines()
    assert all(row in full for row in rows)  # the figure verdicts' rows


def test_the_fig16_arms_table_counts_each_arm_against_its_baseline(tmp_path):
    arms = _script("fig16_arms")
    sweep = tmp_path / "nc10"
    (sweep / "0" / "evaluate" / "noise0.001").mkdir(parents=True)
    (sweep / "1" / "evaluate" / "noise0.001").mkdir(parents=True)
    pd.DataFrame({"folder": ["0", "1"], "overrides": [
        f"p05_arm={arm} task.num_series=2 model.gating.context_size=10"
        for arm in ("baseline", "c_code")]}).to_csv(sweep / "jobs.csv", index=False)

    def runs(nonperiodic, lyapunov, switching):
        return pd.DataFrame({"run": range(4), "E_closed": 1e-6, "max_lyapunov": lyapunov,
                             "switch_prob": switching, "nonperiodic_fraction": nonperiodic,
                             "periodicity_samples": 50})
    runs([0.9, 0.1, 0, 0], [1e-3, 0, 0, 0], 0.5).to_csv(sweep / "0" / "metrics.csv")
    runs([1, 1, 0.8, 0.2], [1e-3, 0, 0, 0], 0.5).to_csv(
        sweep / "0" / "evaluate" / "noise0.001" / "metrics.csv")
    runs([0, 0, 0, 0], [0, 0, 0, 0], [1, 1, 1, 0]).to_csv(sweep / "1" / "metrics.csv")
    runs([0, 0, 0, 0.6], [0, 0, 0, 0], 1).to_csv(
        sweep / "1" / "evaluate" / "noise0.001" / "metrics.csv")
    frame = arms.table(arms.collect([sweep])).set_index("arm")
    assert frame.loc["baseline", "mostly nonperiodic, ρ² = 0 → 10⁻³"] == "1 → 3"
    assert frame.loc["c_code", "mostly nonperiodic, ρ² = 0 → 10⁻³"] == "0 → 1"
    p = _script("capacity_cells").fisher_p(1, 3, 3, 1)
    assert frame.loc["c_code", "p against baseline (10⁻³)"] == f"{p:.2g}"
    assert (frame.loc["baseline", "λ_max > 0 (> 10⁻⁴)"],
            frame.loc["c_code", "stay (< 0.02)"]) == ("1 (1)", 1)


def test_new_cells_join_the_grid_and_a_network_twice_is_refused():
    cells = _script("capacity_cells")
    grid = pd.read_csv(ROOT / "docs" / "capacity_grid_summary.csv")
    cell = grid[(grid.context_size == 10) & (grid.num_series == 2) & (grid.length == 250)]
    new = cell.assign(length=4000)  # a cell the grid lacks
    merged = cells.merge_cells([grid, new])
    assert len(merged) == len(grid) + len(new)
    added = merged[merged.length == 4000].reset_index(drop=True)
    expected = new.sort_values(["noise_var", "run"], ignore_index=True)[added.columns]
    pd.testing.assert_frame_equal(added, expected)
    with pytest.raises(ValueError, match=r"\(10, 2, 250\)"):
        cells.merge_cells([grid, cell])


def test_adding_a_network_twice_exits_2_with_one_line_and_leaves_the_csv(tmp_path):
    grid = ROOT / "docs" / "capacity_grid_summary.csv"
    before = grid.read_bytes()
    pd.read_csv(grid).head(1).to_csv(tmp_path / "summary.csv", index=False)
    done = subprocess.run([sys.executable, "-m", "studies.capacity_cells", "add", str(tmp_path)],
                          capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.count("\n") == 1 and "networks appear twice" in done.stderr
    assert grid.read_bytes() == before


def test_fishers_exact_test_gives_the_textbook_p_values():
    cells = _script("capacity_cells")
    assert np.isclose(cells.fisher_p(3, 1, 1, 3), 34 / 70)  # Fisher's tea-tasting table
    assert np.isclose(cells.fisher_p(10, 0, 0, 10), 2 / 184756)  # the two extreme tables
    assert cells.fisher_p(5, 5, 5, 5) == 1.0
    assert np.isclose(cells.fisher_p(1, 9, 10, 0), cells.fisher_p(10, 0, 1, 9))


def test_the_embedding_split_counts_networks_and_tests_at_the_level_of_the_cell():
    cells = _script("capacity_cells")
    # four cells of two networks: two embed their data and switch, two do not and stay
    table = pd.DataFrame({"context_size": 10, "noise_var": [0] * 8 + [1e-3],
                          "num_series": [2, 2, 2, 2, 5, 5, 5, 5, 5],
                          "length": [250, 250, 500, 500, 250, 250, 500, 500, 500],
                          "E_closed": [1e-6] * 4 + [0.1] * 5,
                          "max_lyapunov": [3e-3, -1e-3, 5e-5, 2e-3, 2e-3, 5e-5, -1e-3, 3e-3, 1],
                          "switch_prob": [0.4] * 4 + [0.0] * 5})
    row = cells.embedding(table).iloc[0]  # the noisy row does not count
    # λ_max > 0 (the paper's criterion), in brackets > 10⁻⁴
    assert (row["chaotic: embed"], row["chaotic: do not"]) == ("3 (2) / 4", "3 (2) / 4")
    assert (row["stay on one curve: embed"], row["stay on one curve: do not"]) == ("0 / 4",
                                                                                  "4 / 4")
    # the cells' label sets [1, 1], [1, 1], [0, 0], [0, 0] have C(4, 2) = 6 assignments, 2 as
    # extreme as the observed one: p = 1/3, where Fisher's test of 8 independent networks
    # gives 2/70
    p = float(row["stay on one curve: p over cells"])
    assert p == pytest.approx(1 / 3, abs=0.01)
    assert cells.fisher_p(0, 4, 4, 0) == pytest.approx(2 / 70)
    assert float(row["chaotic: p over cells"]) == 1.0  # equal shares: every relabelling as far


def test_the_data_trend_is_spearmans_rho_per_nc_with_a_permutation_p():
    cells = _script("capacity_cells")
    frame = pd.DataFrame({"context_size": [10] * 4 + [30] * 4, "data": [1, 2, 3, 4] * 2,
                          "chaotic": [0.1, 0.2, 0.3, 0.4, 0.4, 0.3, 0.2, 0.1]})
    trend = cells.data_trend(frame, "chaotic")
    assert trend[10][0] == pytest.approx(1) and trend[30][0] == pytest.approx(-1)
    # 2 of the 4! = 24 orderings are as extreme as a perfect rank order
    assert trend[10][1] == pytest.approx(2 / 24, abs=0.01)
    # no shuffle of 30 ranks matches a perfect order: p is the observed order's 1 in 100, not 0
    assert cells.spearman(np.arange(30), np.arange(30), permutations=99)[1] == 0.01


def test_the_zero_band_is_the_largest_exponent_of_an_all_periodic_network():
    cells = _script("capacity_cells")
    table = pd.DataFrame({"noise_var": [0, 0, 0, 1e-3, 0, 0],
                          "nonperiodic_fraction": [0, 0, 0.5, 0, 0, 0],
                          "max_lyapunov": [-1e-3, 2e-6, 5e-3, 9e-3, 7e-5, 4e-3],
                          "periodicity_samples": [50, 50, 50, 50, float("nan"), 50],
                          "switch_prob": [0.5, 0.9, 0.4, 0.5, 0.5, 0.0]})
    # not the nonperiodic network, not the noisy row, not a network whose samples were not
    # counted, not one that stays on one curve (one symbol for ever: periodic, yet chaotic)
    assert cells.zero_band(table) == 2e-6


def test_the_residence_table_is_the_one_the_csv_gives():
    residence = _script("residence")
    table = residence.table(pd.read_csv(residence.CSV))
    assert list(table.P) == [0.5, 0.25, 0.125] and (table.networks == 30).all()
    assert residence.to_markdown(table) in _page("table2_own_data")


def test_stays_drawn_from_the_geometric_law_are_at_zero_distance_from_it():
    residence = _script("residence")
    p, rng = 0.25, np.random.default_rng(0)
    assert np.isclose(residence.law(p).sum(), 1)
    laps = np.minimum(rng.geometric(p, size=(4, 200_000)), residence.LONG)
    stays = pd.DataFrame([{"P": p, "job": "j", "run": r, "laps": k, "completed": n, "cut": 0}
                          for r in range(4)
                          for k, n in zip(*np.unique(laps[r], return_counts=True), strict=True)])
    row = residence.table(stays).iloc[0]
    assert row["total variation from the law"] <= 0.005 and row["networks"] == 4
    assert row["mean laps, completed stays pooled (law 1/P)"].startswith("4.0")


def test_the_control_table_is_the_one_the_csvs_give():
    """The authors' C tools trained on moex's data and scored by moex (studies/mregn_control.py):
    docs/mregn_control.md quotes the table the per-network CSVs give."""
    control = _script("mregn_control")
    rows = control.table()
    assert {"reber_nc20", "reber_nc30"} <= set(rows["design"])
    assert (rows["control_n"] >= 2).all() and rows["permutation_p"].between(0, 1).all()
    table = control.markdown(rows)
    assert table in (ROOT / "docs" / "mregn_control.md").read_text()


def test_the_control_labels_table_is_the_one_the_csv_gives():
    """docs/mregn_control.md quotes the chaos labels of every control design as the per-network
    CSV gives them (the paper-setting designs included)."""
    control = _script("mregn_control")
    frame = control.labels_table()
    assert {"table2_p05_paper", "table2_p025_paper", "reber_nc20_no_attraction"} <= set(
        frame["design"])
    assert control.labels_markdown(frame) in (ROOT / "docs" / "mregn_control.md").read_text()


def test_the_controls_prose_numbers_are_the_csvs():
    """The numbers docs/mregn_control.md writes out in words for the paper-setting designs (the
    NC 20 arm without u₀ attraction, Table 2's counts so far) are those of the per-network CSV."""
    from math import comb

    from moex.report import wilson_interval

    nets = pd.read_csv(ROOT / "docs" / "mregn_control_networks.csv")
    page = " ".join((ROOT / "docs" / "mregn_control.md").read_text().split())
    arm = nets[nets.design == "reber_nc20_no_attraction"]
    default = nets[nets.design == "reber_nc20"]
    fit = int((arm.E_g < 0.02).sum())
    assert f"all {len(arm)} networks** (E^g {arm.E_g.mean():.4f} ± {arm.E_g.std():.4f}" in page
    assert f"(λ_max {arm.max_lyapunov.mean():.3f} ± {arm.max_lyapunov.std():.3f};" in page
    assert (f"test KL of {arm.block_kl_test.mean():.3f} ± {arm.block_kl_test.std():.2g}, median "
            f"{arm.block_kl_test.median():.3f}") in page
    train = arm.block_kl_train
    assert f"training KL of {train.mean():.3f} ± {train.std():.3f}" in page
    assert int((default.E_g < 0.02).sum()) == 0 and fit == len(arm) == 20
    p_fisher = 1 / comb(len(arm) + len(default), fit)  # all fit in one arm, none in the other
    mantissa, exponent = f"{p_fisher:.0e}".split("e-")
    superscript = exponent.lstrip("0").translate(str.maketrans("0123456789", "⁰¹²³⁴⁵⁶⁷⁸⁹"))
    assert f"p = 1/C({len(arm) + len(default)}, {fit}) = {mantissa}·10⁻{superscript}" in page
    for design, p in (("table2_p05_paper", "0.5"), ("table2_p025_paper", "0.25")):
        runs = nets[nets.design == design]
        count = runs.chaos.value_counts()
        positive = int((runs.max_lyapunov > 0).sum())
        assert f"{len(runs)} networks per P" in page
        if p == "0.5":
            strict = int((runs.switch_prob >= 0.99).sum())
            high = wilson_interval(int(count.get("chaotic", 0)), len(runs))[1]
            assert f"(0 of {len(runs)}; 95 % Wilson interval [0, {high:.0f}] %): {strict} of " \
                f"{len(runs)}" in page and count.get("chaotic", 0) == 0
            assert f"λ_max > 0 in {positive} of {len(runs)} by the paper's criterion" in page
        else:
            assert (f"At P = 0.25: {count.get('chaotic', 0)} chaotic, "
                    f"{count.get('undetermined', 0)} undetermined, {count.get('not chaotic', 0)} "
                    f"not chaotic (λ_max > 0 in {positive} of {len(runs)})") in page


def test_collecting_the_control_keeps_the_designs_imported_in_another_sitting(tmp_path,
                                                                          monkeypatch):
    """`mregn_control.py compare` reads the designs imported under <out>; the rows of designs
    imported before (their folders gone) stay, and an imported design's rows are replaced."""
    import pandas as pd

    control = _script("mregn_control")
    monkeypatch.setattr(control, "DOCS", tmp_path)
    pd.DataFrame({"run": [0, 1, 0], "max_lyapunov": [0.1, 0.2, 9.0],
                  "design": ["reber_nc20", "reber_nc20", "table2_p05"]}).to_csv(
        tmp_path / "mregn_control_networks.csv", index=False)
    imported = tmp_path / "out" / "table2_p05" / "moex"
    imported.mkdir(parents=True)
    pd.DataFrame({"run": [0, 1], "max_lyapunov": [-1e-4, -2e-4]}).to_csv(
        imported / "metrics.csv", index=False)
    rows = pd.read_csv(control.collect(tmp_path / "out"))
    assert sorted(rows["design"]) == ["reber_nc20"] * 2 + ["table2_p05"] * 2
    assert rows[rows["design"] == "table2_p05"]["max_lyapunov"].tolist() == [-1e-4, -2e-4]
    assert rows[rows["design"] == "reber_nc20"]["max_lyapunov"].tolist() == [0.1, 0.2]


def test_their_lyapunov_tool_is_the_one_for_the_networks_file(tmp_path):
    """`mregn_control.py lyapunov` scores a mixture (gn.dat) with `mregn-lyapunov` and a Reber RNN
    (rnn.dat) with `rnn-lyapunov`, at moex's evaluation sizes, with the network's seed; it skips
    unfinished networks and keeps what a tool printed (run again: not called again)."""
    control = _script("mregn_control")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool, values in (("mregn-lyapunov", "0.5\\n-0.25"), ("rnn-lyapunov", "0.125")):
        script = bin_dir / tool
        script.write_text(f'#!/bin/sh\necho "$@" >> "{tmp_path}/calls"\nprintf "{values}\\n"\n')
        script.chmod(0o755)
    for design, name, seed, done in (("table2_p05", "gn.dat", 3, True),
                                     ("reber_nc20", "rnn.dat", 7, True),
                                     ("reber_nc20", "rnn.dat", 8, False)):
        folder = tmp_path / "out" / design / f"net{seed:03d}"
        folder.mkdir(parents=True)
        (folder / name).write_text("")
        if done:
            (folder / "done").write_text("1 s\n")
    for _ in range(2):
        mixture = control.their_lyapunov("table2_p05", bin_dir, tmp_path / "out")
        rnn = control.their_lyapunov("reber_nc20", bin_dir, tmp_path / "out")
    assert mixture == [{"design": "table2_p05", "network": "net003", "samples": 2,
                        "max_lyapunov": 0.125, "positive_samples": 1}]
    assert rnn == [{"design": "reber_nc20", "network": "net007", "samples": 1,
                    "max_lyapunov": 0.125, "positive_samples": 1}]
    assert (tmp_path / "calls").read_text().splitlines() == [
        "-s 3 -n 100000 -c 50 -t 1000 -l 1 mre.dat gn.dat",
        "-s 7 -n 10000 -c 200 -t 1000 -l 1 rnn.dat"]


def test_paired_estimates_agree_with_themselves():
    """studies/lyapunov_crosscheck.py's per-network summary of paired samples: a gap of 0 and every
    sign the same when both estimates are equal; one sample of opposite sign counted."""
    check = _script("lyapunov_crosscheck")
    frame = pd.DataFrame({"design": "d", "network": ["a"] * 3 + ["b"] * 2,
                          "sample": [0, 1, 2, 0, 1], "exact": [0.1, -0.2, 0.3, 0.01, -0.01]})
    same = check.agreement(frame.assign(two_trajectories=frame["exact"]))
    assert (same["largest_gap"] == 0).all() and same["same_sign"].tolist() == [3, 2]
    off = check.agreement(frame.assign(two_trajectories=[0.1, -0.2, 0.3, 0.01, 0.02]))
    assert off["same_sign"].tolist() == [3, 1]
    assert off["largest_gap"].tolist() == [0.0, pytest.approx(0.03)]


def test_the_pooled_mean_counts_an_initial_network_once_however_many_data_sets_it_ran_on():
    """studies/verdicts.py `pooled`, on cases with known answers: 5 initial networks each run on 6
    data sets with no data effect (the same value 6 times) and 25 networks run once give the
    plain mean and sd/√30 of the 30 networks' values (not /√55); a unit's data sets are averaged
    before units are."""
    verdicts = _script("verdicts")
    rng = np.random.default_rng(3)
    values = rng.normal(2.0, 1.0, 30)
    frame = pd.DataFrame({"unit": [f"n{i}" for i in range(5) for _ in range(6)]
                          + [f"n{i}" for i in range(5, 30)],
                          "value": np.concatenate([np.repeat(values[:5], 6), values[5:]])})
    mean, se, units, observations = verdicts.pooled(frame)
    assert (units, observations) == (30, 55)
    assert np.isclose(mean, values.mean()) and np.isclose(se, values.std(ddof=1) / np.sqrt(30))
    two = pd.DataFrame({"unit": ["a", "a", "b"], "value": [1.0, 3.0, 5.0]})
    assert verdicts.pooled(two)[0] == 3.5  # a's mean 2 and b's 5, each once
    table2 = verdicts.units("Table 2", "P = 0.25", "switch_prob")
    assert table2["unit"].nunique() < len(table2)  # the data-seed networks share units


def test_two_trajectories_give_the_exponent_the_jacobian_gives():
    """studies/lyapunov_crosscheck.py's Jacobian-free check (two trajectories 10⁻⁸ apart,
    renormalised) recovers the largest exponent moex's Benettin estimator finds on the same
    closed loop: a contracting mixture (as initialised) and a chaotic one (experts without leak,
    τ = 1, recurrent weights 16 times larger)."""
    from moex.closed_loop import closed_loop_lyapunov
    from moex.config.model import ModelConfig
    from moex.kernels import get_backend
    from moex.model import init_experts, init_gating, random_state
    from tests.helpers import generators

    check = _script("lyapunov_crosscheck")
    backend = get_backend("cpu")
    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 4, 6
    experts = init_experts(model, 1, 2, generators([0]), torch.float64)
    gating = init_gating(model, 1, 2, generators([2]), torch.float64)
    chaotic = {**experts, "w_rec": 16 * experts["w_rec"], "tau": torch.ones_like(experts["tau"])}
    found = []
    for mixture, gates in ((experts, gating),
                           (chaotic, {**gating, "tau": torch.ones_like(gating["tau"])})):
        state = random_state(mixture, gates, 1, num_features=2, delay=1,
                             generator=torch.Generator().manual_seed(4))
        state = backend.closed_loop(mixture, gates, state, 500).state
        jacobian = closed_loop_lyapunov(mixture, gates, state, 5000, 0, backend=backend,
                                        generator=torch.Generator().manual_seed(5))[..., 0]
        direct = check.two_trajectories(mixture, gates, state, 5000, backend=backend,
                                        generator=torch.Generator().manual_seed(6))
        assert torch.allclose(direct, jacobian, rtol=0.02, atol=1e-3), (direct, jacobian)
        found.append(float(jacobian))
    assert found[0] < -0.01 and found[1] > 0.05  # one contracting, one chaotic


def test_the_training_length_arm_pairs_networks_by_seed_and_names_what_each_does(tmp_path,
                                                                                  monkeypatch):
    """studies/lissajous9_length.py: a network is "like the paper's example" (λ_max > 0, held-out
    block KL < 2), "chaotic elsewhere" or "not chaotic"; the paired differences of arms equal to
    each other are 0; arms of other seeds are refused."""
    length = _script("lissajous9_length")
    rows = pd.DataFrame({"max_lyapunov": [0.007, 0.007, -0.005, 0.0],
                         "block_kl_test": [1.25, 5.9, 1.0, 1.0]})
    assert [length.behaviour(r) for r in rows.itertuples()] == [
        "like the paper's example", "chaotic elsewhere", "not chaotic", "not chaotic"]
    short = pd.read_csv(ROOT / "docs" / "lissajous9_summary.csv")
    short = short[short.job == "n5"]
    monkeypatch.setattr(length, "LONG", tmp_path / "long.csv")
    for steps in (10000, 20000):
        (tmp_path / str(steps)).mkdir()
        short.to_csv(tmp_path / str(steps) / "metrics.csv", index=False)
    length.collect(tmp_path / "10000", tmp_path / "20000").to_csv(length.LONG, index=False)
    same = length.differences(length.arms())
    for column in same.columns[1:]:
        assert same[column].iloc[:-2].str.startswith("+0 ± 0 (0 of 5 up)").all()
        assert same[column].iloc[-2:].tolist() == ["1 → 1 of 5", "4 → 4 of 5"]
    assert length.table(length.arms())["what it does"].iloc[1] == " → ".join(
        ["not chaotic"] * 3)
    frame = pd.read_csv(length.LONG)
    frame.assign(run=frame.run + 5).to_csv(length.LONG, index=False)
    with pytest.raises(ValueError, match="other seeds"):
        length.arms()


def test_the_training_length_tables_are_the_ones_the_csvs_give():
    length = _script("lissajous9_length")
    frames = length.arms()
    page = _page("lissajous9")
    assert length.to_markdown(length.table(frames)) in page
    assert length.to_markdown(length.differences(frames)) in page
    assert length.resolution(frames) in page


def test_the_fig15_detector_finds_a_flip_it_can_see_and_not_one_inside_its_floor():
    """studies/fig15.py `power`: a flip far beyond the noise floor is found every time, the paper's
    flip (−5.4e-5 → +9.95e-4) at a floor of 1e-5 almost always, at the end-of-training floors
    (≥ 2.2e-4) almost never; docs/fig15_power.csv is what the summary's floors give."""
    fig15 = _script("fig15")
    assert fig15.power(0.01, (-1.0, 1.0), trials=500) == 1.0
    assert fig15.power(1e-5, trials=500) > 0.95
    assert fig15.power(2.2e-4, trials=500) < 0.1
    table = fig15.power_table(pd.read_csv(ROOT / "docs" / "fig15_end_summary.csv"))
    pd.testing.assert_frame_equal(table, pd.read_csv(ROOT / "docs" / "fig15_power.csv"))


def test_the_site_builds_strictly_with_every_link_and_reference_resolved(tmp_path):
    """mkdocs.yml: the README, the user guide (guide/), its API reference from the docstrings
    and the reproduction pages as one site; `--strict` fails on a broken link, a missing anchor
    or a docstring mkdocstrings cannot render. The README stays a short entry (≤ 300 lines)."""
    assert len((ROOT / "README.md").read_text().splitlines()) <= 300
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                           str(tmp_path / "site")], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "NO_MKDOCS_2_WARNING": "1"}, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    api = (tmp_path / "site" / "guide" / "api" / "index.html").read_text()
    assert all(name in api for name in ("moex.api.fit", "moex.api.Fitted", "lyapunov_exponents"))
    site = tmp_path / "site"
    pages = {page.relative_to(site).as_posix() for page in site.rglob("*.html")}
    assert {"index.html", "REPRODUCTION/index.html", "guide/own-data/index.html"} <= pages
