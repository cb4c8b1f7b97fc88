"""A recording of the sizes users bring: time per epoch and memory of `moex train task=csv` at
D features, K experts and series of T steps (default D 16, K 10, 4 series x 10 000 steps).

    python benchmarks/bench_sizes.py [--features 16] [--experts 10] [--series 4] [--length 10000]
                                     [--runs 1 4] [--steps 10] [--threads 2]

A switching recording is drawn (K regimes of sinusoids, one per feature, stays of 100-400 steps,
noise SD 0.02) and saved as .npy; for each number of networks the CLI trains it twice, with
`--steps` and 2 x `--steps` steps in each phase, and the difference of the two trainings' phase
times (provenance.json) over `--steps` is the time per epoch, free of start-up and compiles.
Memory: the larger training's peak resident set (the process's own ru_maxrss) beside moex's
estimate, which it checks before any work (`moex.budget.train_bytes`).
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def recording(path: Path, series: int, length: int, features: int, regimes: int) -> None:
    rng = np.random.default_rng(0)
    freq, phase = rng.uniform(0.02, 0.2, (regimes, features)), rng.uniform(0, 6.3, (regimes,
                                                                                    features))
    amp = rng.uniform(0.2, 0.8, (regimes, features))
    out = np.empty((series, length, features))
    for s in range(series):
        t = 0
        while t < length:
            k, steps = rng.integers(regimes), np.arange(t, min(length, t + rng.integers(100, 400)))
            out[s, steps] = amp[k] * np.sin(2 * np.pi * freq[k] * steps[:, None] + phase[k])
            t = steps[-1] + 1
    np.save(path, out + 0.02 * rng.standard_normal(out.shape))


# the child reports its own peak resident set (kB on Linux) on its way out
CHILD = ("import atexit, resource, sys; atexit.register(lambda: print('peak kB', resource."
         "getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)); "
         "from moex.launch import main; main()")


def train(data: Path, experts: int, runs: int, steps: int, *, threads: int, out: Path) -> dict:
    """One `moex train`: its phases' wall seconds and its peak resident set (bytes)."""
    env = {**os.environ, "NUMBA_NUM_THREADS": str(threads), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", CHILD, "train", "task=csv", f"task.path={data}",
                           f"model.num_experts={experts}", f"num_runs={runs}",
                           f"train.experts.steps={steps}", f"train.gating.steps={steps}",
                           "eval=quick", "eval.num_samples=1", f"hydra.run.dir={out}"],
                          capture_output=True, text=True, env=env, cwd=out.parent)
    if done.returncode != 0:
        sys.exit(f"bench_sizes.py: moex train failed:\n{done.stderr[-2000:]}")
    record = json.loads((out / "provenance.json").read_text())
    record = record[-1] if isinstance(record, list) else record
    peak = int(done.stderr.rsplit("peak kB", 1)[1].split()[0]) * 1024
    return {"phase 1": record["seconds"]["phase 1"]["wall"],
            "phase 2": record["seconds"]["phase 2"]["wall"], "peak": peak}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--features", type=int, default=16)
    parser.add_argument("--experts", type=int, default=10)
    parser.add_argument("--series", type=int, default=4)
    parser.add_argument("--length", type=int, default=10_000)
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    from moex.budget import train_bytes
    from moex.config import Config
    from moex.tasks import task_config

    print(f"# D {args.features}, K {args.experts}, {args.series} series x {args.length} steps, "
          f"{args.threads} threads, cpu backend, float64")
    print("| networks | phase 1 ms per epoch | phase 2 ms per epoch | peak memory (GiB) | "
          "moex's estimate (GiB) |\n|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as scratch:
        data = Path(scratch) / "recording.npy"
        recording(data, args.series, args.length, args.features, args.experts)
        for runs in args.runs:
            short = train(data, args.experts, runs, args.steps, threads=args.threads,
                          out=Path(scratch) / f"short{runs}")
            long = train(data, args.experts, runs, 2 * args.steps, threads=args.threads,
                         out=Path(scratch) / f"long{runs}")
            per = [(long[p] - short[p]) * 1e3 / args.steps for p in ("phase 1", "phase 2")]
            cfg = Config(task=task_config("csv"), num_runs=runs)
            cfg.model.num_experts, cfg.eval.enabled = args.experts, False  # eval=quick's
            # records (1 sample) are a few MB
            estimate = train_bytes(cfg, args.series, args.length, args.features) / 2**30
            print(f"| {runs} | {per[0]:.1f} | {per[1]:.1f} | {long['peak'] / 2**30:.2f} | "
                  f"{estimate:.2f} |")


if __name__ == "__main__":
    main()
