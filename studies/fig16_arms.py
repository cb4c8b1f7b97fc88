"""Fig. 16's second half, one factor at a time: is the contradiction a choice of moex's model?

The paper: "in the region corresponding to a small amount of training data, output is periodic
even if noise is added" (Sec. 4.3). In moex's smallest capacity cell (NT 2, LT 250) most networks
turn nonperiodic at ρ² = 10⁻³. Here that cell is trained again at NC 10 and 30 under each arm of
conf/p05_arm/ that changes the model or its training towards the authors' C code (one factor per
arm; `c_code` all of them together), with the baseline on the same seeds:

    moex train -m experiment=p05_study p05_arm=baseline,targets_onehot,c_code,... \\
        task.num_series=2 task.length=250 model.gating.context_size=10 \\
        cache_dir=outputs/fig16_cause/phase1_cache hydra.sweep.dir=outputs/fig16_cause/nc10
    moex evaluate run_dir=<job> eval.noise_var=0.001 out_dir=<job>/evaluate/noise0.001   # each job
    python -m studies.fig16_arms outputs/fig16_cause/nc10 outputs/fig16_cause/nc30

Writes docs/fig16_arms.csv (one row per arm, NC, ρ² and network) and prints, per arm and NC: the
networks with a majority of nonperiodic samples at ρ² = 0 → 10⁻³ (the paper: few at both), those
with λ_max > 10⁻⁴ and those staying on one curve without noise, and Fisher's exact p of the
count at 10⁻³ against the baseline's.
"""

import sys
from pathlib import Path

import pandas as pd

from moex.report import to_markdown
from studies.capacity_cells import STAY, arms_at_noise, chaotic, mostly_nonperiodic
from studies.common import DOCS

NOISE = 1e-3
COLUMNS = ["run", "E_closed", "max_lyapunov", "switch_prob", "nonperiodic_fraction",
           "periodicity_samples"]


def collect(sweeps: list[Path]) -> pd.DataFrame:
    """Every job of the sweeps without noise (its own metrics.csv) and at ρ² = `NOISE`."""
    parts = []
    for sweep in sweeps:
        jobs = pd.read_csv(sweep / "jobs.csv", dtype=str)
        for folder, overrides in zip(jobs.folder, jobs.overrides, strict=True):
            keys = dict(kv.split("=", 1) for kv in overrides.split())
            for noise, path in ((0.0, sweep / folder / "metrics.csv"),
                                (NOISE, sweep / folder / "evaluate" / f"noise{NOISE:g}"
                                 / "metrics.csv")):
                runs = pd.read_csv(path)[COLUMNS]
                parts.append(runs.assign(arm=keys["p05_arm"], noise_var=noise,
                                         context_size=int(keys["model.gating.context_size"])))
    return pd.concat(parts, ignore_index=True)[
        ["arm", "context_size", "noise_var", *COLUMNS]].sort_values(
        ["context_size", "arm", "noise_var", "run"], ignore_index=True)


def table(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per NC and arm, the baseline first."""
    noisy = arms_at_noise(runs, NOISE).set_index(["context_size", "arm"])
    rows = []
    for nc, at_nc in runs.groupby("context_size"):
        for arm in ["baseline"] + sorted(set(at_nc.arm) - {"baseline"}):
            quiet = at_nc[(at_nc.arm == arm) & (at_nc.noise_var == 0)]
            counts = noisy.loc[(nc, arm)]
            rows.append({
                "NC": int(nc), "arm": arm, "networks": int(counts.networks),
                "mostly nonperiodic, ρ² = 0 → 10⁻³":
                    f"{mostly_nonperiodic(quiet, 0)} → {int(counts.mostly)}",
                "p against baseline (10⁻³)": "–" if arm == "baseline" else f"{counts.p:.2g}",
                "λ_max > 0 (> 10⁻⁴)": chaotic(quiet),
                "stay (< 0.02)": int((quiet.switch_prob < STAY).sum()),
                "switching": f"{quiet.switch_prob.mean():.2f} ± {quiet.switch_prob.std():.2f}",
                "E^closed": f"{quiet.E_closed.mean():.2g}"})
    return pd.DataFrame(rows)


if __name__ == "__main__":
    if len(sys.argv) > 1:
        try:
            runs = collect([Path(a) for a in sys.argv[1:]])
        except FileNotFoundError as error:  # a sweep not finished, or a job not evaluated
            print(f"fig16_arms.py: {error}", file=sys.stderr)
            sys.exit(2)
        runs.to_csv(DOCS / "fig16_arms.csv", index=False)
    print(to_markdown(table(pd.read_csv(DOCS / "fig16_arms.csv"))))
