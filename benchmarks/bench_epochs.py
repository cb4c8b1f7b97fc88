"""Phase-1 and phase-2 epochs per second at the two-Lissajous sizes (10 series x 1000 steps,
N = 2, M = 10, M_g = 15), reference (PyTorch autograd) vs compiled (numba) backend.

    python benchmarks/bench_epochs.py --runs 1 30 --threads 1 2 --steps 5
"""

import argparse
import time

import torch

from moex.config import Config
from moex.model import init_experts, init_gating, set_backend
from moex.pipeline import load_task, run_seeds
from moex.train import train_experts, train_gating


def _time(fn, steps, repeats=3):
    """Seconds per epoch: the best of `repeats` blocks of `steps` epochs (a shared machine's
    noise only ever adds time)."""
    fn(1)  # warm-up (numba compilation, allocator)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn(steps)
        best = min(best, (time.perf_counter() - start) / steps)
    return best


def bench(runs: int, backend: str, threads: int, steps: int, torch_threads: int = 0) -> dict:
    torch.set_num_threads(torch_threads or threads)
    try:
        import numba
        numba.set_num_threads(threads)
    except ImportError:
        pass
    set_backend(backend)
    cfg = Config()
    cfg.train.experts.adaptive_lr = True  # the target: phase 1 with the adaptive rate
    series = torch.as_tensor(load_task(cfg).series)
    gens = [torch.Generator().manual_seed(s) for s in run_seeds(0, runs)]
    experts = init_experts(cfg.model, 10, 2, gens)
    gating = init_gating(cfg.model, 10, 2, gens)
    ghat = torch.softmax(torch.randn(runs, 10, 999, 2, generator=torch.Generator().manual_seed(0)),
                         -1)

    def phase1(n):
        cfg.train.experts.steps = n
        train_experts(experts, series, cfg.model, cfg.train.experts, cfg.train)

    def phase2(n):
        cfg.train.gating.steps = n
        train_gating(gating, ghat, series[:, :-1], cfg.model, cfg.train.gating, cfg.train)

    return {"runs": runs, "backend": backend, "threads": threads,
            "phase1_ms": 1e3 * _time(phase1, steps), "phase2_ms": 1e3 * _time(phase2, steps)}


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 30])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--backends", nargs="+", default=["reference", "compiled"])
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--torch-threads", type=int, default=0,
                        help="PyTorch's own threads (default: as many as --threads)")
    args = parser.parse_args()
    print("| runs | backend | threads | phase-1 epoch (ms) | phase-2 epoch (ms) |")
    print("|---|---|---|---|---|")
    for runs in args.runs:
        for backend in args.backends:
            for threads in args.threads:
                r = bench(runs, backend, threads, args.steps, args.torch_threads)
                print(f"| {r['runs']} | {r['backend']} | {r['threads']} | "
                      f"{r['phase1_ms']:.1f} | {r['phase2_ms']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
