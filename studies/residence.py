"""Fig. 9 in numbers: the residence times of Table 2's networks against the data's geometric law.

    python -m studies.residence collect SWEEP...   # writes docs/table2_own_data_residence.csv
    python -m studies.residence                    # prints the table REPRODUCTION.md quotes

`collect` reads every job's samples.npz (`residence_hist` and `residence_censored_hist`: per
network, the stays of k = 1 … 99 repetitions of one curve, and of 100 or more in the last bin,
completed and cut off by a sample's end) and the job's `task.switch_prob`. Data that switch with
probability P after each lap stay k laps with probability P (1 − P)^(k − 1), so a stay reaches k
laps with probability (1 − P)^(k − 1) and lasts 1/P laps on average. As in the paper's Fig. 9 the
distribution compared is the average of the networks' own distributions (each network weighs the
same however many stays it made); a stay cut off by a sample's end counts at its length, a lower
bound (about two per sample, 0.1-0.3 % of a switching network's stays).
"""

import sys
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from moex.report import to_markdown
from studies.common import DOCS

CSV = DOCS / "table2_own_data_residence.csv"
REACH = (5, 10, 20, 40)  # the stay lengths k of the table's "reaches k laps" columns
LONG = 100  # the histogram's last bin: stays of 100 laps or more


def collect(sweeps: list[Path]) -> pd.DataFrame:
    """One row per network, P and stay length: completed and cut-off stays."""
    rows = []
    for job in sorted(p.parent for s in sweeps for p in s.glob("*/samples.npz")):
        p = OmegaConf.load(job / ".hydra" / "config.yaml").task.switch_prob
        with np.load(job / "samples.npz") as data:
            done, cut = data["residence_hist"], data["residence_censored_hist"]
        for run in range(len(done)):
            rows += [{"P": p, "job": f"{job.parent.name}/{job.name}", "run": run, "laps": k,
                      "completed": int(done[run, k]), "cut": int(cut[run, k])}
                     for k in range(1, done.shape[1]) if done[run, k] or cut[run, k]]
    return pd.DataFrame(rows)


def averaged(stays: pd.DataFrame) -> pd.Series:
    """The networks' own distributions over stay lengths 1 … LONG, averaged (Fig. 9)."""
    counts = stays.assign(n=stays.completed + stays.cut).pivot_table(
        index=["job", "run"], columns="laps", values="n", aggfunc="sum", fill_value=0)
    counts = counts.reindex(columns=range(1, LONG + 1), fill_value=0)
    return counts.div(counts.sum(axis=1), axis=0).mean()


def law(p: float) -> pd.Series:
    """The geometric law of the data over 1 … LONG laps, the last bin holding ≥ LONG."""
    k = np.arange(1, LONG + 1)
    probability = p * (1 - p) ** (k - 1)
    probability[-1] = (1 - p) ** (LONG - 1)
    return pd.Series(probability, index=k)


def table(stays: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for p, at in stays.groupby("P", sort=False):
        ours, theirs = averaged(at), law(p)
        reach, reach_law = ours[::-1].cumsum()[::-1], theirs[::-1].cumsum()[::-1]
        networks = at.groupby(["job", "run"])
        rows.append({
            "P": p, "networks": networks.ngroups,
            "mean laps, completed stays pooled (law 1/P)":
                f"{(at.laps * at.completed).sum() / at.completed.sum():.2f} ({1 / p:g})",
            **{f"reaches {k} laps: ours / law": f"{reach[k]:.2g} / {reach_law[k]:.2g}"
               for k in REACH},
            "networks with a stay ≥ 100 laps":
                int(networks.apply(lambda n: (n.laps == LONG).any()).sum()),
            "total variation from the law": round(0.5 * (ours - theirs).abs().sum(), 3),
        })
    return pd.DataFrame(rows).sort_values("P", ascending=False, ignore_index=True)


if __name__ == "__main__":
    if sys.argv[1:2] == ["collect"]:
        collect([Path(s) for s in sys.argv[2:]]).to_csv(CSV, index=False)
    print(to_markdown(table(pd.read_csv(CSV))))
