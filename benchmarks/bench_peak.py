"""This core's clock and float64 peak, measured: 16 independent scalar FMA chains in a numba loop
keep a core's FMA pipes busy, so their rate is pipes × 2 flops × clock; the vector peak is then
flops per cycle × clock.

    python benchmarks/bench_peak.py [--pipes 2] [--flops-per-cycle 16] [--steps 20000000]

The defaults are Zen 4's (two 256-bit FMA pipes: 8 float64 FMAs, 16 flops per cycle; AMD's
Software Optimization Guide for Family 19h); other CPUs need their own (Intel cores with two
512-bit FMA units: 2 pipes, 32 flops per cycle).
"""

import argparse
import time

import numpy as np
from numba import njit


@njit(fastmath={"contract"})
def _chains(n, x):  # pragma: no cover (compiled)
    a = x.copy()  # 16 accumulators, each its own dependency chain
    b, c = 0.999999, 1e-7
    for _ in range(n):
        for j in range(16):
            a[j] = a[j] * b + c  # one fused multiply-add (`contract`)
    return a.sum()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pipes", type=int, default=2)
    parser.add_argument("--flops-per-cycle", type=int, default=16)
    parser.add_argument("--steps", type=int, default=20_000_000)
    args = parser.parse_args(argv)
    x = np.linspace(0.5, 1.0, 16)
    _chains(10, x)
    best = min(_timed(args.steps, x) for _ in range(3))
    rate = 16 * 2 * args.steps / best / 1e9
    clock = rate / (args.pipes * 2)
    print(f"scalar FMA chains: {rate:.2f} Gflop/s -> clock {clock:.2f} GHz at {args.pipes} FMA "
          f"pipes; float64 peak {args.flops_per_cycle} x {clock:.2f} = "
          f"{args.flops_per_cycle * clock:.1f} Gflop/s per core")


def _timed(steps: int, x: np.ndarray) -> float:
    start = time.perf_counter()
    _chains(steps, x)
    return time.perf_counter() - start


if __name__ == "__main__":
    main()
