"""λ_max of the authors' Table 2 control networks four ways: moex's estimator (Benettin's method
on the closed loop's Jacobian, `moex evaluate`); the same with the gates held at 1/K in the
Jacobian, as the authors' tool differentiates the mixture (`eval.jacobian_gates=uniform`); the
authors' `mregn-lyapunov` itself (studies/mregn_control.py lyapunov); and a check that uses no
Jacobian at all: two closed-loop trajectories 10⁻⁸ apart, their distance measured and
renormalised every `CHUNK` steps, its mean log growth per step (Benettin's two-trajectory method
on the nonlinear map itself).

    moex evaluate run_dir=<out>/<design>/moex eval.jacobian_gates=uniform \
        out_dir=<out>/<design>/moex_uniform                # for each design, then
    python -m studies.lyapunov_crosscheck <out folder>        # <out>/<design>/moex, as imported

writes docs/lyapunov_crosscheck.csv, one row per network, and prints it. The other direction,
moex-trained networks scored by the authors' tool:

    moex evaluate run_dir=<run> eval=paper out_dir=<run>/exact        # and, with the gates at 1/K,
    moex evaluate run_dir=<run> eval=paper eval.jacobian_gates=uniform out_dir=<run>/uniform
    python -m studies.lyapunov_crosscheck moex <run> <C network folder> <bin folder> <out folder>

exports each network of the moex run to the C tools' files (`moex.importer.export_run`, over the
files of a C-trained network of the same sizes), scores it with `mregn-lyapunov` and writes
docs/lyapunov_crosscheck_moex.csv beside moex's two estimates.

The two estimates of the same trajectories, sample by sample (each network's 50 initial states,
the same transient, then the exact-Jacobian estimate and the two-trajectory check from the same
point):

    python -m studies.lyapunov_crosscheck paired <out folder>

writes docs/lyapunov_crosscheck_paired.csv (one row per network and sample) and prints, per
network, how far the two are apart and in how many samples they agree in sign.
"""

import sys
from pathlib import Path

import pandas as pd
import torch

from moex import checkpoint
from moex.closed_loop import closed_loop_lyapunov
from moex.importer import export_run
from moex.kernels import get_backend
from moex.model import random_state
from moex.mregn_format import read_save
from studies.common import DOCS
from studies.mregn_control import their_lyapunov

DESIGNS = ("table2_p05", "table2_p025")
SAMPLES, TRANSIENT, STEPS, CHUNK, EPS = 4, 1000, 100_000, 10, 1e-8
PAIRED_SAMPLES = 50  # as moex's evaluation draws (eval.num_samples)


def two_trajectories(experts, gating, state, steps: int, *, backend, generator) -> torch.Tensor:
    """(R, N) mean log growth per step of a perturbation of size `EPS` along a random direction,
    renormalised every `CHUNK` steps: the largest exponent without the Jacobian."""
    shift = torch.randn(state.flat().shape, generator=generator, dtype=state.flat().dtype)
    other = state.like(state.flat() + EPS * shift / shift.norm(dim=-1, keepdim=True))
    total = torch.zeros(state.flat().shape[:-1], dtype=state.flat().dtype)
    for _ in range(steps // CHUNK):
        state = backend.closed_loop(experts, gating, state, CHUNK).state
        other = backend.closed_loop(experts, gating, other, CHUNK).state
        gap = other.flat() - state.flat()
        size = gap.norm(dim=-1, keepdim=True)
        total += torch.log(size[..., 0] / EPS)
        other = state.like(state.flat() + EPS * gap / size)
    return total / (steps // CHUNK * CHUNK)


def crosscheck(out: Path) -> pd.DataFrame:
    backend, rows = get_backend("cpu"), []
    theirs = pd.read_csv(DOCS / "mregn_control_lyapunov.csv")
    for design in DESIGNS:
        saved = checkpoint.load(out / design / "moex")
        ours = pd.read_csv(out / design / "moex" / "metrics.csv")
        uniform = pd.read_csv(out / design / "moex_uniform" / "metrics.csv")
        generator = torch.Generator().manual_seed(0)
        state = random_state(saved.experts, saved.gating, SAMPLES,
                             num_features=saved.series.shape[-1],
                             delay=int(saved.config["model"]["delay"]), generator=generator)
        state = backend.closed_loop(saved.experts, saved.gating, state, TRANSIENT).state
        growth = two_trajectories(saved.experts, saved.gating, state, STEPS, backend=backend,
                                  generator=generator)
        tool = theirs[theirs["design"] == design].reset_index(drop=True)
        for r in range(len(ours)):
            rows.append({"design": design, "network": tool["network"][r],
                         "moex": ours["max_lyapunov"][r], "moex_se": ours["max_lyapunov_se"][r],
                         "moex_uniform_gates": uniform["max_lyapunov"][r],
                         "two_trajectories": float(growth[r].mean()),
                         "two_trajectories_spread": float(growth[r].std()),
                         "mregn_lyapunov": tool["max_lyapunov"][r]})
    return pd.DataFrame(rows)


def paired(out: Path, samples: int = PAIRED_SAMPLES, steps: int = STEPS) -> pd.DataFrame:
    """Each imported network's `samples` trajectories measured both ways from the same initial
    states: Benettin's exact-Jacobian estimate (`closed_loop_lyapunov`, `TRANSIENT` steps to align
    the tangent) and `two_trajectories` from the state after the same `TRANSIENT` steps."""
    backend, rows = get_backend("cpu"), []
    for design in DESIGNS:
        saved = checkpoint.load(out / design / "moex")
        generator = torch.Generator().manual_seed(0)
        start = random_state(saved.experts, saved.gating, samples,
                             num_features=saved.series.shape[-1],
                             delay=int(saved.config["model"]["delay"]), generator=generator)
        exact = closed_loop_lyapunov(saved.experts, saved.gating, start.like(start.flat().clone()),
                                     steps, TRANSIENT, generator=generator, backend=backend)[..., 0]
        state = backend.closed_loop(saved.experts, saved.gating, start, TRANSIENT).state
        direct = two_trajectories(saved.experts, saved.gating, state, steps, backend=backend,
                                  generator=generator)
        files = pd.read_csv(out / design / "moex" / "imported_from.csv")
        names = {int(r): Path(f).parent.name for r, f in zip(files["network"], files["file"],
                                                              strict=True)}
        for r in range(exact.shape[0]):
            for n in range(samples):
                rows.append({"design": design, "network": names[r],
                             "sample": n, "exact": float(exact[r, n]),
                             "two_trajectories": float(direct[r, n])})
    return pd.DataFrame(rows)


def agreement(frame: pd.DataFrame) -> pd.DataFrame:
    """Per network: the mean of each estimate, the largest difference of a pair, and in how
    many pairs the sign agrees."""
    frame = frame.assign(gap=(frame["exact"] - frame["two_trajectories"]).abs(),
                         same_sign=(frame["exact"] > 0) == (frame["two_trajectories"] > 0))
    return frame.groupby(["design", "network"], sort=False).agg(
        exact=("exact", "mean"), two_trajectories=("two_trajectories", "mean"),
        largest_gap=("gap", "max"), median_gap=("gap", "median"),
        same_sign=("same_sign", "sum"), samples=("sample", "count")).reset_index()


def moex_networks(run_dir: Path, template: Path, bin_dir: Path, out: Path) -> pd.DataFrame:
    """Each network of a finished moex run as the C tools' files in <out>/moex/net<r+1>/ (over
    `template`'s mre.dat and gn.dat), its λ_max from `mregn-lyapunov`, and moex's exact and
    uniform-gate estimates (<run>/exact/metrics.csv, <run>/uniform/metrics.csv)."""
    record = checkpoint.load(run_dir)
    templates = {name: read_save(template / name) for name in ("mre.dat", "gn.dat")}
    ours = pd.read_csv(run_dir / "exact" / "metrics.csv")
    uniform = pd.read_csv(run_dir / "uniform" / "metrics.csv")
    for r in range(len(ours)):
        folder = out / "moex" / f"net{r + 1:03d}"
        export_run(record, r, templates, folder)
        (folder / "done").write_text(f"exported from {run_dir}, run {r}\n")
    tool = pd.DataFrame(their_lyapunov("moex", bin_dir, out))
    return pd.DataFrame({"run": ours["run"], "moex": ours["max_lyapunov"],
                         "moex_se": ours["max_lyapunov_se"],
                         "moex_uniform_gates": uniform["max_lyapunov"],
                         "mregn_lyapunov": tool["max_lyapunov"],
                         "switch_prob": ours["switch_prob"]})


if __name__ == "__main__":
    if sys.argv[1] == "paired":
        frame = paired(Path(sys.argv[2]))
        frame.to_csv(DOCS / "lyapunov_crosscheck_paired.csv", index=False)
        frame = agreement(frame)
    elif sys.argv[1] == "moex":
        frame = moex_networks(*(Path(a).resolve() for a in sys.argv[2:6]))
        frame.to_csv(DOCS / "lyapunov_crosscheck_moex.csv", index=False)
    else:
        frame = crosscheck(Path(sys.argv[1]))
        frame.to_csv(DOCS / "lyapunov_crosscheck.csv", index=False)
    print(frame.to_string(index=False))
