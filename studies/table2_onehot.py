"""Table 2 with one-hot phase-2 targets against the paper and the soft targets, 30 networks per P.

    python -m studies.table2_onehot        # prints the Markdown table and the paired comparison

Reads docs/table2_onehot30_summary.csv (one-hot targets: `experiment=paper_table2_chaotic`, one
job of 30 networks per P) and docs/table2_summary.csv (the paper's soft targets ĝ, Table 2 at full
scale). Both used seed 0: network r of one is network r of the other (the same initial weights and
data), trained on another CPU, so the comparison is paired by network, round-off apart. "stay":
switching probability below 0.02; "alternate": above 0.8; "chaotic": λ_max > 0.
"""


import numpy as np
import pandas as pd

from moex.report import wilson_interval
from moex.tasks.paper import PAPER_TABLE2
from studies.common import DOCS

STAY, ALTERNATE, NEAR = 0.02, 0.8, 0.05


def sign_flip_p(difference: np.ndarray, draws: int = 100_000) -> float:
    """Two-sided p of a paired difference's mean being 0: the share of random sign flips of the
    pairs whose mean is at least as far from 0 (the pairs' labels exchangeable under the null)."""
    signs = np.random.default_rng(0).choice([-1.0, 1.0], size=(draws, len(difference)))
    flipped = np.abs((signs * difference).mean(axis=1))
    return float((1 + (flipped >= abs(difference.mean()) - 1e-15).sum()) / (draws + 1))


def design_row(runs: pd.DataFrame, paper: float) -> dict:
    """One design's row: its runs' switching probability and chaotic share against the paper's."""
    switching, n = runs["switch_prob"], len(runs)
    chaotic = int((runs["max_lyapunov"] > 0).sum())
    low, high = wilson_interval(chaotic, n)
    return {
        "switching mean ± sd (n)": f"{switching.mean():.3f} ± {switching.std():.3f} ({n})",
        "distance from the paper":
            f"{(switching.mean() - paper) / (switching.std() / np.sqrt(n)):+.1f} SE",
        "within ±0.05 of the paper / the data": f"{int(((switching - paper).abs() <= NEAR).sum())}"
            f" / {int(((switching - runs['data_switch_prob']).abs() <= NEAR).sum())} of {n}",
        "stay / alternate":
            f"{int((switching < STAY).sum())} / {int((switching > ALTERNATE).sum())}",
        "λ_max mean": f"{runs['max_lyapunov'].mean():.4f}",
        "λ_max > 0 [95 % CI]": f"{chaotic} / {n} [{low:.0f}, {high:.0f}] %",
        "nonperiodic": f"{runs['nonperiodic_fraction'].mean():.0%}",
    }


def at_p(runs: pd.DataFrame, p: float) -> pd.DataFrame:
    """The networks of one P of Table 2 that did not fail."""
    return runs[(runs["task.switch_prob"] == p) & ~runs["failed"].astype(bool)]


def table() -> tuple[pd.DataFrame, pd.DataFrame]:
    onehot = pd.read_csv(DOCS / "table2_onehot30_summary.csv")
    soft = pd.read_csv(DOCS / "table2_summary.csv")
    rows, pairs = [], []
    for _, paper in PAPER_TABLE2.iterrows():
        p = paper["task.switch_prob"]
        mine, theirs = at_p(onehot, p), at_p(soft, p)
        if mine.empty:
            continue
        for name, runs in (("soft", theirs), ("one-hot", mine)):
            rows.append({"P": p, "targets": name, "paper": f"{paper['paper_switch_prob']:.3f}",
                         "data": f"{runs['data_switch_prob'].mean():.3f}",
                         **design_row(runs, paper["paper_switch_prob"])})
        both = mine.merge(theirs, on="run", suffixes=("_onehot", "_soft"))
        difference = both["switch_prob_onehot"] - both["switch_prob_soft"]
        pairs.append({"P": p, "pairs": len(both),
                      "one-hot − soft, mean ± sd":
                          f"{difference.mean():+.3f} ± {difference.std():.3f}",
                      "median": f"{difference.median():+.3f}",
                      "sign-flip p": f"{sign_flip_p(difference.to_numpy()):.2g}",
                      "sd of switching, soft → one-hot": f"{both['switch_prob_soft'].std():.3f} → "
                                                         f"{both['switch_prob_onehot'].std():.3f}"})
    return pd.DataFrame(rows), pd.DataFrame(pairs)


def markdown(frame: pd.DataFrame) -> str:
    lines = ["| " + " | ".join(map(str, frame.columns)) + " |", "|" + "---|" * len(frame.columns)]
    lines += ["| " + " | ".join(map(str, row)) + " |" for row in frame.itertuples(False)]
    return "\n".join(lines)


if __name__ == "__main__":
    rows, pairs = table()
    print(markdown(rows), "", markdown(pairs), sep="\n")
