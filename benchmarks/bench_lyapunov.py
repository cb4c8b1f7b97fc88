"""Closed loop with the Lyapunov tangent at the two-Lissajous sizes: milliseconds per step for
R networks × N samples, extrapolated to the paper's 100000 steps, on any backend.

    python benchmarks/bench_lyapunov.py --runs 30 --samples 50 --steps 2000 --threads 1 2
    python benchmarks/bench_lyapunov.py --runs 90 --samples 50 --backends gpu --device cuda

The parameters and states stay on the CPU as in an evaluation (`moex.closed_loop`), except for
the reference backend on a GPU, which computes where its tensors are.
"""

import argparse
import time

import numba
import torch
from bench_epochs import print_kernels  # (benchmarks/ is the script's folder)

from moex.closed_loop import closed_loop_lyapunov
from moex.config import Config
from moex.jobs import run_seeds
from moex.kernels import get_backend
from moex.model import init_experts, init_gating, random_state


def closed_loop(runs: int, samples: int, threads: int, backend: str, device: str):
    """fn(steps): `closed_loop_lyapunov` with one tangent for runs × samples trajectories (no
    transient), on `backend`, at the two-Lissajous sizes; and the backend
    (`moex.kernels.Backend`)."""
    backend = get_backend(backend, device)
    # the compiled kernels' threads do the parallel work (`moex.kernels.cpu.threads`)
    torch.set_num_threads(1 if backend.name == "cpu" else threads)
    numba.set_num_threads(threads)
    cfg = Config()
    gens = [torch.Generator().manual_seed(s) for s in run_seeds(0, runs)]
    home = device if backend.name == "reference" else "cpu"
    experts = {k: v.to(home) for k, v in init_experts(cfg.model, 10, 2, gens).items()}
    gating = {k: v.to(home) for k, v in init_gating(cfg.model, 10, 2, gens).items()}
    generator = torch.Generator().manual_seed(0)
    state = random_state(experts, gating, samples, num_features=2, delay=1, generator=generator)

    def fn(steps):
        with torch.no_grad():
            closed_loop_lyapunov(experts, gating, state, steps, 0, generator=generator,
                                 backend=backend)

    return fn, backend


def bench(runs: int, samples: int, steps: int, *, threads: int, backend: str, device: str,
          repeats: int = 3) -> float:
    """Seconds per closed-loop step (with one tangent vector) for runs × samples trajectories,
    the best of `repeats` blocks of `steps` steps."""
    fn, chosen = closed_loop(runs, samples, threads, backend, device)
    cuda = chosen.device.startswith("cuda")
    if not chosen.caps.interpreted:  # (Triton's interpreter compiles nothing)
        fn(steps)  # warm-up at the timed length: every chunk size compiled before
    best = float("inf")
    for _ in range(repeats):  # a shared machine's noise only ever adds time
        start = time.perf_counter()
        fn(steps)
        if cuda:
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - start)
    return best / steps


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--samples", type=int, default=50)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--backends", nargs="+", default=["reference", "cpu"])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--kernels", action="store_true",
                        help="then print each compiled Triton kernel's registers and spills")
    args = parser.parse_args()
    print("| networks x samples | device | backend | threads | ms per step | s per 100 000 steps |")
    print("|---|---|---|---|---|---|")
    for backend in args.backends:
        for threads in args.threads:
            per_step = bench(args.runs, args.samples, args.steps, threads=threads,
                             backend=backend, device=args.device, repeats=args.repeats)
            print(f"| {args.runs} x {args.samples} | {args.device} | {backend} | {threads} | "
                  f"{1e3 * per_step:.3f} | {per_step * 100_000:.0f} |", flush=True)
    if args.kernels:
        print_kernels()


if __name__ == "__main__":
    main()
