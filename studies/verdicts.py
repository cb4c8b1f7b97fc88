"""The verdict table at the top of REPRODUCTION.md, recomputed from the per-network CSVs in docs/.

    python -m studies.verdicts              # the Markdown table of REPRODUCTION.md
    python -m studies.verdicts --evidence   # with the evidence column (docs/verdicts.md)

Each row: the paper's number; ours as mean ± sd (n) over the table's own batch (one data set,
independent networks), with its median and the number of networks beyond 3 robust SDs; where
the same design ran on more data sets, the mean over independent units (`pooled`: an initial
network reused on several data sets is one unit; evidence beside the verdict); the difference
moex − paper with its 95 % interval; the authors' code trained on the same data and scored by
moex (studies/mregn_control.py), where run; and the verdict of ONE RULE (`decide`):
  - the interval of moex − paper (z 1.96) counts the paper's own sampling error: its n networks
    (50 in Table 1, 30 in Table 2) assumed to spread as a typical moex network (robust SD, 1.4826
    × the median absolute deviation, so that moex's outliers do not widen the tolerance); a share
    uses the binomial error of both shares (Newcombe's interval from two Wilson intervals);
  - *reproduced*: the interval contains 0 and lies inside ± the margin: half the robust SD of
    one network for a mean (a difference smaller than half a typical network's spread), 10
    percentage points for a share;
  - *differs*: the interval excludes 0 (with the cause where a controlled comparison found it,
    CAUSES: "cause found", a "candidate cause", or "cause open");
  - *inconclusive*: neither; the row says how many moex networks would decide it (or that none
    would: the paper's own error is wider than the margin);
  - a flag where dropping the one or two networks furthest from the median changes the word.
tests/test_docs.py checks that REPRODUCTION.md and docs/verdicts.md quote this table.
"""

import sys

import numpy as np
import pandas as pd

from moex.report import to_markdown, wilson_interval
from moex.tasks.paper import PAPER_TABLE1, PAPER_TABLE2
from studies.common import DOCS


def _distance(values: pd.Series, paper: float, digits: str = ".3f") -> str:
    values = values.dropna()
    return (f"{values.mean():{digits}} ± {values.std():{digits}} ({len(values)}), "
            f"{(values.mean() - paper) / (values.std() / np.sqrt(len(values))):+.1f} SE")


def _paper(table: str, setting: float, metric: str) -> float:
    """The paper's number: Table 1 by NC, Table 2 by P."""
    frame, key = ((PAPER_TABLE1, "model.gating.context_size") if table == "Table 1"
                  else (PAPER_TABLE2, "task.switch_prob"))
    return float(frame.set_index(key).loc[setting, f"paper_{metric}"])


def _onehot(p: float) -> str:
    onehot = pd.read_csv(DOCS / "table2_onehot30_summary.csv")
    return ("one-hot targets on the same seeds (another CPU): "
            + _distance(onehot.switch_prob[onehot["task.switch_prob"] == p],
                        _paper("Table 2", p, "switch_prob")))


def _paired_targets(p: float) -> str:
    """The paired one-hot − soft difference of switching at P (studies/table2_onehot.py)."""
    from studies.table2_onehot import at_p, sign_flip_p

    onehot, soft = (at_p(pd.read_csv(DOCS / f), p) for f in ("table2_onehot30_summary.csv",
                                                             "table2_summary.csv"))
    both = onehot.merge(soft, on="run", suffixes=("_onehot", "_soft"))
    diff = (both.switch_prob_onehot - both.switch_prob_soft).to_numpy()
    se = diff.std(ddof=1) / np.sqrt(len(diff))
    return (f"paired one-hot − soft {diff.mean():+.3f} ± {se:.3f} (SE, n {len(diff)}), "
            f"sign-flip p {sign_flip_p(diff):.2g}")


def _targets_evidence(p: float):
    return lambda: _paired_targets(p) + "; " + _onehot(p)


def _protocol_evidence() -> str:
    runs = pd.read_csv(DOCS / "table1_nc20_protocol.csv")
    return ("with the C code's symbol rule and KL formula (50 networks retrained): "
            + _distance(runs.block_kl_train_threshold_10000_mregnkl,
                        _paper("Table 1", 20, "block_kl_train")))


def _protocol_evidence_nc10() -> str:
    arms = pd.read_csv(DOCS / "table1_nc10_arms.csv")
    runs = arms[arms.arm == "baseline_c_protocol"]
    return ("with the C code's symbol rule and KL formula (50 networks retrained): "
            + _distance(runs.block_kl_train, _paper("Table 1", 10, "block_kl_train")))


def _reber_test_open() -> str:
    seeds = pd.read_csv(DOCS / "data_seeds_reber_summary.csv").block_kl_test
    arms = pd.read_csv(DOCS / "table1_nc20_arms.csv")
    both = arms[arms.arm == "init_tau"].block_kl_test.mean() - \
        arms[arms.arm == "baseline"].block_kl_test.mean()
    every = arms[arms.arm == "init_tau_attraction"]
    paper = _paper("Table 1", 20, "block_kl_test")
    return ("not the protocol; not the data or held-out draw (10 data sets × "
            f"5 networks: median {seeds.median():.3f}, mean " + _distance(seeds, paper) +
            " through 2 networks with a periodic closed loop); not the C code's "
            f"initialisation, learned τ or attraction alone, nor the first two together "
            f"({both:+.3f}); all three give a median of {every.block_kl_test.median():.3f}, near "
            f"the paper's mean,"
            f" only by fitting worse (E^g median {every.E_g.median():.3f}) (question 3); the "
            f"authors' code on the same data without its u₀ attraction, "
            f"{_control_fit('reber_nc20_no_attraction')}")


def _control_fit(design: str) -> str:
    """The control's networks of `design` that fit (E^g < 0.02): their test KL."""
    control = pd.read_csv(DOCS / "mregn_control_networks.csv")
    trained = control[control.design == design]
    fit = trained[trained.E_g < 0.02].block_kl_test
    return (f"its {len(fit)} of {len(trained)} networks that fit (E^g < 0.02): "
            f"{fit.mean():.3f} ± {fit.std():.3f}, median {fit.median():.3f}")


def _saturated_nc10() -> str:
    e_g = _table1_runs(10).E_g
    return (f"{(e_g > 1).sum()} saturated network (E^g {e_g.max():.2f}) carries the mean; the "
            f"median is {e_g.median():.3f}")


def _table1_runs(nc: int) -> pd.DataFrame:
    reber = pd.read_csv(DOCS / "table1_summary.csv")
    return reber[(reber["model.gating.context_size"] == nc) & ~reber["failed"]]


def _reber_test_open_nc30() -> str:
    runs = pd.read_csv(DOCS / "table1_c_protocol.csv")
    protocol = runs[runs.context_size == 30].pivot(index="run", columns="protocol",
                                                   values="block_kl_test")
    held = pd.read_csv(DOCS / "table1_nc30_held_out.csv").pivot(
        index="run", columns="test_series", values="block_kl_test")
    changes = ", ".join(f"{n} series {(held[n] - held[4]).mean():+.3f}" for n in (1, 40))
    return (f"the C code's protocol {(protocol['c_protocol'] - protocol['moex']).mean():+.3f} "
            f"({len(protocol)} networks retrained); held-out data of other sizes than 4 series, "
            f"paired on the same networks: {changes}; the authors' code on the same data, "
            f"{_control_fit('reber_nc30')}")


# (table, setting, metric) -> (the kind of "differs" where the rule says differs, a cause in one
# phrase, the evidence); rows not named that differ: cause open
CAUSES = {
    ("Table 1", 10, "E_g"): ("differs, cause open", "one saturated network moves the mean",
                             _saturated_nc10),
    ("Table 1", 10, "block_kl_train"): ("differs, cause found", "the paper's protocol (the C "
                                        "code's symbol rule and KL formula)",
                                        _protocol_evidence_nc10),
    ("Table 1", 20, "block_kl_train"): ("differs, cause found", "the paper's protocol (the C "
                                        "code's symbol rule and KL formula)", _protocol_evidence),
    ("Table 1", 20, "block_kl_test"): ("differs, cause open", "not the protocol, data, held-out "
                                       "draw, the C code's choices alone or moex's training",
                                       _reber_test_open),
    ("Table 1", 30, "block_kl_test"): ("differs, cause open", "not the protocol, the amount "
                                       "of held-out data or moex's training",
                                       _reber_test_open_nc30),
    ("Table 2", "P = 0.5", "switch_prob"): ("differs, candidate cause",
                                            "the soft phase-2 targets (not significant)",
                                            _targets_evidence(0.5)),
    ("Table 2", "P = 0.25", "switch_prob"): ("differs, candidate cause",
                                             "the soft phase-2 targets (not significant)",
                                             _targets_evidence(0.25)),
}
METRICS = {"E_g": "E^g", "block_kl_train": "KL train", "block_kl_test": "KL test",
           "max_lyapunov": "λ_max", "switch_prob": "switching prob."}


PAPER_N = {"Table 1": 50, "Table 2": 30}  # networks behind each of the paper's means


CONTROL = {  # the control closest to the paper's settings per row, and what it is
    "reber_nc20_no_attraction": ("Table 1", 20, "no u₀ attraction"),
    "reber_nc30": ("Table 1", 30, "default build"),
    "table2_p05_paper": ("Table 2", "P = 0.5", "paper's settings"),
    "table2_p025_paper": ("Table 2", "P = 0.25", "paper's settings"),
}


def _control(table, setting, metric) -> str:
    """The authors' code trained on moex's data and scored by moex (docs/mregn_control.md): the
    design of CONTROL for the row, named."""
    summary = pd.read_csv(DOCS / "mregn_control_summary.csv")
    for row in summary.itertuples():
        if CONTROL.get(row.design, ())[:2] == (table, setting) and row.metric == metric:
            tag = CONTROL[row.design][2]
            if metric == "positive_percent":
                return f"{row.control:.0f} % ({row.control_n}; {tag})"
            return f"{row.control:.4g} ± {row.control_sd:.2g} ({row.control_n}; {tag})"
    return "—"


def units(table, setting, metric) -> pd.DataFrame:
    """Every network of the row's design, on every data set it ran on, with its unit: the
    initial network it grew from. The table's batch (seed 0, runs 0..n-1, data set 0), the
    data-seed experiments (runs 0-4 of seed 0 again, on other data sets: the same units) and, in
    Table 2, the runs with a data set per network (seeds 100 on: units of their own). Retrains of
    the same seeds on the same data are left out (the same networks again, round-off apart)."""
    def frame(runs, unit):
        return pd.DataFrame({"unit": unit, "value": runs[metric].to_numpy()})

    if table == "Table 1":
        batch = _table1_runs(setting)
        frames = [frame(batch, batch["run"].map("seed 0 run {}".format))]
        if setting == 20:
            seeds = pd.read_csv(DOCS / "data_seeds_reber_summary.csv")
            seeds = seeds[(seeds["task.data_seed"] != 0) & ~seeds.failed.astype(bool)]
            frames.append(frame(seeds, seeds["run"].map("seed 0 run {}".format)))
        return pd.concat(frames, ignore_index=True).dropna()
    p = float(setting.removeprefix("P = "))
    two = pd.read_csv(DOCS / "table2_summary.csv")
    two = two[(two["task.switch_prob"] == p) & ~two.failed.astype(bool)]
    seeds = pd.read_csv(DOCS / DATA_SEEDS[p])
    seeds = seeds[(seeds["task.data_seed"] != 0) & ~seeds.failed.astype(bool)]
    own = pd.read_csv(DOCS / "table2_own_data_summary.csv")
    own = own[(own["task.switch_prob"] == p) & ~own.failed.astype(bool)]
    return pd.concat([frame(two, two["run"].map("seed 0 run {}".format)),
                      frame(seeds, seeds["run"].map("seed 0 run {}".format)),
                      frame(own, [f"seed {s} run {r}" for s, r in zip(own["seed"], own["run"],
                                                                      strict=True)])],
                     ignore_index=True).dropna()


DATA_SEEDS = {0.5: "data_seeds_p05_summary.csv", 0.25: "data_seeds_summary.csv",
              0.125: "data_seeds_p0125_summary.csv"}


def pooled(frame: pd.DataFrame) -> tuple[float, float, int, int]:
    """The mean over independent units (the model: each initial network is one draw; its value
    is the mean of its networks over the data sets it ran on; units are independent and weigh
    the same), its standard error sd(unit means) / √units, the number of units and of
    observations. An initial network reused on six data sets counts once, not six times."""
    means = frame.groupby("unit")["value"].mean()
    return (float(means.mean()), float(means.std(ddof=1) / np.sqrt(len(means))), len(means),
            len(frame))


Z = 1.96  # two-sided 95 %
MARGIN_SD = 0.5  # a mean's margin: half the robust SD of one network
MARGIN_SHARE = 10.0  # a share's margin, percentage points


def robust_sd(values: np.ndarray) -> float:
    """1.4826 × the median absolute deviation (the SD for normal data, blind to a few outliers);
    the plain SD where more than half the values are equal."""
    mad = 1.4826 * np.median(np.abs(values - np.median(values)))
    return float(mad) if mad > 0 else float(np.std(values, ddof=1))


def decide(low: float, high: float, margin: float) -> str:
    """The rule's word for a 95 % interval [low, high] of moex − paper."""
    if low > 0 or high < 0:
        return "differs"
    return "reproduced" if -margin < low and high < margin else "inconclusive"


def needed(diff: float, sd: float, spread: float, paper_n: int, margin: float) -> str:
    """How many moex networks would decide an inconclusive row, its difference, sd and robust
    spread as measured: the fewest n whose interval (moex's sd/√n with the paper's error) is
    narrower than the margin left beside the difference (reproduced), or than the difference
    (differs)."""
    best = []
    for room in (margin - abs(diff), abs(diff)):
        left = (room / Z) ** 2 - spread**2 / paper_n
        if room > 0 and left > 0:
            best.append(int(np.ceil(sd**2 / left)))
    return (f"about {min(best)} networks would decide it" if best else
            "no number of moex networks decides it (the paper's own error is wider)")


def _mean_interval(values: np.ndarray, paper: float, paper_n: int) -> tuple:
    """(difference, low, high, margin, robust SD) of a mean row."""
    spread = robust_sd(values)
    diff = values.mean() - paper
    half = Z * np.sqrt(values.var(ddof=1) / len(values) + spread**2 / paper_n)
    return diff, diff - half, diff + half, MARGIN_SD * spread, spread


def _carried(values: np.ndarray, word: str, judge) -> str:
    """A flag where the word rests on one or two networks: dropping those furthest from the
    median changes it."""
    order = np.argsort(-np.abs(values - np.median(values)))
    for k in (1, 2):
        if judge(np.delete(values, order[:k])) != word:
            return f" ({k} network{'s carry' if k > 1 else ' carries'} it)"
    return ""


def _row(table, setting, metric, paper, values) -> dict:
    values = values.dropna().to_numpy(float)
    n, mean, sd = len(values), values.mean(), values.std(ddof=1)
    center, se, networks, observations = pooled(units(table, setting, metric))
    paper_n = PAPER_N[table]

    def judge(x):
        return decide(*_mean_interval(x, paper, paper_n)[1:4])

    diff, low, high, margin, spread = _mean_interval(values, paper, paper_n)
    word = decide(low, high, margin)
    kind = "differs, cause open" if word == "differs" else word
    cause, evidence = "", ""
    if (table, setting, metric) in CAUSES:  # its evidence always; its cause where it differs
        found, phrase, explain = CAUSES[(table, setting, metric)]
        evidence = explain()
        if word == "differs":
            kind, cause = found, phrase
    if word == "inconclusive":
        evidence = "; ".join(e for e in (needed(diff, sd, spread, paper_n, margin), evidence)
                             if e)
    median = np.median(values)
    beyond = int((np.abs(values - median) > 3 * spread).sum())
    own = _own_data(table, setting, metric)
    return {"result": f"{table}, {setting}", "quantity": METRICS[metric],
            "paper": f"{paper:.4g}",
            "moex mean ± sd (n); median; beyond 3 SD": f"{mean:.4g} ± {sd:.2g} ({n}); "
                                                        f"{median:.4g}; {beyond}",
            "pooled over initial networks ± SE (networks, observations)": (
                f"{center:.4g} ± {se:.2g} ({networks}, {observations})"
                if observations > n else "—"),
            "moex − paper [95 %] (margin)": f"{diff:+.3g} [{low:+.3g}, {high:+.3g}] "
                                            f"(± {margin:.2g})",
            "authors' code (n)": _control(table, setting, metric),
            "verdict": kind + (f": {cause}" if cause else "")
                       + _carried(values, word, judge),
            "evidence": "; ".join(e for e in (evidence, own) if e) or "—"}


def _own_data(table, setting, metric) -> str:
    """Table 2's switching and λ_max rows: the same statistic with a data set per network."""
    if table != "Table 2" or metric not in ("switch_prob", "max_lyapunov"):
        return ""
    own = pd.read_csv(DOCS / "table2_own_data_summary.csv")
    p = float(setting.removeprefix("P = "))
    runs = own[metric][(own["task.switch_prob"] == p) & ~own.failed.astype(bool)]
    paper = _paper("Table 2", p, metric)
    digits = ".3f" if metric == "switch_prob" else ".3g"
    return (f"with a data set per network: {_distance(runs, paper, digits)}" if len(runs)
            else "")


SENSITIVITY = 1e-4  # the second chaos criterion, stated beside the paper's λ_max > 0


def share_interval(k: int, n: int, paper_percent: float, paper_n: int) -> tuple:
    """(difference, low, high) in percentage points of moex's share k/n − the paper's share of
    its paper_n networks: Newcombe's hybrid score interval from the two Wilson intervals."""
    p1, p0 = k / n, paper_percent / 100
    l1, u1 = (v / 100 for v in wilson_interval(k, n))
    l0, u0 = (v / 100 for v in wilson_interval(round(p0 * paper_n), paper_n))
    diff = p1 - p0
    return (100 * diff, 100 * (diff - np.hypot(p1 - l1, u0 - p0)),
            100 * (diff + np.hypot(u1 - p1, p0 - l0)))


def _share(table, setting, paper_percent, lyapunov) -> dict:
    lyapunov = lyapunov.dropna().to_numpy(float)
    n, positive = len(lyapunov), int((lyapunov > 0).sum())
    strict = int((lyapunov > SENSITIVITY).sum())
    paper_n = PAPER_N[table]

    def judge(x):
        return decide(*share_interval(int((x > 0).sum()), len(x), paper_percent,
                                      paper_n)[1:], MARGIN_SHARE)

    diff, low, high = share_interval(positive, n, paper_percent, paper_n)
    word = decide(low, high, MARGIN_SHARE)
    evidence = "—"
    if word == "inconclusive":
        p = positive / n if 0 < positive < n else paper_percent / 100
        sd = 100 * np.sqrt(p * (1 - p))
        evidence = needed(diff, sd, sd, paper_n, MARGIN_SHARE)
    return {"result": f"{table}, {setting}", "quantity": "% λ_max > 0",
            "paper": f"{paper_percent:g} %",
            "moex mean ± sd (n); median; beyond 3 SD": f"{100 * positive / n:.0f} % "
            f"({positive} / {n}); > 10⁻⁴: {100 * strict / n:.0f} %",
            "pooled over initial networks ± SE (networks, observations)": "—",
            "moex − paper [95 %] (margin)": f"{diff:+.0f} [{low:+.0f}, {high:+.0f}] points "
                                            f"(± {MARGIN_SHARE:g})",
            "authors' code (n)": _control(table, setting, "positive_percent"),
            "verdict": ("differs, cause open" if word == "differs" else word)
                       + _carried(lyapunov, word, judge), "evidence": evidence}


def verdicts() -> pd.DataFrame:
    rows = []
    for _, paper in PAPER_TABLE1.iterrows():
        nc = int(paper["model.gating.context_size"])
        runs = _table1_runs(nc)
        for metric in ("E_g", "block_kl_train", "block_kl_test", "max_lyapunov"):
            rows.append(_row("Table 1", nc, metric, paper[f"paper_{metric}"], runs[metric]))
        rows.append(_share("Table 1", nc, paper["paper_positive_percent"],
                           runs["max_lyapunov"]))
    two = pd.read_csv(DOCS / "table2_summary.csv")
    for _, paper in PAPER_TABLE2.iterrows():
        p = paper["task.switch_prob"]
        runs = two[(two["task.switch_prob"] == p) & ~two["failed"]]
        for metric in ("switch_prob", "max_lyapunov"):
            rows.append(_row("Table 2", f"P = {p:g}", metric, paper[f"paper_{metric}"],
                             runs[metric]))
        rows.append(_share("Table 2", f"P = {p:g}", paper["paper_positive_percent"],
                           runs["max_lyapunov"]))
    for row in rows:
        row["result"] = row["result"].replace("Table 1, ", "Table 1, NC = ")
    return pd.DataFrame(rows)


KINDS = ["reproduced", "differs, cause found", "differs, candidate cause",
         "differs, cause open", "inconclusive"]


def tally(frame: pd.DataFrame) -> str:
    """One line for the top of REPRODUCTION.md: how many rows the rule gives each word."""
    kinds = frame.verdict.map(lambda v: next(k for k in KINDS if v.startswith(k)))
    n = kinds.value_counts().reindex(KINDS, fill_value=0)
    carried = int(frame.verdict.str.contains(r"carr(?:y|ies) it").sum())
    return (f"Of the table's {len(frame)} rows, by one rule (studies/verdicts.py): {n.iloc[0]} "
            f"reproduced; {n.iloc[1:4].sum()} differ, {n.iloc[1]} with the cause found, "
            f"{n.iloc[2]} with a candidate cause and {n.iloc[3]} with the cause open; "
            f"{n.iloc[4]} inconclusive; {carried} of them rest on one or two networks.")


def tool_question() -> str:
    """Question 4's answer (what the authors' λ_max tool measures), every number from
    docs/lyapunov_crosscheck.csv, so that the sentence cannot go stale."""
    c = pd.read_csv(DOCS / "lyapunov_crosscheck.csv")
    r = np.corrcoef(c.mregn_lyapunov, c.moex)[0, 1]
    r_05 = np.corrcoef(*c[c.design == "table2_p05"][["mregn_lyapunov", "moex"]].T.values)[0, 1]
    uniform = np.corrcoef(c.mregn_lyapunov, c.moex_uniform_gates)[0, 1]
    signs = int((np.sign(c.mregn_lyapunov) == np.sign(c.moex_uniform_gates)).sum())
    gap = (c.two_trajectories - c.moex).abs()
    far = gap[gap > 1e-3].sort_values(ascending=False)
    return (f"On the {len(c)} Table 2 control networks their tool reads "
            f"{c.mregn_lyapunov.min():+.3f} … {c.mregn_lyapunov.max():+.3f} where moex reads "
            f"{c.moex.min():+.3f} … {c.moex.max():+.3f} (r {r:.2f}; {r_05:.2f} at P = 0.5); "
            f"moex with `eval.jacobian_gates=uniform` reproduces it network by network (r "
            f"{uniform:.3f}, {signs} of {len(c)} signs, median difference "
            f"{np.median(np.abs(c.mregn_lyapunov - c.moex_uniform_gates)):.1e}), and a "
            f"Jacobian-free two-trajectory estimate agrees with moex's exact estimate in "
            f"{int((gap <= 1e-3).sum())} of {len(c)} (median difference {gap.median():.1e}); the "
            f"{len(far)} exceptions ({', '.join(f'{v:.2g}' for v in far)}) are networks with two "
            f"attractors, on which both methods agree trajectory by trajectory.")


SHORT = {"result": "result", "quantity": "quantity", "paper": "paper",
         "moex mean ± sd (n); median; beyond 3 SD": "moex: mean ± sd (n); median; beyond 3 SD",
         "moex − paper [95 %] (margin)": "moex − paper [95 %] (margin) → verdict"}


def markdown(frame: pd.DataFrame, evidence: bool = False) -> str:
    """The table: REPRODUCTION.md quotes it in five columns (the interval and the verdict in
    one), docs/verdicts.md whole, with the evidence column."""
    if not evidence:
        frame = frame.assign(**{"moex − paper [95 %] (margin)": frame["moex − paper [95 %] "
                                                                        "(margin)"]
                                + " → " + frame["verdict"]})[list(SHORT)].rename(columns=SHORT)
    return to_markdown(frame).rstrip("\n")


if __name__ == "__main__":
    frame = verdicts()
    print(tally(frame))
    print(markdown(frame, evidence="--evidence" in sys.argv))
    if "--evidence" in sys.argv:
        print(f"\nQuestion 4: {tool_question()}")
