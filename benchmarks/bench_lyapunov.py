"""Closed loop with the Lyapunov tangent at the two-Lissajous sizes: seconds per step for R
networks × N samples (reference PyTorch code), extrapolated to the paper's 100000 steps.

    python benchmarks/bench_lyapunov.py --runs 30 --samples 50 --steps 2000 --threads 2
"""

import argparse
import time

import torch

from moex.config import Config
from moex.evaluate import EvalConfig, closed_loop_lyapunov, random_state
from moex.model import init_experts, init_gating
from moex.pipeline import run_seeds


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--samples", type=int, default=50)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cfg = Config()
    gens = [torch.Generator().manual_seed(s) for s in run_seeds(0, args.runs)]
    experts = {k: v.to(args.device) for k, v in init_experts(cfg.model, 10, 2, gens).items()}
    gating = {k: v.to(args.device) for k, v in init_gating(cfg.model, 10, 2, gens).items()}
    generator = torch.Generator().manual_seed(0)
    state = random_state(experts, gating, args.samples, 2, 1, generator)
    eval_cfg = EvalConfig(lyapunov_steps=args.steps, transient=0)
    with torch.no_grad():
        start = time.perf_counter()
        closed_loop_lyapunov(experts, gating, state, eval_cfg, generator)
        if args.device == "cuda":
            torch.cuda.synchronize()
        seconds = time.perf_counter() - start
    per_step = seconds / args.steps
    print(f"| {args.runs} x {args.samples} | {args.device} | {args.threads} | "
          f"{1e3 * per_step:.3f} | {per_step * 100_000:.0f} |")


if __name__ == "__main__":
    main()
