"""What the adaptive learning rate (Sec. 2.1.4) costs over a fixed rate on the cpu backend, with
the forward pass and the objective (with ∂L/∂o) of an accepted trial reused by the next gradient
step (the stepper's record of its lanes, `lanes.Forwarded.enabled`) and without (every call runs
its own forward pass and objective).

    python benchmarks/bench_adaptive.py [--runs 1 30] [--rounds 5]

Two-Lissajous sizes (10 series x 1000 steps, 2 experts of 10 units, a gating RNN of 15), one
thread. Each figure is the marginal CPU ms per network-epoch (a training of --base + --steps
epochs minus one of --base); the cases take turns within each round, and each round gives a
ratio to the fixed-rate phase 1 of the same round, so a drift of the machine's speed hits both.
"""

import argparse
import statistics

from bench_epochs import marginal, ratios, trainers, warm_up

from moex.kernels.cpu import lanes

CASES = (("phase 1, fixed rate", True), ("phase 1, adaptive rate", True),
         ("phase 1, adaptive rate", False), ("phase 2, adaptive rate", True),
         ("phase 2, adaptive rate", False))


def rounds(runs: int, count: int, steps: int, base: int) -> dict[tuple[str, bool], list[float]]:
    """{(phase, reuse): [ms per network-epoch, one per round]}."""
    fns = trainers("lissajous2", runs, "cpu")[0]
    out = {case: [] for case in CASES}
    for phase, reuse in CASES:  # compile (or load) at the timed sizes
        lanes.Forwarded.enabled = reuse
        warm_up(fns[phase], steps, base)
    try:
        for _ in range(count):
            for phase, reuse in CASES:
                lanes.Forwarded.enabled = reuse
                out[(phase, reuse)].append(1e3 * marginal(fns[phase], steps, base)[1] / runs)
    finally:
        lanes.Forwarded.enabled = True
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 30])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--base", type=int, default=10)
    args = parser.parse_args(argv)
    print("| R | work | CPU ms per network-epoch, trial's pass reused | run again | "
          "reused / run again | / phase 1 at a fixed rate |\n|---|---|---|---|---|---|")
    for runs in args.runs:
        times = rounds(runs, args.rounds, args.steps, args.base)
        fixed = times[CASES[0]]
        print(f"| {runs} | {CASES[0][0]} | {statistics.median(fixed):.2f} | | | 1 |")
        for phase in ("phase 1, adaptive rate", "phase 2, adaptive rate"):
            reused, again = times[(phase, True)], times[(phase, False)]
            cells = [f"{statistics.median(reused):.2f}", f"{statistics.median(again):.2f}",
                     ratios(reused, again), ratios(reused, fixed) if "1" in phase else ""]
            print(f"| {runs} | {phase} | {' | '.join(cells)} |", flush=True)


if __name__ == "__main__":
    main()
