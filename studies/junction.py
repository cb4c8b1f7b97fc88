"""Does a network's ĝ ambiguity where the two curves meet predict that it stays on one curve?
(open question 1 of the P = 0.5 study). Phase 1 fits gate targets ĝ = softmax(β) (Eq. 11) to
every step of the training data; phase 2 teaches the gating network to reproduce them. Where a lap
ends, the data continues on either curve with probability P, and the two curves pass through the
same point, so ĝ there has to carry the switch. If phase 1 leaves ĝ ambiguous (≈ 0.5) around the
lap boundaries, phase 2 has a weak target there, and a network might learn to stay.

    python -m studies.junction RUN_DIR    # a phase-1-trained Table 2 P = 0.5 run (checkpoint.pt)

Per network, from the checkpoint's β and labels (no training, no evaluation):
    ambiguity_boundary  mean min_k ĝ_k over the first 3 steps of every lap (0: crisp, 0.5: none)
    ambiguity_inside    the same over the other steps
    missed_switch       mean ĝ of the *old* curve at the first step after a switch
joined by network index with Table 2's soft-target outcome at P = 0.5 (docs/table2_summary.csv:
the same seeds, data and phase-1 settings; phase 1 there ran on another CPU, so its experts are
these up to round-off grown over 30 000 steps: the script prints how far the two phase-1 errors
E lie apart). Writes
docs/junction_ambiguity.csv and prints Spearman's ρ (permutation p) between each measure and the
switching probability, and the measures of the networks that stay (< 0.03) against the others.
"""

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from studies.common import DOCS

STAYS, LAP, FIRST = 0.03, 25, 3


def measures(checkpoint: Path) -> pd.DataFrame:
    state = torch.load(checkpoint, weights_only=False)
    ghat = torch.softmax(state["beta"], -1).numpy()  # (R, S, T - 1, K): target step t + 1
    labels = np.asarray(state["labels"])[:, 1:]  # (S, T - 1), aligned with ĝ
    steps = np.arange(labels.shape[1]) + 1
    boundary = ((steps % LAP) < FIRST) & (steps >= LAP)
    ambiguity = ghat.min(-1)  # (R, S, T - 1)
    switched = np.zeros_like(labels, dtype=bool)
    switched[:, 1:] = labels[:, 1:] != labels[:, :-1]
    old = np.zeros_like(labels)
    old[:, 1:] = labels[:, :-1]
    s_idx, t_idx = np.nonzero(switched)
    missed = ghat[:, s_idx, t_idx, old[s_idx, t_idx]].mean(-1)
    return pd.DataFrame({"run": np.arange(ghat.shape[0]),
                         "ambiguity_boundary": ambiguity[:, :, boundary].mean((1, 2)),
                         "ambiguity_inside": ambiguity[:, :, ~boundary].mean((1, 2)),
                         "missed_switch": missed,
                         "E_here": [float(e) for e in phase1_error(state)]})


def phase1_error(state) -> np.ndarray:
    """E (Eq. 10's squared error, per run) of the checkpoint's experts on its training data, from
    the training history's last phase-1 row."""
    rows = pd.DataFrame(state["experts_rows"])
    last = rows[rows.step == rows.step.max()].sort_values("run")
    return last["E"].to_numpy()


def spearman(a: np.ndarray, b: np.ndarray, permutations: int = 20000) -> tuple[float, float]:
    """Spearman's rank correlation and its two-sided permutation p (b's ranks shuffled). Ranks
    (ties averaged) less their mean (n + 1) / 2 are multiples of 1/2, so each permutation's
    Σ (ra - mean)(rb - mean), which orders the permutations as their correlation does, is
    summed exactly in integers: ties with the observed order count, as they should."""
    ra, rb = pd.Series(a).rank().to_numpy(), pd.Series(b).rank().to_numpy()
    rho = np.corrcoef(ra, rb)[0, 1]
    twice_a, twice_b = (np.rint(2 * r - (len(r) + 1)).astype(np.int64) for r in (ra, rb))
    rng = np.random.default_rng(0)
    shuffled = np.array([rng.permutation(len(rb)) for _ in range(permutations)])
    null = twice_b[shuffled] @ twice_a
    # the observed order counts as one of the permutations, so p is never 0
    return rho, ((np.abs(null) >= abs(twice_b @ twice_a)).sum() + 1) / (permutations + 1)


def main(run_dir: str) -> None:
    ours = measures(Path(run_dir) / "checkpoint.pt")
    table2 = pd.read_csv(DOCS / "table2_summary.csv")
    soft = table2[table2["task.switch_prob"] == 0.5][["run", "E", "switch_prob", "max_lyapunov"]]
    both = ours.merge(soft, on="run")
    both.to_csv(DOCS / "junction_ambiguity.csv", index=False)
    gap = (both.E_here / both.E - 1).abs()
    print(f"{len(both)} networks; phase-1 E here against Table 2's: median relative difference "
          f"{gap.median():.1%}, largest {gap.max():.1%}")
    stays = both.switch_prob < STAYS
    for col in ("ambiguity_boundary", "ambiguity_inside", "missed_switch"):
        rho, p = spearman(both[col].to_numpy(), both.switch_prob.to_numpy())
        print(f"{col:>18}: Spearman ρ with switching {rho:+.2f} (p = {p:.3f}); the {stays.sum()} "
              f"that stay {both[col][stays].mean():.4f} ± {both[col][stays].std():.4f}, the "
              f"{(~stays).sum()} others {both[col][~stays].mean():.4f} ± "
              f"{both[col][~stays].std():.4f}")


if __name__ == "__main__":
    main(sys.argv[1])
