"""How much does round-off alone move a trained network's outcome? (open question 1.) Three pairs
of runs in docs/ trained the *same* initial networks on the *same* data with the *same* settings;
only the floating-point rounding differs (another CPU, or another number of networks trained side
by side, which changes how the kernels pack and sum lanes). Every difference between a network
and its twin is round-off amplified by 40 000 training steps and by the closed loop.

    python -m studies.roundoff      # writes docs/roundoff_pairs.csv, prints the summary table

The pairs (A against B; what differs):
    soft, P = 0.5: Table 2's networks 0-9 (R = 30, AMD EPYC) against the P = 0.5 study's
        `baseline` arm (R = 10, AMD EPYC); R.
    soft, P = 0.25: Table 2's networks 0-4 (R = 30, AMD EPYC) against the data-seed
        experiment's data set 0 (R = 5, Intel Xeon); R and CPU.
    one-hot, P = 0.5: Table 2 one-hot's networks 0-9 (R = 30, Intel Xeon) against the study's
        `targets_onehot` arm (R = 10, AMD EPYC); R and CPU.
"""


import numpy as np
import pandas as pd

from moex.report import to_markdown
from studies.common import DOCS

COLUMNS = ["run", "E", "switch_prob", "max_lyapunov", "nonperiodic_fraction"]
MOVED = 0.05  # a switching probability that moved more than this counts as a changed outcome


def _table2(p: float, n: int) -> pd.DataFrame:
    runs = pd.read_csv(DOCS / "table2_summary.csv")
    return runs[runs["task.switch_prob"] == p].sort_values("run").head(n)[COLUMNS]


def _arm(name: str) -> pd.DataFrame:
    runs = pd.read_csv(DOCS / "p05_study_summary.csv")
    return runs[runs["p05_arm"] == name].sort_values("run")[COLUMNS]


def pairs() -> pd.DataFrame:
    seeds = pd.read_csv(DOCS / "data_seeds_summary.csv")
    onehot = pd.read_csv(DOCS / "table2_onehot30_summary.csv")
    sets = {
        "soft, P = 0.5 (R)": (_table2(0.5, 10), _arm("baseline")),
        "soft, P = 0.25 (R, CPU)": (_table2(0.25, 5),
                                    seeds[seeds["task.data_seed"] == 0][COLUMNS]),
        "one-hot, P = 0.5 (R, CPU)": (onehot[onehot["task.switch_prob"] == 0.5]
                                      .sort_values("run").head(10)[COLUMNS],
                                      _arm("targets_onehot")),
    }
    out = []
    for name, (a, b) in sets.items():
        both = a.merge(b, on="run", suffixes=("_a", "_b"))
        assert len(both) == len(a) == len(b), name
        both.insert(0, "pair", name)
        out.append(both)
    return pd.concat(out, ignore_index=True)


def summary(table: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for name, group in table.groupby("pair", sort=False):
        moved = (group.switch_prob_a - group.switch_prob_b).abs()
        e_gap = (group.E_a / group.E_b - 1).abs()
        sign = np.sign(group.max_lyapunov_a) != np.sign(group.max_lyapunov_b)
        rows.append({"pair": name, "networks": len(group),
                     "E equal (rel. 1e-9)": int((e_gap < 1e-9).sum()),
                     "median |Δ switching|": moved.median(),
                     f"|Δ switching| > {MOVED}": int((moved > MOVED).sum()),
                     "largest |Δ switching|": moved.max(),
                     "λ_max sign differs": int(sign.sum()),
                     "sd of switching across networks (A)": group.switch_prob_a.std()})
    return pd.DataFrame(rows)


if __name__ == "__main__":
    table = pairs()
    table.to_csv(DOCS / "roundoff_pairs.csv", index=False)
    print(to_markdown(summary(table)))
