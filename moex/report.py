"""Sweeps into tables (paper Tables 1-2, Figs. 9, 14, 16): gather every job of a multirun folder,
aggregate over runs, and write CSV, Markdown and figures at the multirun root."""

import dataclasses
import json
from io import StringIO
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from moex import io, plotting, provenance
from moex.config import CONF_DIR
from moex.errors import ConfigError, check
from moex.metrics.lyapunov import CHAOS_LABELS, chaos_labels
from moex.metrics.table import REPORTED
from moex.progress import packed
from moex.tasks import TASKS, own_keys
from moex.tasks.paper import PAPER_TABLES

# settings the paper's tables and figures are keyed by: a column under its config key even where
# every job agrees; every other setting that varies between jobs becomes a column too
SETTINGS = ("task.name", "task.switch_prob", "task.num_series", "task.length",
            "model.gating.context_size", "eval.noise_var", "eval.jacobian_gates",
            "eval.num_samples", "eval.lyapunov_steps")
# replicates, not settings: jobs that differ only in these pool into one row (they still tell
# networks apart, `_network_key`)
REPLICATES = ("seed", "task.data_seed", "source")  # source: the C tools' folders an import read
# config groups whose chosen option is a study's arm (conf/<study>_arm/, the arms an experiment
# sweeps): a setting (column: the group), its arms kept in the sweep's order, and a table
# tables/<study>_study of their outcomes
ARMS = tuple(sorted(p.name for p in Path(CONF_DIR).iterdir()
                    if p.is_dir() and p.name.endswith("_arm")))
# keys that are no setting of a network: where a job writes, how often it logs, what it plots,
# and how many networks it trains (run r is seeded by (seed, r) alone: run 0 of one run and of
# five is one network)
BOOKKEEPING = ("out_dir", "resume", "cache_dir", "run_dir", "num_runs", "eval.enabled",
               "eval.plot_steps",
               "train.checkpoint_every", "train.experts.log_every", "train.gating.log_every",
               "plot.")
# heat-map panels (Figs. 14, 16): setting -> the panel's title
PANELS = {"model.gating.context_size": "NC = {:g}", "eval.noise_var": "ρ² = {:g}"}
# the settings that change a task's data (and so its switching probability)
DATA_KEYS = ("task.name", "task.switch_prob", "task.num_series", "task.length",
             "task.transition_rule", "task.choice_prob", "task.period")
NEAR = 0.05  # a network "switches at the data's rate" within ±NEAR (the P = 0.5 study's goal)


def _flatten(tree: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _task_keys(config: dict) -> dict:
    """A job's config with its task's keys as its task's own config has them, defaults filled:
    a job written before tasks had their own configs holds every task's keys, one written since
    those its YAML and overrides set; both name the same settings alike (a task this version does
    not know, or a value its task refuses, leaves the config as it was written)."""
    task = config.get("task")
    if not isinstance(task, dict) or task.get("name") not in TASKS:
        return config
    try:
        typed = TASKS[task["name"]].config(**own_keys(task, task["name"]))
    except (ConfigError, TypeError, ValueError):
        return config
    return {**config, "task": dataclasses.asdict(typed)}


def gather(folders) -> tuple[pd.DataFrame, pd.DataFrame, list[str]]:
    """Every job folder below each of `folders` (a sweep, a run, or any parent of them: a job is
    a folder with .hydra/config.yaml), and every re-evaluation `moex evaluate` wrote inside one
    (<job>/evaluate/<date>/, e.g. at another noise level): a re-evaluation is a job of its own
    whose eval.* settings come from its eval_config.yaml. Jobs are named by their path below
    their folder, prefixed by the folder's name when there are several folders.

    Returns:
        runs: one row per (job, run) with the job's settings and its metrics.csv columns;
        jobs: one row per job with its status (done, failed, interrupted, missing metrics);
        varying: the columns of the settings that differ between jobs.
    """
    found = []  # (name, folder, settings, status) per job

    def add(name: str, folder: Path, config: dict, choices: dict, status: dict) -> None:
        settings = {k: _hashable(v) for k, v in config.items()
                    if not k.startswith(BOOKKEEPING)}
        settings.update({f"choice:{group}": option for group, option in choices.items()
                         if not group.startswith("hydra/")})
        found.append((name, folder, settings, status))

    roots = [Path(f) for f in ([folders] if isinstance(folders, str | Path) else folders)]
    found_configs = [(folder, path) for folder in roots for path in sorted(
        folder.glob("**/.hydra/config.yaml"), key=lambda p: (len(str(p)), str(p)))]
    for root, config_path in found_configs:
        job_dir = config_path.parent.parent  # (sorted: job 2 before job 10)
        inside = job_dir.relative_to(root).as_posix()
        name = root.name if inside == "." else inside
        if len(roots) > 1 and inside != ".":
            name = f"{root.name}/{inside}"
        config = _flatten(_task_keys(_read(config_path, yaml.safe_load, dict)))
        hydra_path = config_path.with_name("hydra.yaml")
        choices = (_read(hydra_path, lambda text: yaml.safe_load(text)["hydra"]["runtime"]
                         ["choices"], dict) if hydra_path.exists() else {})
        status_path = job_dir / "status.json"
        add(name, job_dir, config, choices,
            _read(status_path, json.loads, dict) if status_path.exists() else {})
        for eval_config in sorted(job_dir.glob("evaluate/*/eval_config.yaml")):
            folder = eval_config.parent
            evaluated = _flatten({"eval": _read(eval_config, yaml.safe_load, dict)})
            add(f"{name}/evaluate/{folder.name}", folder, {**config, **evaluated},
                choices, {"status": "done"} if (folder / io.METRICS_CSV).exists() else {})
    varying = [k for k in varying_settings([settings for _, _, settings, _ in found])
               if k not in REPLICATES]
    runs, jobs, named = [], [], _columns(varying)
    for name, folder, settings, status in found:
        columns = {column: settings.get(key) for key, column in named.items()}
        metrics_path = folder / io.METRICS_CSV
        # a job without status.json (an import, an older run) is done once its metrics exist
        state = status.get("status", "done" if metrics_path.exists() else "running or killed")
        if state == "done" and not metrics_path.exists():
            state = "missing metrics"
        jobs.append({"job": name, **columns, "status": state,
                     "error": status.get("error", ""),
                     "provenance": provenance.exactness_key(provenance.read(folder)),
                     "path": str(folder)})
        if metrics_path.exists():
            metrics = _read(metrics_path, lambda text: pd.read_csv(StringIO(text)), pd.DataFrame)
            check("run" in metrics, f"{metrics_path} has no run column, so it is not a moex "
                                    f"metrics.csv; fix or remove it")
            runs.append(metrics.assign(job=name, network_of=_network_key(settings), **columns))
    return (pd.concat(runs, ignore_index=True) if runs else pd.DataFrame(), pd.DataFrame(jobs),
            [named[k] for k in varying])


def _network_key(settings: dict) -> str:
    """What names a job's networks apart from their run index: its settings (the seed among
    them; `BOOKKEEPING` keys, the number of runs included, are not settings)."""
    return repr(sorted(settings.items()))


def once_each(runs: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The runs with each network once, and the repeats left out: a network trained again with
    the same settings and seed, a copied folder, or a re-evaluation at the same settings is the
    same network (column `network_of` and `run` equal); the first job in order keeps it. Pooled
    twice it would count as two networks."""
    if "network_of" not in runs:
        return runs, runs.iloc[:0]
    repeat = runs.duplicated(["network_of", "run"])
    first = runs[~repeat].set_index(["network_of", "run"])["job"]
    left = runs.loc[repeat, ["job", "run"]].assign(same_as=[
        first[(key, r)] for key, r in zip(runs.loc[repeat, "network_of"], runs.loc[repeat, "run"],
                                          strict=True)])
    return runs[~repeat].drop(columns="network_of"), left.reset_index(drop=True)


def _read(path: Path, parse, kind: type):
    """`parse` of the text of `path`, which must give a `kind`; a damaged file is a
    `ConfigError` naming it."""
    try:
        value = parse(path.read_text())
    except Exception as exc:  # yaml, json, pandas and decoding errors alike
        raise ConfigError(f"{path} cannot be read ({type(exc).__name__}: "
                          f"{str(exc).splitlines()[0] if str(exc) else ''}); fix or remove "
                          f"it") from None
    check(isinstance(value, kind), f"{path} does not hold a {kind.__name__}; fix or remove it")
    return value


def _hashable(value):
    """A config value as something a table can group by (lists and dicts as their YAML)."""
    if isinstance(value, list | dict):
        return yaml.safe_dump(value, default_flow_style=True).strip()
    return value


def varying_settings(jobs: list[dict]) -> list[str]:
    """The keys whose value differs between jobs (a key some jobs lack counts as differing),
    in first-seen order."""
    keys = list(dict.fromkeys(k for settings in jobs for k in settings))
    return [k for k in keys if len({repr(settings.get(k)) for settings in jobs}) > 1]


def _columns(varying: list[str]) -> dict[str, str]:
    """Column name of each setting: its config key, for SETTINGS and ARMS (always present) and
    every other key that varies (a choice under its group's name; one named like a setting's
    column gets the suffix `_choice`)."""
    columns = {key: key for key in SETTINGS}
    columns.update({f"choice:{group}": group for group in ARMS})
    for key in varying:
        if key not in columns:
            name = key.removeprefix("choice:")
            columns[key] = name if name not in columns.values() else f"{name}_choice"
    return columns


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion, in percent."""
    if n == 0:
        return float("nan"), float("nan")
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, 100 * float(centre - half)), min(100.0, 100 * float(centre + half))


def aggregate(runs: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """Mean and standard deviation over runs of every metric, and the share of runs with a
    positive maximum Lyapunov exponent (with its 95 % Wilson interval), per setting; with the
    data's switching probability, also the share of runs within ±NEAR of it. Failed runs count
    as missing."""
    ok = runs[~runs.get("failed", pd.Series(False, index=runs.index)).astype(bool)]
    grouped = ok.groupby(keys, dropna=False)
    table = grouped[[m for m in REPORTED if m in ok]].agg(["mean", "std"])
    table.columns = [f"{m}_{s}" for m, s in table.columns]
    positives, count = grouped["max_lyapunov"].apply(lambda x: int((x > 0).sum())), grouped.size()
    _share(table, "positive", positives, count)
    labels = chaos_labels(ok)  # the label with its error, beside the paper's criterion
    for name in CHAOS_LABELS:
        hits = (labels == name).groupby([ok[k] for k in keys], dropna=False).sum()
        table[f"{name.replace(' ', '_')}_count"] = hits.reindex(table.index, fill_value=0)
    _share(table, "chaotic", table["chaotic_count"], count)
    if {"switch_prob", "data_switch_prob"} <= set(ok):
        near = (ok["switch_prob"] - ok["data_switch_prob"]).abs() <= NEAR
        table["near_data_percent"] = near.groupby([ok[k] for k in keys], dropna=False).mean() * 100
    table["num_runs"] = count
    table["failed_runs"] = runs.groupby(keys, dropna=False).size() - table["num_runs"]
    return table.reset_index()


def _share(table: pd.DataFrame, name: str, hits, count) -> None:
    """The columns `<name>_percent`, `<name>_ci_low` and `<name>_ci_high`: hits / count per
    setting, with its 95 % Wilson interval."""
    table[f"{name}_percent"] = 100 * hits / count
    ci = [wilson_interval(k, n) for k, n in zip(hits, count, strict=True)]
    table[f"{name}_ci_low"] = [low for low, _ in ci]
    table[f"{name}_ci_high"] = [high for _, high in ci]


def to_markdown(frame: pd.DataFrame) -> str:
    """A plain Markdown table (no extra dependency)."""
    def cell(v):
        if isinstance(v, float):
            return "missing" if np.isnan(v) else f"{v:.6g}"
        return str(v)

    lines = ["| " + " | ".join(frame.columns) + " |", "|" + "---|" * len(frame.columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in frame.itertuples(False)]
    return "\n".join(lines) + "\n"


def _write_table(out: Path, name: str, frame: pd.DataFrame) -> None:
    io.write_csv(out / "tables" / f"{name}.csv", frame)
    io.atomic_write(out / "tables" / f"{name}.md",
                    lambda tmp: Path(tmp).write_text(to_markdown(frame)))


def paper_tables(summary: pd.DataFrame, keys: list[str]) -> dict[str, pd.DataFrame]:
    """The paper's tables (`moex.tasks.paper.PAPER_TABLES`: Table 1 by context size, Table 2 by
    P) beside the sweep's numbers, for the tasks the sweep has; rows the sweep lacks are shown as
    missing. Every other setting in `keys` (those that vary between jobs) is a column of its
    own."""
    tables = {}
    for paper in PAPER_TABLES:
        ours = summary[summary["task.name"] == paper.task]
        if not len(ours) or (paper.needs_several and ours[paper.key].nunique() < 2):
            continue
        cols = [c for c in (paper.key, *_others(keys, paper.key, "task.name"), *paper.columns)
                if c in ours]
        tables[paper.name] = (paper.numbers.merge(ours[cols], on=paper.key, how="outer")
                              .sort_values(paper.key, ascending=not paper.descending,
                                           ignore_index=True))
    for arm in (a for a in ARMS if a in summary):
        cols = [arm, *_others(keys, arm), "switch_prob_mean", "switch_prob_std",
                "data_switch_prob_mean",
                "near_data_percent", "max_lyapunov_mean", "positive_percent", "positive_ci_low",
                "positive_ci_high", "chaotic_percent", "undetermined_count",
                "nonperiodic_fraction_mean", "E_mean", "E_g_mean",
                "E_closed_mean", "num_runs", "failed_runs"]
        tables[f"{arm.removesuffix('_arm')}_study"] = summary[[c for c in cols if c in summary]]
    return tables


def _others(keys: list[str], *shown: str) -> list[str]:
    return [k for k in keys if k not in shown]


def report(folders, out_dir: Path | None = None, fmt: str = "png") -> dict[str, pd.DataFrame]:
    """Write summary.csv, tables/*.csv|md and figures/* (as `fmt`) for the jobs of `folders`
    (one folder or several) into `out_dir` (default: the one folder); safe to re-run."""
    folders = [Path(folders)] if isinstance(folders, str | Path) else [Path(f) for f in folders]
    sweep_dir = Path(out_dir) if out_dir is not None else folders[0]
    runs, jobs, keys = gather(folders)
    if len(jobs):  # each distinct machine/versions record as a letter: jobs with another letter
        # were produced elsewhere and need not agree bit for bit (provenance.json says how)
        labels = {k: chr(ord("A") + i) for i, k in enumerate(pd.unique(
            jobs["provenance"][jobs["provenance"] != ""]))}
        jobs["provenance"] = jobs["provenance"].map(lambda k: labels.get(k, "not recorded"))
    out = {"jobs": jobs}
    if len(jobs):
        _write_table(sweep_dir, "jobs", jobs.drop(columns=["path"]))
    if runs.empty:
        return out
    runs, repeats = once_each(runs)
    out["repeats"] = repeats
    if len(repeats):
        _write_table(sweep_dir, "repeats", repeats)
    io.write_csv(sweep_dir / "summary.csv", runs)
    summary = aggregate(runs, keys or ["task.name"])
    for arm in (a for a in ARMS if a in summary):  # arms in the sweep's order, not alphabetical
        first = {name: i for i, name in enumerate(pd.unique(runs[arm]))}
        summary = summary.sort_values(arm, key=lambda a, first=first: a.map(first),
                                      ignore_index=True)
    for k in ("task.name", "task.switch_prob", "model.gating.context_size"):  # paper tables
        if k not in summary:
            summary[k] = runs[k].iloc[0]
    _write_table(sweep_dir, "by_setting", summary)
    out["summary"], out["keys"] = summary, keys
    for name, table in paper_tables(summary, keys).items():
        _write_table(sweep_dir, name, table)
        out[name] = table
    _figures(sweep_dir, runs, summary, jobs=jobs, keys=keys, fmt=fmt)
    return out


SHOWN = (("E_g", "E^g"), ("block_kl_test", "KL test"), ("switch_prob", "switching"),
         ("max_lyapunov", "λ_max"))  # the terminal summary's metrics, where a report has them


def short_summary(summary: pd.DataFrame, keys: list[str], width: int = 100) -> str:
    """A few lines for the terminal (≤ `width` columns): per setting, n, the key metrics as
    mean ± sd (the value alone for one network), the chaos labels' counts and the share with
    λ_max > 0 (the paper's criterion); the whole tables are in tables/. A "name value" pair is
    never split across lines."""
    lines = []
    for row in summary.to_dict("records"):  # (itertuples would rename the dotted keys)
        setting = ", ".join(f"{k} {row[k]}" for k in keys if k in row) or "all runs"
        parts = [f"n {row['num_runs']}"] + [
            f"{text} {row[f'{m}_mean']:.3g}" + (f" ± {row[f'{m}_std']:.2g}"
                                                if row["num_runs"] > 1 else "")
            for m, text in SHOWN if f"{m}_mean" in row and pd.notna(row[f"{m}_mean"])]
        if "chaotic_count" in row:
            parts += [f"chaotic {row['chaotic_count']}, undetermined {row['undetermined_count']}, "
                      f"not {row['not_chaotic_count']}",
                      f"λ_max > 0 in {row['positive_percent']:.0f} %"]
        lines += packed(f"{setting}:", parts, sep="; ", width=width)
    return "\n".join(lines)


def heat_limits(values: pd.Series, column: str) -> tuple[float, float]:
    """One colour range for every panel of a column: shares on their full scale."""
    if column.endswith("_percent"):
        return 0.0, 100.0
    if column.startswith("nonperiodic_fraction"):
        return 0.0, 1.0
    finite = values[np.isfinite(values.astype(float))]
    return (float(finite.min()), float(finite.max())) if len(finite) else (0.0, 1.0)


def _panel_title(keys: list[str], values) -> str:
    """A heat-map panel's title: each setting that tells it apart, in lines of ≤ 30 characters."""
    import textwrap

    values = values if isinstance(values, tuple) else (values,)
    text = ", ".join(PANELS[k].format(v) if k in PANELS else f"{k} = {v}"
                     for k, v in zip(keys, values, strict=True))
    return "\n".join(textwrap.wrap(text, 30))


def _figures(sweep_dir: Path, runs, summary, *, jobs, keys, fmt: str = "png") -> None:
    figures = sweep_dir / "figures"
    if {"task.num_series", "task.length"} <= set(summary):
        # one panel per value of every other setting that varies (NC, and the noise level when
        # re-evaluations add one: Fig. 16), all panels of a column in one figure; a panel only
        # where NT and LT each take two values or more and the column has a value
        others = [k for k in PANELS if k in summary] + [
            k for k in keys if k not in ("task.num_series", "task.length", *PANELS)]
        for column in ("E_closed_mean", "chaotic_percent", "positive_percent",
                       "nonperiodic_fraction_mean"):
            if column not in summary:
                continue
            panels = [(_panel_title(others, values), group)
                      for values, group in (summary.groupby(others) if others
                                            else [((), summary)])
                      if group["task.num_series"].nunique() > 1
                      and group["task.length"].nunique() > 1 and group[column].notna().any()]
            if panels:
                fig = plotting.plot_heatmaps(panels, "task.num_series", "task.length", column,
                                             heat_limits(summary[column], column))
                plotting.save_figure(fig, figures / f"heatmap_{column}.png", fmt)
    present = [a for a in ARMS if a in runs]
    if present and {"switch_prob", "max_lyapunov"} <= set(runs):
        # coloured by the study arm, else by the first setting that varies (e.g. P), never one
        # colour over settings whose data differ
        arm = next((a for a in present if runs[a].notna().any()), present[0])
        data_keys = [k for k in keys if k in DATA_KEYS]  # what sets the data's switching
        group = arm if runs[arm].notna().any() or not data_keys else "setting"
        if group == "setting":  # one group (and data line) per data setting, named by its keys
            runs = runs.assign(setting=[", ".join(f"{k} {v}" for k, v in zip(
                data_keys, row, strict=True)) for row in runs[data_keys].itertuples(index=False)])
        fig = plotting.plot_scatter_by(runs, "max_lyapunov", "switch_prob", group,
                                       reference=runs.get("data_switch_prob"), band=NEAR)
        noise = runs.get("noise_var", pd.Series(dtype=float)).dropna().unique()
        if len(noise) == 1 and noise[0] > 0:  # one noise for all: the noisy loop's switching
            ax = fig.axes[0]
            ax.set_title(f"{ax.get_title()}\nswitching measured with noise ρ² = {noise[0]:g} "
                         f"on x_n")
        plotting.save_figure(fig, figures / "switch_prob_vs_lyapunov.png", fmt)
    for paper in PAPER_TABLES:  # a symbolic task's table per network: chaos and the test KL
        ours = runs[runs["task.name"] == paper.task]
        nc = "model.gating.context_size"
        if paper.key == nc and ours[nc].nunique() > 1 \
                and {"max_lyapunov", "block_kl_test"} <= set(ours):
            fig = plotting.plot_scatter_by(ours, "max_lyapunov", "block_kl_test", nc, log_y=True)
            plotting.save_figure(fig, figures / f"{paper.name}_kl_vs_lyapunov.png", fmt)
    switch_prob = jobs.get("task.switch_prob", pd.Series(np.nan, index=jobs.index))  # lissajous2
    liss = jobs[(jobs["status"] == "done") & switch_prob.notna()
                & ~jobs["job"].str.contains("/evaluate/")]  # Fig. 9: the trained evaluation
    hists = {}
    for _, job in liss.iterrows():
        path = Path(job["path"]) / io.SAMPLES
        if path.exists():
            with np.load(path) as data:
                if "residence_hist" in data:  # cut-off stays: not in older folders
                    cut = data.get("residence_censored_hist", 0 * data["residence_hist"])
                    hists.setdefault(job["task.switch_prob"], []).append(
                        (data["residence_hist"], cut))
    if len(hists) > 1 and liss["task.name"].nunique() == 1:  # one task's curves, by P
        fig = plotting.plot_residence_panels(
            {p: tuple(np.concatenate(part) for part in zip(*h, strict=True))
             for p, h in hists.items()})
        plotting.save_figure(fig, figures / "residence_times.png", fmt)
