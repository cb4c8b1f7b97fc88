"""Open question 3, model side: is the Reber test-KL gap (ours about half the paper's) the model?
Table 1's 50 networks at one NC trained again with one change each against the same seeds'
baseline: the C code's initialisation (`model.init=mregn`), learned time constants
(`model.learn_time_constants=true`), the u_0 attraction term (`train.gating.attraction=true`).

    python -m studies.table1_arms NC baseline=RUN_DIR init_mregn=RUN_DIR ...  # run folders
    python -m studies.table1_arms NC --add init_tau=RUN_DIR ...  # more arms beside the CSV's
    python -m studies.table1_arms NC                             # the table from the CSV alone

Writes docs/table1_nc<NC>_arms.csv (one row per arm and network) and prints, per arm, each
metric's mean ± sd and its paired change against the baseline (mean ± standard error over the
networks: the same initial seeds in every arm).
"""

import sys
from pathlib import Path

import numpy as np
import pandas as pd

from moex.report import to_markdown
from studies.common import DOCS

METRICS = ["E_g", "block_kl_train", "block_kl_test", "max_lyapunov"]


def arms(folders: dict[str, str]) -> pd.DataFrame:
    parts = []
    for arm, folder in folders.items():
        runs = pd.read_csv(Path(folder) / "metrics.csv")[["run", *METRICS]]
        runs.insert(0, "arm", arm)
        parts.append(runs)
    return pd.concat(parts, ignore_index=True)


def summary(table: pd.DataFrame) -> pd.DataFrame:
    base = table[table.arm == "baseline"].set_index("run")
    rows = []
    for arm, group in table.groupby("arm", sort=False):
        group = group.set_index("run")
        row = {"arm": arm, "n": len(group),
               "λ_max > 0": f"{int((group.max_lyapunov > 0).sum())} / {len(group)}"}
        for metric in METRICS:
            row[metric] = f"{group[metric].mean():.4g} ± {group[metric].std():.2g}"
            if arm != "baseline":
                diff = (group[metric] - base[metric]).dropna()
                row[f"Δ {metric}"] = (f"{diff.mean():+.3g} ± "
                                      f"{diff.std() / np.sqrt(len(diff)):.2g}")
        rows.append(row)
    return pd.DataFrame(rows).fillna("")


if __name__ == "__main__":
    nc, args = sys.argv[1], sys.argv[2:]
    csv = DOCS / f"table1_nc{nc}_arms.csv"
    add = args[:1] == ["--add"]
    folders = dict(arg.split("=", 1) for arg in args[add:])
    if folders:
        table = arms(folders)
        if add:
            kept = pd.read_csv(csv)
            table = pd.concat([kept[~kept.arm.isin(folders)], table], ignore_index=True)
        table.to_csv(csv, index=False)
    else:
        table = pd.read_csv(csv)
    print(to_markdown(summary(table)))
