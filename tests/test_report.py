import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import torch

from moex.report import (
    aggregate,
    gather,
    report,
    short_summary,
    to_markdown,
    wilson_interval,
)
from tests.test_cli import TINY

MOEX = [sys.executable, "-c", "from moex.cli import main; main()"]


@pytest.mark.parametrize("launcher", ["basic", "joblib"])
def test_tiny_paper_table2_sweep_and_report(launcher, tmp_path):
    sweep = tmp_path / "sweep"
    result = subprocess.run(
        MOEX + ["train", "-m", "experiment=paper_table2", *TINY, f"hydra/launcher={launcher}",
                f"hydra.sweep.dir={sweep}"] +
        (["hydra.launcher.n_jobs=2"] if launcher == "joblib" else []),
        cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    summary, last = result.stdout.strip().splitlines()[-2:]  # and what to run next
    assert summary.startswith(f"moex: sweep folder {sweep.resolve()}: 3 jobs (3 done"), summary
    assert last == f"moex: compare them with: moex report {sweep.resolve()}", last
    jobs = sorted((p for p in sweep.iterdir() if p.is_dir()),
                  key=lambda p: -float(p.joinpath(".hydra/config.yaml").read_text()
                                       .split("switch_prob: ")[1].split()[0]))
    assert sorted(p.name for p in jobs) == ["0", "1", "2"]
    index = pd.read_csv(sweep / "jobs.csv")  # which folder holds which overrides
    assert index["folder"].tolist() == [0, 1, 2]
    assert all("task.switch_prob=" in o for o in index["overrides"])
    jobs = [p.name for p in jobs]  # P = 0.5, 0.25, 0.125
    for job in jobs:
        assert json.loads((sweep / job / "status.json").read_text())["status"] == "done"
    # a partial sweep: remove one job's metrics (P = 0.125), mark another failed (P = 0.25)
    (sweep / jobs[2] / "metrics.csv").unlink()
    (sweep / jobs[1] / "status.json").write_text(json.dumps({"status": "failed",
                                                             "error": "RuntimeError: boom"}))
    out = subprocess.run(MOEX + ["report", str(sweep)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert "failed RuntimeError: boom" in out.stdout and "missing metrics" in out.stdout
    # the terminal gets a short summary (whole tables are in tables/), every line ≤ 100 columns
    assert max(len(line) for line in out.stdout.splitlines()[:-1]) <= 100, out.stdout
    assert "task.switch_prob 0.5: n 2; " in out.stdout and "tables/table2.md" in out.stdout
    table2 = pd.read_csv(sweep / "tables" / "table2.csv")
    assert table2["task.switch_prob"].tolist() == [0.5, 0.25, 0.125]
    assert table2["paper_switch_prob"].tolist() == [0.451033, 0.275999, 0.150866]
    row = table2.set_index("task.switch_prob")
    assert row.loc[0.125, "num_runs"] != row.loc[0.125, "num_runs"]  # missing, not zero
    assert row.loc[0.5, "num_runs"] == 2
    assert (sweep / "tables" / "table2.md").read_text().count("missing") >= 1
    assert (sweep / "summary.csv").exists() and (sweep / "tables" / "jobs.md").exists()
    # safe to re-run
    assert report(sweep)["table2"].shape == table2.shape


def test_aggregate_mean_sd_and_positive_share():
    runs = pd.DataFrame({"context_size": [10, 10, 10, 20], "max_lyapunov": [0.1, -0.1, 0.3, 0.2],
                         "E_g": [1.0, 2.0, 3.0, 4.0], "failed": [False, False, False, False]})
    table = aggregate(runs, ["context_size"]).set_index("context_size")
    assert table.loc[10, "E_g_mean"] == 2.0 and table.loc[10, "E_g_std"] == 1.0
    assert abs(table.loc[10, "positive_percent"] - 200 / 3) < 1e-9
    assert table.loc[20, "num_runs"] == 1


def test_wilson_interval_matches_its_closed_form_and_brackets_the_share():
    low, high = wilson_interval(26, 30)  # z = 1.96: [70.3, 94.7] % (closed form, by hand)
    assert abs(low - 70.32) < 0.01 and abs(high - 94.69) < 0.01
    assert wilson_interval(0, 10)[0] == 0 and wilson_interval(10, 10)[1] == 100
    assert all(np.isnan(wilson_interval(0, 0)))


def test_aggregate_share_near_the_data_and_interval_per_arm():
    runs = pd.DataFrame({"arm": ["a"] * 4 + ["b"] * 2,
                         "switch_prob": [0.45, 0.40, 0.60, 0.50, 1.0, 0.48],
                         "data_switch_prob": [0.47, 0.47, 0.47, 0.47, 0.47, 0.47],
                         "max_lyapunov": [0.1, 0.2, -0.1, 0.3, 0.0, 0.1],
                         "failed": [False] * 6})
    table = aggregate(runs, ["arm"]).set_index("arm")
    assert table.loc["a", "near_data_percent"] == 50 and table.loc["b", "near_data_percent"] == 50
    assert table.loc["a", "positive_percent"] == 75 and table.loc["b", "positive_percent"] == 50
    assert (table.loc["a", "positive_ci_low"], table.loc["a", "positive_ci_high"]) == \
        wilson_interval(3, 4)


def test_markdown_marks_missing_cells():
    text = to_markdown(pd.DataFrame({"a": [1.0, float("nan")], "b": ["x", "y"]}))
    assert text.splitlines()[0] == "| a | b |" and "| missing | y |" in text


def test_report_of_an_empty_folder_is_an_error(tmp_path):
    out = subprocess.run(MOEX + ["report", str(tmp_path)], capture_output=True, text=True)
    assert out.returncode == 2 and "holds no job folder" in out.stderr


def _fake_job(job_dir, config: str, metrics: dict, choices: str = "") -> None:
    """A finished job folder as a sweep leaves it: .hydra/config.yaml (and hydra.yaml with the
    config-group `choices`), status.json and metrics.csv (one run per value, none failed)."""
    hydra_dir = job_dir / ".hydra"
    hydra_dir.mkdir(parents=True)
    hydra_dir.joinpath("config.yaml").write_text(config)
    if choices:
        hydra_dir.joinpath("hydra.yaml").write_text(
            f"hydra:\n  runtime:\n    choices:\n{choices}")
    (job_dir / "status.json").write_text(json.dumps({"status": "done"}))
    runs = len(next(iter(metrics.values())))
    pd.DataFrame({"run": range(runs), **metrics, "failed": [False] * runs}).to_csv(
        job_dir / "metrics.csv", index=False)


def test_report_of_a_study_reads_the_arm_from_hydra_choices(tmp_path):
    """Arms are config-group choices (not config values): the report reads them from each job's
    .hydra/hydra.yaml, tabulates per arm and draws switching probability against λ_max."""
    for job, arm, switch in [("0", "baseline", [0.45, 1.0]), ("1", "nc30", [0.5, 0.48])]:
        _fake_job(tmp_path / job,
                  "task:\n  name: lissajous2\n  switch_prob: 0.5\nmodel:\n  gating:\n"
                  "    context_size: 15\n",
                  {"switch_prob": switch, "data_switch_prob": [0.47, 0.47],
                   "max_lyapunov": [0.002, -0.001], "E_g": [0.002, 0.003]},
                  choices=f"      p05_arm: {arm}\n      task: lissajous2\n")
    out = report(tmp_path)
    study = out["p05_study"].set_index("p05_arm")
    assert study.loc["baseline", "near_data_percent"] == 50
    assert study.loc["nc30", "near_data_percent"] == 100
    assert study.loc["baseline", "positive_percent"] == 50
    assert (tmp_path / "figures" / "switch_prob_vs_lyapunov.png").stat().st_size > 0
    assert pd.read_csv(tmp_path / "tables" / "p05_study.csv")["p05_arm"].tolist() == \
        ["baseline", "nc30"]


def test_report_adds_re_evaluations_as_their_own_setting(tmp_path):
    """`moex evaluate` inside a job (<job>/evaluate/<date>/) at another noise level is a job of
    its own: Fig. 16's cells at ρ² = 0 and 0.001 side by side, one heat map per (NC, ρ²)."""
    def metrics(nonperiodic):
        return {"nonperiodic_fraction": [nonperiodic, nonperiodic / 2],
                "max_lyapunov": [0.1, -0.1], "E_closed": [0.01, 0.02]}

    for job, (nt, lt) in enumerate([(2, 250), (2, 500), (5, 250), (5, 500)]):
        _fake_job(tmp_path / str(job),
                  f"task:\n  name: lissajous2\n  switch_prob: 0.5\n  num_series: {nt}\n"
                  f"  length: {lt}\nmodel:\n  gating:\n    context_size: 10\n"
                  "eval:\n  noise_var: 0.0\n  num_samples: 50\n", metrics(0.0))
        again = tmp_path / str(job) / "evaluate" / "2026-11-25_09-00-00"
        again.mkdir(parents=True)
        pd.DataFrame({"run": [0, 1], **metrics(1.0), "failed": [False, False]}).to_csv(
            again / "metrics.csv", index=False)
        (again / "eval_config.yaml").write_text("noise_var: 0.001\nnum_samples: 50\n")
    # a re-evaluation still computing (no metrics yet) is listed, not counted
    (tmp_path / "0" / "evaluate" / "2026-11-25_10-00-00").mkdir()
    (tmp_path / "0" / "evaluate" / "2026-11-25_10-00-00" / "eval_config.yaml").write_text(
        "noise_var: 0.01\n")
    out = report(tmp_path)
    jobs = out["jobs"].set_index("job")
    assert jobs.loc["0/evaluate/2026-11-25_09-00-00", "status"] == "done"
    assert jobs.loc["0/evaluate/2026-11-25_10-00-00", "status"] == "running or killed"
    summary = out["summary"].set_index(["eval.noise_var", "task.num_series", "task.length"])
    assert summary.loc[(0.0, 2, 250), "nonperiodic_fraction_mean"] == 0.0
    assert summary.loc[(0.001, 5, 500), "nonperiodic_fraction_mean"] == 0.75
    assert (summary["num_runs"] == 2).all() and len(summary) == 8
    # one figure per column, its panels (NC 10 at ρ² 0 and 0.001) side by side
    assert sorted(p.name for p in (tmp_path / "figures").glob("heatmap_*")) == [
        "heatmap_E_closed_mean.png", "heatmap_chaotic_percent.png",
        "heatmap_nonperiodic_fraction_mean.png", "heatmap_positive_percent.png"]


def test_no_heat_map_without_two_values_on_each_axis_and_none_of_a_column_without_values(
        tmp_path):
    """The issue's report of single runs: every NT × LT "map" would be one cell, so none is
    drawn; a column no job has (a Reber task's E^closed) gets no empty panel; file names stay
    short whatever the settings."""
    for job, (nt, lt, nc) in enumerate([(2, 250, 10), (2, 500, 20), (5, 250, 30)]):
        _fake_job(tmp_path / str(job), f"task:\n  name: reber\n  num_series: {nt}\n  length: "
                  f"{lt}\nmodel:\n  gating:\n    context_size: {nc}\n",
                  {"max_lyapunov": [0.1, -0.1], "nonperiodic_fraction": [0.5, 1.0]})
    report(tmp_path)
    assert not list((tmp_path / "figures").glob("heatmap_*"))
    for job, (nt, lt) in enumerate([(2, 250), (2, 500), (5, 250), (5, 500)]):
        _fake_job(tmp_path / f"grid{job}", f"task:\n  name: reber\n  num_series: {nt}\n  "
                  f"length: {lt}\nmodel:\n  gating:\n    context_size: 10\n",
                  {"max_lyapunov": [0.1, -0.1], "nonperiodic_fraction": [0.5, 1.0]})
    report(tmp_path)
    names = sorted(p.name for p in (tmp_path / "figures").iterdir())
    assert "heatmap_E_closed_mean.png" not in names and "heatmap_positive_percent.png" in names
    assert max(map(len, names)) <= 80


def test_the_same_network_counts_once_however_often_it_is_reported(tmp_path):
    """Run folders A and B of one setting but other seeds pool (4 networks); a copy of A, and A
    re-evaluated at the same evaluation settings, hold A's networks again: each counts once,
    with a note naming the job it repeats (the issue's "seed 0 trained three times, n = 6")."""
    import shutil

    config = ("seed: {}\nnum_runs: 2\ntask:\n  name: lissajous2\n  switch_prob: 0.5\nmodel:\n"
              "  gating:\n    context_size: 15\neval:\n  noise_var: 0.0\n  num_samples: 50\n")
    for job, seed, lam in (("A", 0, [0.1, 0.2]), ("B", 1, [0.3, 0.4])):
        _fake_job(tmp_path / job, config.format(seed), {"max_lyapunov": lam, "E_g": [0.01, 0.02]})
    again = tmp_path / "A" / "evaluate" / "2026-12-02_10-00-00"
    again.mkdir(parents=True)
    pd.DataFrame({"run": [0, 1], "max_lyapunov": [0.1, 0.2], "E_g": [0.01, 0.02],
                  "failed": [False, False]}).to_csv(again / "metrics.csv", index=False)
    (again / "eval_config.yaml").write_text("noise_var: 0.0\nnum_samples: 50\n")
    shutil.copytree(tmp_path / "A", tmp_path / "A copy")
    # one network of A trained again alone (num_runs 1): run 0 is the same network
    _fake_job(tmp_path / "A0", config.format(0).replace("num_runs: 2", "num_runs: 1"),
              {"max_lyapunov": [0.15], "E_g": [0.01]})
    folders = [tmp_path / name for name in ("A", "B", "A copy", "A0")]
    out = report(folders, tmp_path / "out")
    assert out["summary"]["num_runs"].sum() == 4
    assert out["summary"]["max_lyapunov_mean"].tolist() == [pytest.approx(0.25)]
    repeats = out["repeats"]
    assert len(repeats) == 2 + 2 + 2 + 1 and set(repeats["same_as"]) == {"A"}
    assert (tmp_path / "out" / "tables" / "repeats.csv").exists()
    result = subprocess.run([*MOEX, "report", *map(str, folders), "--out",
                             str(tmp_path / "out2")], capture_output=True, text=True)
    assert result.returncode == 0 and "7 run(s) are networks another job already holds" in \
        result.stdout


def test_report_of_table1_tabulates_per_context_size_and_plots_each_network(tmp_path):
    for job, nc in enumerate([10, 20]):
        _fake_job(tmp_path / str(job),
                  f"task:\n  name: reber\nmodel:\n  gating:\n    context_size: {nc}\n",
                  {"E_g": [0.1, 0.2], "block_kl_train": [1.0, 2.0], "block_kl_test": [1.5, 2.5],
                   "max_lyapunov": [0.2, -0.01]})
    table1 = report(tmp_path)["table1"].set_index("model.gating.context_size")
    assert table1.loc[10, "block_kl_test_mean"] == 2.0 and table1.loc[10, "positive_percent"] == 50
    assert table1.loc[10, "paper_block_kl_test"] == 2.388665
    assert table1.loc[30, "num_runs"] != table1.loc[30, "num_runs"]  # not run: missing
    assert (tmp_path / "figures" / "table1_kl_vs_lyapunov.png").stat().st_size > 0


def test_report_never_pools_a_setting_it_has_no_name_for(tmp_path):
    """A sweep over a key none of the paper's tables is keyed by (the phase-2 target temperature):
    one row per value, the key named in summary.csv, by_setting, jobs and Table 2."""
    for job, (p, temperature, switch) in enumerate([(0.5, 1, [0.1, 0.2]), (0.5, 0, [0.5, 0.6]),
                                                   (0.25, 1, [0.3, 0.3]), (0.25, 0, [0.2, 0.2])]):
        _fake_job(tmp_path / str(job),
                  f"task:\n  name: lissajous2\n  switch_prob: {p}\nmodel:\n  gating:\n"
                  f"    context_size: 15\ntrain:\n  gating:\n"
                  f"    target_temperature: {temperature}\n"
                  f"  checkpoint_every: {job}\n",  # bookkeeping: differs, groups nothing
                  {"switch_prob": switch, "max_lyapunov": [0.1, 0.2]})
    out = report(tmp_path)
    key = "train.gating.target_temperature"
    summary = out["summary"].set_index(["task.switch_prob", key])
    assert len(summary) == 4 and (summary["num_runs"] == 2).all()
    assert summary.loc[(0.5, 1), "switch_prob_mean"] == pytest.approx(0.15)
    assert summary.loc[(0.5, 0), "switch_prob_mean"] == pytest.approx(0.55)
    assert "train.checkpoint_every" not in out["summary"]
    assert key in pd.read_csv(tmp_path / "summary.csv")
    assert key in (tmp_path / "tables" / "jobs.md").read_text()
    table2 = out["table2"]
    assert key in table2 and len(table2.dropna(subset=["num_runs"])) == 4


def test_report_groups_jobs_that_lack_a_key_apart_from_those_that_set_it(tmp_path):
    reber = "task:\n  name: reber\nmodel:\n  gating:\n    context_size: 20\n"
    _fake_job(tmp_path / "0", reber, {"max_lyapunov": [0.1, 0.2]})
    _fake_job(tmp_path / "1", reber + "precision: float32\n", {"max_lyapunov": [0.3, 0.4]})
    # seeds are replicates, not settings: another seed pools with the job that lacks the key
    _fake_job(tmp_path / "2", reber + "seed: 3\n", {"max_lyapunov": [0.5, 0.6]})
    summary = report(tmp_path)["summary"]
    assert len(summary) == 2 and summary["precision"].isna().sum() == 1
    assert sorted(summary["num_runs"]) == [2, 4] and "seed" not in summary


def test_a_sweep_over_a_config_group_names_the_choice_apart_from_the_setting(tmp_path):
    """`-m task=reber,lissajous2` varies both task.name and the `task` choice: two columns,
    each named as the config names it."""
    for job, task in enumerate(["reber", "lissajous2"]):
        _fake_job(tmp_path / str(job), f"task:\n  name: {task}\nmodel:\n  gating:\n"
                  f"    context_size: 20\n", {"max_lyapunov": [0.1, 0.2]},
                  choices=f"      task: {task}\n")
    summary = report(tmp_path)["summary"]
    assert summary["task.name"].tolist() == summary["task"].tolist() and len(summary) == 2


def test_report_compares_runs_from_different_folders(tmp_path):
    """Two single runs trained apart (another gating size each) compared in one report: one
    row per setting, named by its config key; several folders without --out go to a dated
    folder; svg on request."""
    for size in (5, 6):
        done = subprocess.run(MOEX + ["train", "task=lissajous2", *TINY,
                                      f"model.gating.context_size={size}",
                                      f"hydra.run.dir={tmp_path / f'nc{size}'}"],
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr
    dated = subprocess.run(MOEX + ["report", str(tmp_path / "nc5"), str(tmp_path / "nc6")],
                           capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert dated.returncode == 0, dated.stderr
    written = list((tmp_path / "outputs" / "report").iterdir())
    assert len(written) == 1 and f"report written to outputs/report/{written[0].name}" in \
        dated.stdout
    out = subprocess.run(MOEX + ["report", str(tmp_path / "nc5"), str(tmp_path / "nc6"),
                                 "--out", str(tmp_path / "both"), "--format", "svg"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    summary = pd.read_csv(tmp_path / "both" / "tables" / "by_setting.csv")
    assert summary["model.gating.context_size"].tolist() == [5, 6]
    # provenance: both folders say what produced them, the same machine and versions
    record = json.loads((tmp_path / "nc5" / "provenance.json").read_text())[-1]
    assert record["verb"] == "train" and record["backend"] == "cpu"
    assert record["versions"]["torch"] == torch.__version__ and record["cpu"]
    assert set(record["seconds"]) == {"phase 1", "phase 2", "evaluation"}
    assert "Provenance" in (tmp_path / "nc5" / "report.md").read_text()
    assert "warning" not in out.stdout
    assert set(pd.read_csv(tmp_path / "both" / "tables" / "jobs.csv")["provenance"]) == {"A"}
    # a folder from other package versions: a warning and another letter
    records = json.loads((tmp_path / "nc6" / "provenance.json").read_text())
    records[-1]["versions"]["numba"] = "0.0.1"
    (tmp_path / "nc6" / "provenance.json").write_text(json.dumps(records))
    again = subprocess.run(MOEX + ["report", str(tmp_path / "nc5"), str(tmp_path / "nc6"),
                                   "--out", str(tmp_path / "both"), "--format", "svg"],
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and "2 different machines or package versions" in again.stdout
    assert pd.read_csv(tmp_path / "both" / "tables" / "jobs.csv")["provenance"].tolist() == [
        "A", "B"]
    assert set(pd.read_csv(tmp_path / "both" / "summary.csv")["job"]) == {"nc5", "nc6"}
    assert not list((tmp_path / "both" / "figures").glob("*.png"))  # svg only, if any figure


def test_the_scatter_says_when_its_switching_was_measured_under_noise(tmp_path, monkeypatch):
    """Every job evaluated with one noise level ρ² > 0: the switching-against-λ_max figure's
    title says so; without noise it does not."""
    from moex import plotting

    titles = {}
    monkeypatch.setattr(plotting, "save_figure",
                        lambda fig, path, fmt="png": titles.update({path.stem: fig.axes[0]
                                                                    .get_title()}))
    for noise in (0.001, 0.0):
        folder = tmp_path / str(noise)
        for job, p in (("0", 0.5), ("1", 0.25)):
            _fake_job(folder / job, f"task:\n  name: lissajous2\n  switch_prob: {p}\n",
                      {"switch_prob": [0.4, 0.3], "data_switch_prob": [0.47, 0.47],
                       "max_lyapunov": [0.002, -0.001], "noise_var": [noise, noise]})
        report(folder)
        said = "noise ρ² = 0.001" in titles["switch_prob_vs_lyapunov"]
        assert said == (noise > 0), noise


def test_one_network_reads_without_nan_and_labels_count_beside_the_papers_criterion():
    """A setting with one network shows its values without "± nan"; the chaos labels with their
    error are counted beside the paper's λ_max > 0; a run page's cell says "1 sample" where a
    network has no error to give."""
    from moex.run_page import lyapunov_cells

    runs = pd.DataFrame({"task": "lissajous2", "run": [0, 0, 1, 2], "job": [0, 1, 1, 1],
                         "max_lyapunov": [7e-6, 0.01, -0.02, 1e-3],
                         "max_lyapunov_se": [6.5e-6, 1e-4, 1e-3, float("nan")],
                         "lyapunov_steps": 100000, "E_g": [0.08, 0.1, 0.1, 0.1]})
    table = aggregate(runs, ["job"]).set_index("job")
    assert table.loc[0, "undetermined_count"] == 1 and table.loc[0, "chaotic_count"] == 0
    assert table.loc[0, "positive_percent"] == 100  # the paper's criterion calls it chaotic
    assert table.loc[1, ["chaotic_count", "undetermined_count", "not_chaotic_count"]].tolist() \
        == [1, 1, 1]
    text = short_summary(table.reset_index(), ["job"])
    assert "nan" not in text and "chaotic 0, undetermined 1, not 0" in text
    cells = lyapunov_cells(runs.assign(lyapunov_samples=[50, 50, 50, 1]))
    assert cells == ["7e-06 ± 6.5e-06 (undetermined)", "0.01 ± 0.0001 (chaotic)",
                     "-0.02 ± 0.001 (not chaotic)", "0.001 (1 sample; undetermined)"]


def test_switching_against_lambda_draws_each_settings_own_data_line(tmp_path):
    """A sweep over P: the switching-vs-λ_max figure draws the data's switching per P (never
    one line averaged over the three P values)."""
    import matplotlib

    matplotlib.use("Agg")
    from unittest import mock

    from moex import plotting

    for job, (p, data) in enumerate([(0.5, 0.47), (0.25, 0.26), (0.125, 0.13)]):
        _fake_job(tmp_path / str(job), f"task:\n  name: lissajous2\n  switch_prob: {p}\n",
                  {"max_lyapunov": [0.001, 0.002], "switch_prob": [data, data],
                   "data_switch_prob": [data, data]})
    with mock.patch.object(plotting, "plot_scatter_by", wraps=plotting.plot_scatter_by) as drawn:
        report(tmp_path)
    runs, _, _, group = drawn.call_args.args[:4]
    levels = drawn.call_args.kwargs["reference"].groupby(runs[group]).mean()
    assert sorted(levels.round(2)) == [0.13, 0.26, 0.47]
    assert set(runs[group]) == {"task.switch_prob 0.5", "task.switch_prob 0.25",
                                "task.switch_prob 0.125"}


def test_a_report_of_unlike_runs_draws_without_a_warning(tmp_path):
    """Runs of different tasks, sizes and data: every figure drawn without a matplotlib warning
    (long setting names are wrapped in the key, not allowed to squeeze the axes to nothing)."""
    import warnings

    for job, (task, nt, lt, p) in enumerate([("reber", 3, 200, 0.5), ("lissajous9", 2, 200, 0.5),
                                             ("lissajous2", 10, 1000, 0.5),
                                             ("lissajous2", 2, 40, 0.25)]):
        _fake_job(tmp_path / str(job), f"task:\n  name: {task}\n  num_series: {nt}\n  length: {lt}"
                  f"\n  switch_prob: {p}\nmodel:\n  gating:\n    context_size: {5 + job}\n",
                  {"max_lyapunov": [0.001, -0.1], "switch_prob": [1.0, 0.0],
                   "data_switch_prob": [0.5, 0.5]})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        report(tmp_path)
    assert [str(w.message) for w in caught if issubclass(w.category, UserWarning)] == []
    assert (tmp_path / "figures" / "switch_prob_vs_lyapunov.png").stat().st_size > 0


def test_imported_runs_are_done_and_their_source_folders_are_no_setting(tmp_path):
    """`moex import` folders (no status.json, a metrics.csv) count as done; the C tools' source
    folders tell networks apart like a seed but are no setting: two imports of one setting pool."""
    for job in ("a", "b"):
        _fake_job(tmp_path / job, f"source:\n- /c/{job}/net001\ntask:\n  name: lissajous2\n",
                  {"max_lyapunov": [0.001, 0.002]})
        (tmp_path / job / "status.json").unlink()
    out = report([tmp_path / "a", tmp_path / "b"], tmp_path / "out")
    assert set(out["jobs"]["status"]) == {"done"}
    assert len(out["summary"]) == 1 and out["summary"]["num_runs"].iloc[0] == 4
    assert "source" not in out["summary"] and out["repeats"].empty


def test_jobs_written_before_and_after_tasks_had_their_own_configs_pool(tmp_path):
    """A job folder of an older moex holds every task's keys in .hydra/config.yaml, one of this
    version the keys its task YAML set: the same settings are one setting, not two."""
    old = ("task:\n  name: lissajous2\n  num_series: 10\n  length: 1000\n  num_test_series: 10\n"
           "  period: 25.0\n  switch_prob: 0.5\n  transition_rule: paper\n  choice_prob: 0.5\n"
           "  burn_in: 100\n  primitives: []\n  transition: []\n  path: ''\n  labels: ''\n"
           "  columns: []\n  scale: none\n  data_seed: -1\nseed: 0\n")
    new = ("task:\n  name: lissajous2\n  num_series: 10\n  length: 1000\n  switch_prob: 0.5\n"
           "seed: 1\n")
    for job, config in (("old", old), ("new", new)):
        _fake_job(tmp_path / job, config, {"max_lyapunov": [0.01, -0.01], "E_g": [0.1, 0.2]})
    runs, jobs, varying = gather(tmp_path)
    assert varying == [] and len(jobs) == 2 and len(runs) == 4
    assert set(runs["task.switch_prob"]) == {0.5}
