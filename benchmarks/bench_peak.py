"""This core's clock and peak, measured two ways. 16 independent scalar FMA chains in a numba loop
keep a core's FMA pipes busy, so their rate is pipes × 2 flops × clock; the vector peak is then
flops per cycle × clock (the book value at the scalar clock). And 12 independent chains of
vector FMAs in the kernels' own blocks of lanes (`simd.lanes`, `simd.fma`: 8 float64, 16 float32
with AVX-512) give the vector rate the kernels can reach, in float64 and float32: on CPUs that
lower their clock under 512-bit work (Intel's AVX-512 licences) it is below the book value. The
scalar chains are compiled with numba's SLP vectoriser off and their machine code checked for
packed FMAs (the script stops if it finds one).

    python benchmarks/bench_peak.py [--pipes 2] [--flops-per-cycle 16] [--steps 20000000]

And the machine's own two-thread ceiling at that moment (`two_threads`): the float64 vector chains
on two threads at once against one. It is 2.00x where each thread has a core to itself; a VM's two
vCPUs that share a host core's execution units (with each other or with another tenant's work)
give less, and no kernel's two-thread speed-up can then reach 2x either.

The defaults are Zen 4's (two 256-bit FMA pipes: 8 float64 FMAs, 16 flops per cycle; AMD's
Software Optimization Guide for Family 19h); other CPUs need their own (Intel cores with two
512-bit FMA units: 2 pipes, 32 flops per cycle).
"""

import argparse
import re
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
from numba import njit

from moex.kernels.cpu.simd import JIT, fma, lanes, typed, width


@njit(fastmath={"contract"})
def _chains(n, x):  # pragma: no cover (compiled)
    a = x.copy()  # 16 accumulators, each its own dependency chain
    b, c = 0.999999, 1e-7
    for _ in range(n):
        for j in range(16):
            a[j] = a[j] * b + c  # one fused multiply-add (`contract`)
    return a.sum()


@njit(nogil=True, **JIT)
def _vector_chains(n, x):  # pragma: no cover (compiled)
    """12 chains of one block of lanes each (enough to cover 2 pipes x 4-5 cycles of latency)."""
    LB = width(x)
    a0, a1, a2, a3, a4, a5 = lanes(x), lanes(x), lanes(x), lanes(x), lanes(x), lanes(x)
    a6, a7, a8, a9, a10, a11 = lanes(x), lanes(x), lanes(x), lanes(x), lanes(x), lanes(x)
    for v in range(LB):
        a0[v] = a1[v] = a2[v] = a3[v] = a4[v] = a5[v] = x[v]
        a6[v] = a7[v] = a8[v] = a9[v] = a10[v] = a11[v] = x[v]
    b, c = typed(x, 0.999999), typed(x, 1e-7)
    for _ in range(n):
        for v in range(LB):
            a0[v], a1[v], a2[v] = fma(a0[v], b, c), fma(a1[v], b, c), fma(a2[v], b, c)
            a3[v], a4[v], a5[v] = fma(a3[v], b, c), fma(a4[v], b, c), fma(a5[v], b, c)
            a6[v], a7[v], a8[v] = fma(a6[v], b, c), fma(a7[v], b, c), fma(a8[v], b, c)
            a9[v], a10[v], a11[v] = fma(a9[v], b, c), fma(a10[v], b, c), fma(a11[v], b, c)
    total = typed(x, 0.0)
    for v in range(LB):
        total += a0[v] + a1[v] + a2[v] + a3[v] + a4[v] + a5[v]
        total += a6[v] + a7[v] + a8[v] + a9[v] + a10[v] + a11[v]
    return total


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pipes", type=int, default=2)
    parser.add_argument("--flops-per-cycle", type=int, default=16)
    parser.add_argument("--steps", type=int, default=20_000_000)
    args = parser.parse_args(argv)
    x = np.linspace(0.5, 1.0, 16)
    # compiled with the SLP vectoriser off (numba's default, which `simd` turns on when imported:
    # the 16 chains then ran as two 8-lane vector chains and "measured" a clock near 6 GHz)
    slp, numba.config.SLP_VECTORIZE = numba.config.SLP_VECTORIZE, 0
    try:
        _chains(10, x)
    finally:
        numba.config.SLP_VECTORIZE = slp
    if re.search(r"\bvfn?m(add|sub)\d+p[sd]\b", _chains.inspect_asm(_chains.signatures[0])):
        sys.exit("bench_peak.py: the scalar FMA chains compiled to packed (vector) FMAs; the "
                 "clock they give would be wrong")
    best = min(_timed(args.steps, x) for _ in range(3))
    rate = 16 * 2 * args.steps / best / 1e9
    clock = rate / (args.pipes * 2)
    print(f"scalar FMA chains: {rate:.2f} Gflop/s -> clock {clock:.2f} GHz at {args.pipes} FMA "
          f"pipes; float64 peak {args.flops_per_cycle} x {clock:.2f} = "
          f"{args.flops_per_cycle * clock:.1f} Gflop/s per core")
    for dtype in (np.float64, np.float32):
        x = np.linspace(0.5, 1.0, width(np.dtype(dtype))).astype(dtype)
        _vector_chains(10, x)
        steps = args.steps // 4  # (a quarter of the scalar probe's steps: each is 12 vector FMAs)
        best = min(_timed(steps, x, _vector_chains) for _ in range(3))
        print(f"vector FMA chains, {np.dtype(dtype).name} ({x.size} lanes): "
              f"{12 * 2 * x.size * steps / best / 1e9:.1f} Gflop/s per core "
              f"({12 * steps / best / 1e9:.2f} G vector FMAs per second)")
    # (at least ~3 ms a timing: at the tests' 100 000 steps a timing of 0.08 ms read 0.11x, the
    # scheduler's answer beside another test process's busy threads, not the machine's)
    ceiling = two_threads(max(args.steps // 4, 1_000_000))
    print(f"two threads' vector FMA rate over one thread's: {ceiling:.2f}x")


def two_threads(steps: int = 6_000_000) -> float:
    """The float64 vector chains' rate on two threads at once over their rate on one thread
    (each thread `steps` steps, best of two timings each; ~20 ms a timing at the default on a
    3.6 GHz core): the ceiling this machine gives two threads of compute-bound work now."""
    x = np.linspace(0.5, 1.0, width(np.dtype(np.float64)))
    _vector_chains(10, x)
    one = min(_timed(steps, x, _vector_chains) for _ in range(2))
    with ThreadPoolExecutor(2) as pool:
        # (the pool starts a thread per task while none is idle: as a rule both are running
        # before the timing; a timing that found one starting is not the best of two)
        list(pool.map(time.sleep, (0.0, 0.0)))

        def both() -> float:
            start = time.perf_counter()
            list(pool.map(_vector_chains, (steps, steps), (x, x)))
            return time.perf_counter() - start

        two = min(both() for _ in range(2))
    return 2 * one / two


def _timed(steps: int, x: np.ndarray, chains=_chains) -> float:
    start = time.perf_counter()
    chains(steps, x)
    return time.perf_counter() - start


if __name__ == "__main__":
    main()
