"""The nine-curve task's training length as a controlled arm (Sec. 3.2.2, Figs. 10-13).

The same 5 seeds, data and settings as the paper-scale run (30000 + 10000 steps), trained twice
as long in both phases (60000 + 20000); nothing else changed:

    moex train experiment=paper_lissajous9 train.experts.steps=60000 train.gating.steps=20000 \\
        hydra.run.dir=outputs/paper_lissajous9/long_n5
    python docs/lissajous9_length.py outputs/paper_lissajous9/long_n5

Writes docs/lissajous9_long_summary.csv (the long run's metrics.csv) and prints, network by
network (paired by seed) against the paper-scale rows of docs/lissajous9_summary.csv: what each
network does in closed loop, its λ_max, switching and test KL, and the paired differences
(mean ± standard error over the 5 seeds). Without an argument it prints from the CSVs.

What a network does (from its final evaluation, 50 random initial states × 100 000 steps):
"chaotic switching" if λ_max > 0 (the paper's criterion) and it changes curve at least once per
100 periods of a curve (`switch_rate` ≥ 0.01); "one orbit" if it changes curve less often
(whatever its λ_max: an orbit that rarely completes a lap); "periodic" otherwise.
"""

import sys
from pathlib import Path

import numpy as np
import pandas as pd

from moex.report import to_markdown

DOCS = Path(__file__).resolve().parent
LONG = DOCS / "lissajous9_long_summary.csv"
COLUMNS = ["run", "E", "E_g", "E_closed", "block_kl_train", "block_kl_test", "max_lyapunov",
           "positive_sample_fraction", "switch_prob", "switch_rate"]
SWITCHES = 0.01  # changes of curve per period below which a network stays on one orbit
PAIRED = {"E^closed": "E_closed", "block KL test": "block_kl_test", "λ_max": "max_lyapunov",
          "switches per lap": "switch_prob", "switches per period": "switch_rate"}


def behaviour(row) -> str:
    if not row.switch_rate >= SWITCHES:  # (NaN: no switch was ever seen)
        return "one orbit"
    return "chaotic switching" if row.max_lyapunov > 0 else "periodic"


def arms() -> tuple[pd.DataFrame, pd.DataFrame]:
    """(paper-scale, long) rows, one per seed, in the same order."""
    short = pd.read_csv(DOCS / "lissajous9_summary.csv")
    short = short[short.job == "n5"][COLUMNS].sort_values("run", ignore_index=True)
    long = pd.read_csv(LONG)[COLUMNS].sort_values("run", ignore_index=True)
    if list(short.run) != list(long.run):
        raise ValueError(f"the arms hold other seeds: {list(short.run)} and {list(long.run)}")
    return short, long


def table(short: pd.DataFrame, long: pd.DataFrame) -> pd.DataFrame:
    """One row per network: each metric as paper-scale → long."""
    rows = []
    for (_, a), (_, b) in zip(short.iterrows(), long.iterrows(), strict=True):
        rows.append({
            "network": int(a.run),
            "behaviour": f"{behaviour(a)} → {behaviour(b)}",
            "λ_max (samples > 0)": f"{a.max_lyapunov:.4f} ({a.positive_sample_fraction:.0%}) → "
                                   f"{b.max_lyapunov:.4f} ({b.positive_sample_fraction:.0%})",
            "switches per lap (per period)": f"{a.switch_prob:.2f} ({a.switch_rate:.3f}) → "
                                             f"{b.switch_prob:.2f} ({b.switch_rate:.3f})",
            "block KL test": f"{a.block_kl_test:.2f} → {b.block_kl_test:.2f}",
            "E^closed": f"{a.E_closed:.3f} → {b.E_closed:.3f}",
            "E^g": f"{a.E_g:.2g} → {b.E_g:.2g}"})
    return pd.DataFrame(rows)


def differences(short: pd.DataFrame, long: pd.DataFrame) -> pd.DataFrame:
    """Paired long − paper-scale differences: mean ± standard error over the seeds (NaN rows,
    a switching rate never measured, left out and counted)."""
    rows = []
    for name, column in PAIRED.items():
        diff = (long[column] - short[column]).dropna()
        se = diff.std(ddof=1) / np.sqrt(len(diff)) if len(diff) > 1 else float("nan")
        rows.append({"metric": name, "paired long − paper-scale": f"{diff.mean():+.3g} ± "
                     f"{se:.2g}", "n": len(diff),
                     "networks that rose": int((diff > 0).sum())})
    counts = {arm: frame.apply(behaviour, axis=1).value_counts().to_dict()
              for arm, frame in (("paper-scale", short), ("long", long))}
    rows.append({"metric": "chaotic switching", "paired long − paper-scale":
                 f"{counts['paper-scale'].get('chaotic switching', 0)} → "
                 f"{counts['long'].get('chaotic switching', 0)} of {len(long)}",
                 "n": len(long), "networks that rose": ""})
    return pd.DataFrame(rows)


if __name__ == "__main__":
    if len(sys.argv) > 1:
        metrics = Path(sys.argv[1]) / "metrics.csv"
        if not metrics.is_file():
            print(f"lissajous9_length.py: no {metrics} (the training has not finished)",
                  file=sys.stderr)
            sys.exit(2)
        pd.read_csv(metrics).to_csv(LONG, index=False)
    short, long = arms()
    print(to_markdown(table(short, long)))
    print()
    print(to_markdown(differences(short, long)))
