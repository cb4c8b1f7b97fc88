"""The host's share of a training epoch on the cpu backend: the time outside the compiled
kernels' calls (the training loop's Python, PyTorch's small operations, the staging of
parameters) as a fraction of the epoch, per phase, one thread.

    python benchmarks/bench_host.py [--runs 1 30] [--steps 100] [--repeats 3] [--separate]

The compiled calls of a training step are the ones through `moex.kernels.cpu.threads.over` (the
separate calls: phase kernels, momentum update, adaptive-rate trial) and the stepper's
(`moex.kernels.cpu.step`: each phase's `evaluate`, which makes each run's sums and momentum step
inside, and the update functions between, through `threads.over` where the buffers are large);
the script wraps them all to add up the time spent inside (a call inside another counted once).
In the separate calls each phase's sums per run (a few µs) are called directly and count as host
time. `--separate`: the training loop's separate calls (no stepper), for the comparison. Epoch
and host times are marginal (`base + steps` epochs minus `base`, as `bench_epochs.py`), the pair
with the least epoch time of `--repeats`. Two-Lissajous sizes.
"""

import argparse

import numba
import torch
from bench_epochs import outside_pairs, trainers

from moex.kernels.cpu import phases, step, threads

COMPILED = [(threads, "over"), (phases.ExpertProblem, "evaluate"),
            (phases.GatingProblem, "evaluate"), (step, "before_gradient"), (step, "after_trial"),
            (step, "after_trials")]


def host_share(fn, steps: int, base: int, repeats: int) -> tuple[float, float]:
    """(epoch, host) seconds per epoch of `fn(n)` (n epochs), host = outside the compiled calls
    (`COMPILED`): the pair with the least epoch time."""
    return min(outside_pairs(fn, COMPILED, steps, base, repeats))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 30])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--base", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--separate", action="store_true",
                        help="the training loop's separate calls, no stepper")
    args = parser.parse_args(argv)
    if args.separate:
        phases._Problem.stepper = lambda self, *a, **k: None
    numba.set_num_threads(1)
    torch.set_num_threads(1)
    print("| phase | R | ms per epoch | host ms per epoch | host share |\n|---|---|---|---|---|")
    for R in args.runs:
        for name, fn in trainers("lissajous2", R, "cpu")[0].items():
            epoch, host = host_share(fn, args.steps, args.base, args.repeats)
            print(f"| {name} | {R} | {1e3 * epoch:.3f} | {1e3 * host:.3f} | "
                  f"{100 * host / epoch:.1f} % |", flush=True)


if __name__ == "__main__":
    main()
