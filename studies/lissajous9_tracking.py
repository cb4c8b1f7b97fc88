"""Figs. 10-13's tracking (paper Fig. 11), with λ_max's standard error: the history of phase 2
of a `paper_lissajous9` run kept as docs/lissajous9_history.csv, the tracked table of
docs/reproduction/lissajous9.md, and each network's changes of λ_max between tracking points
judged against their errors.

    python -m studies.lissajous9_tracking RUN_DIR     # writes docs/lissajous9_history.csv and
                                                   # lissajous9_rerun_summary.csv, prints
    python -m studies.lissajous9_tracking             # prints from docs/lissajous9_history.csv

A change between consecutive tracking points is *beyond its error* when |Δλ| > 2 √(se₁² + se₂²);
a sign change is *resolved* when both values lie beyond 2 se of zero, on opposite sides.
"""

import sys
from pathlib import Path

import numpy as np
import pandas as pd

from moex.report import to_markdown
from studies.common import DOCS

HISTORY = DOCS / "lissajous9_history.csv"
COLUMNS = ["run", "step", "E_g", "block_kl_train", "max_lyapunov", "max_lyapunov_se"]
SHOWN = (0, 500, 1000, 2000, 3000, 4000, 5000, 6000, 8000, 9999)  # the table's steps
SETTLED = 1000  # E^g has settled by then (the page's reading of Fig. 11)


def history(run_dir: Path) -> pd.DataFrame:
    """The tracked rows of phase 2 (those with λ_max) of a run folder's history.csv."""
    frame = pd.read_csv(run_dir / "history.csv")
    frame = frame[(frame["phase"] == "gating") & frame["max_lyapunov"].notna()]
    return frame[COLUMNS].sort_values(["run", "step"]).reset_index(drop=True)


def table(frame: pd.DataFrame, runs=(0, 3)) -> str:
    """The page's tracked table: E^g's mean over networks, and block KL and λ_max ± 2 se of the
    networks named."""
    steps = [s for s in SHOWN if s in set(frame["step"])]
    at = frame.set_index(["run", "step"])
    lines = ["| gating step | " + " | ".join(map(str, steps)) + " |",
             "|---" * (len(steps) + 1) + "|",
             "| E^g, mean of 5 | " + " | ".join(
                 f"{frame.loc[frame['step'] == s, 'E_g'].mean():.2g}" for s in steps) + " |"]
    for run in runs:
        lines.append(f"| KL network {run} | " + " | ".join(
            f"{at.loc[(run, s), 'block_kl_train']:.2f}" for s in steps) + " |")
    for run in runs:
        lam, se = at.loc[run, "max_lyapunov"], at.loc[run, "max_lyapunov_se"]
        lines.append(f"| λ_max network {run} (± 2 se) | " + " | ".join(
            f"{lam[s]:.2g} ± {2 * se[s]:.1g}" for s in steps) + " |")
    return "\n".join(lines)


def _two(x: float) -> float:
    return float(f"{x:.2g}")  # two significant digits, as the page prints them


def judged(frame: pd.DataFrame) -> pd.DataFrame:
    """Per network, from step SETTLED on: λ_max's sign changes, those resolved, the changes
    beyond their error, the largest |Δλ| and the largest 2 se, and the KL's largest step."""
    rows = []
    for run, one in frame[frame["step"] >= SETTLED].groupby("run"):
        lam, se = one["max_lyapunov"].to_numpy(), one["max_lyapunov_se"].to_numpy()
        kl = one["block_kl_train"].to_numpy()
        step, bound = np.diff(lam), 2 * np.hypot(se[1:], se[:-1])
        sign = np.sign(lam)
        resolved = np.where(np.abs(lam) > 2 * se, sign, 0)
        rows.append({"network": run, "points": len(lam),
                     "sign changes": int((sign[1:] != sign[:-1]).sum()),
                     "resolved sign changes": int(((resolved[1:] * resolved[:-1]) < 0).sum()),
                     "changes beyond error": f"{int((np.abs(step) > bound).sum())} of {len(step)}",
                     "largest change of λ_max": _two(np.abs(step).max()),
                     "largest 2 se": _two(2 * se.max()),
                     "largest KL step": _two(np.abs(np.diff(kl)).max())})
    return pd.DataFrame(rows)


SUMMARY = DOCS / "lissajous9_rerun_summary.csv"
FINAL = ["run", "E", "E_g", "E_closed", "block_kl_train", "block_kl_test", "max_lyapunov",
         "max_lyapunov_se", "chaos", "positive_sample_fraction", "switch_prob", "switch_rate",
         "nonperiodic_fraction"]


def main(argv: list[str]) -> None:
    if argv:
        history(Path(argv[0])).to_csv(HISTORY, index=False)
        metrics = pd.read_csv(Path(argv[0]) / "metrics.csv")
        metrics[[c for c in FINAL if c in metrics]].to_csv(SUMMARY, index=False)
        print(f"wrote {HISTORY.relative_to(DOCS.parent)}, {SUMMARY.relative_to(DOCS.parent)}")
    frame = pd.read_csv(HISTORY)
    print(table(frame), "", to_markdown(judged(frame)), sep="\n")


if __name__ == "__main__":
    main(sys.argv[1:])
