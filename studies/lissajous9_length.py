"""The nine-curve task's training length as a controlled arm (Sec. 3.2.2, Figs. 10-13).

The same 5 seeds, data and settings as the paper-scale run (30000 + 10000 steps), trained twice
as long in both phases (60000 + 20000), and that run's own gating network at its step 10000
(60000 + 10000: the checkpoint of gating step 10000, continued by `moex train` with
`train.gating.steps=10000`, so that it only writes its outputs and its final evaluation):

    moex train experiment=paper_lissajous9 train.experts.steps=60000 train.gating.steps=20000 \\
        hydra.run.dir=outputs/paper_lissajous9/long_n5
    python -m studies.lissajous9_length outputs/paper_lissajous9/long_n5_gating10k \\
        outputs/paper_lissajous9/long_n5

Writes docs/lissajous9_long_summary.csv (both runs' metrics.csv, column `gating_steps`) and
prints, network by network (paired by seed), what each does in closed loop, its λ_max, switching
and test KL in the three arms, and the paired differences (mean ± standard error over the 5
seeds) of the two comparisons: phase 2 twice as long on the same phase 1 (one factor), and the
whole training twice as long against the paper-scale run (which an earlier moex trained on
another CPU: round-off differs too). Without arguments it prints from the CSVs.

What a network does (its final evaluation, 50 random initial states × 100 000 steps):
"like the paper's example" if λ_max > 0 (the paper's criterion) and its block KL on held-out
data is below 2 (the paper-scale run: 1.25 for its one network like the paper's, 5.9-7.6 for
those on an orbit the data do not have); "chaotic elsewhere" if λ_max > 0 and the KL is higher;
"not chaotic" otherwise. (The rule was fixed after the 60000 + 10000 evaluation and before the
60000 + 20000 one.)
"""

import sys
from pathlib import Path

import numpy as np
import pandas as pd

from moex.report import to_markdown, wilson_interval
from studies.capacity_cells import fisher_p
from studies.common import DOCS

LONG = DOCS / "lissajous9_long_summary.csv"
COLUMNS = ["run", "E", "E_g", "E_closed", "block_kl_train", "block_kl_test", "max_lyapunov",
           "positive_sample_fraction", "switch_prob", "switch_rate"]
KL_LIKE_PAPER = 2.0
ARMS = ("30000 + 10000", "60000 + 10000", "60000 + 20000")
GATING_STEPS = (10000, 20000)  # of the two long arms
PHASE_2 = f"{ARMS[2]} − {ARMS[1]} (phase 2 only)"
WHOLE = f"{ARMS[2]} − {ARMS[0]}"
PAIRED = {"E^g": "E_g", "E^closed": "E_closed", "block KL test": "block_kl_test",
          "λ_max": "max_lyapunov", "switches per lap": "switch_prob"}


def behaviour(row) -> str:
    if not row.max_lyapunov > 0:
        return "not chaotic"
    return "like the paper's example" if row.block_kl_test < KL_LIKE_PAPER else "chaotic elsewhere"


def arms() -> list[pd.DataFrame]:
    """The three arms' rows, one per seed in the same order (`ARMS`)."""
    short = pd.read_csv(DOCS / "lissajous9_summary.csv")
    frames = [short[short.job == "n5"]]
    long = pd.read_csv(LONG)
    frames += [long[long.gating_steps == steps] for steps in GATING_STEPS]
    frames = [f[COLUMNS].sort_values("run", ignore_index=True) for f in frames]
    for frame in frames[1:]:
        if list(frame.run) != list(frames[0].run):
            raise ValueError(f"the arms hold other seeds: {list(frames[0].run)} and "
                             f"{list(frame.run)}")
    return frames


def table(frames: list[pd.DataFrame]) -> pd.DataFrame:
    """One row per network: each metric in the three arms, in `ARMS`' order."""
    def joined(fmt, rows):
        return " → ".join(fmt(r) for r in rows)

    out = []
    for i in range(len(frames[0])):
        rows = [f.iloc[i] for f in frames]
        out.append({
            "network": int(rows[0].run),
            "what it does": joined(behaviour, rows),
            "λ_max (samples > 0)": joined(
                lambda r: f"{r.max_lyapunov:.4f} ({r.positive_sample_fraction:.0%})", rows),
            "switches per lap": joined(lambda r: f"{r.switch_prob:.2f}", rows),
            "block KL test": joined(lambda r: f"{r.block_kl_test:.2f}", rows),
            "E^closed": joined(lambda r: f"{r.E_closed:.2f}", rows)})
    return pd.DataFrame(out)


def _paired(before: pd.DataFrame, after: pd.DataFrame, column: str) -> str:
    diff = (after[column] - before[column]).dropna()
    se = diff.std(ddof=1) / np.sqrt(len(diff)) if len(diff) > 1 else float("nan")
    return f"{diff.mean():+.3g} ± {se:.2g} ({int((diff > 0).sum())} of {len(diff)} up)"


def _like_paper(frame: pd.DataFrame) -> int:
    return int((frame.apply(behaviour, axis=1) == "like the paper's example").sum())


def differences(frames: list[pd.DataFrame]) -> pd.DataFrame:
    """Paired differences over the seeds (mean ± SE, how many rose): phase 2 twice as long on
    the same phase 1, and the whole training twice as long against the paper-scale run; then
    each arm's count of networks like the paper's example and of λ_max > 0."""
    short, mid, long = frames
    rows = [{"metric": name, PHASE_2: _paired(mid, long, column),
             WHOLE: _paired(short, long, column)} for name, column in PAIRED.items()]
    n = len(short)
    for what, count in (("like the paper's example", _like_paper),
                        ("λ_max > 0", lambda f: int((f.max_lyapunov > 0).sum()))):
        rows.append({"metric": f"networks {what}", PHASE_2: f"{count(mid)} → {count(long)} of {n}",
                     WHOLE: f"{count(short)} → {count(long)} of {n}"})
    return pd.DataFrame(rows)


def resolution(frames: list[pd.DataFrame]) -> str:
    """What 5 networks per arm can tell: the longest arm's share like the paper's example with
    its Wilson interval, and Fisher's exact p of 1 against 4 of n, a large change."""
    n, k = len(frames[-1]), _like_paper(frames[-1])
    low, high = wilson_interval(k, n)
    return (f"{ARMS[2]}: {k} of {n} like the paper's example, 95 % Wilson interval "
            f"[{low:.0f}, {high:.0f}] %; 1 against {n - 1} of {n} would give Fisher's exact p "
            f"{fisher_p(1, n - 1, n - 1, 1):.2f}")


def collect(mid: Path, long: Path) -> pd.DataFrame:
    """Both runs' metrics.csv, with the gating steps each trained."""
    return pd.concat([pd.read_csv(folder / "metrics.csv").assign(gating_steps=steps)
                      for folder, steps in zip((mid, long), GATING_STEPS, strict=True)],
                     ignore_index=True)


if __name__ == "__main__":
    if len(sys.argv) > 1:
        folders = [Path(a) for a in sys.argv[1:]]
        missing = [str(f / "metrics.csv") for f in folders if not (f / "metrics.csv").is_file()]
        if len(folders) != 2 or missing:
            print("lissajous9_length.py: give the 60000 + 10000 and the 60000 + 20000 run "
                  f"folders, both finished (missing: {', '.join(missing) or 'a folder'})",
                  file=sys.stderr)
            sys.exit(2)
        collect(*folders).to_csv(LONG, index=False)
    frames = arms()
    print(to_markdown(table(frames)))
    print()
    print(to_markdown(differences(frames)))
    print()
    print(resolution(frames))
