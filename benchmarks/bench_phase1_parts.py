"""Where a phase-1 step's time goes on the cpu backend: each stage of the compiled step timed
alone, one thread, with its arithmetic per element.

    python benchmarks/bench_phase1_parts.py [--runs 1 30] [--repeats 30] [--dtype float32]

The step (`moex.kernels.cpu.phases.ExpertProblem`) is called stage by stage, as it runs when
there are fewer chunks of runs than threads: the forward pass of every block of lanes (Eqs. 1-3
teacher-forced), the mixture likelihood and its gradient per (run, series) (Eqs. 9-13), BPTT per
block, and the sums per run; plus the staging of parameters into lanes and back (the whole
`value_and_grad` minus its stages) and the training loop around the call (`train_experts`
outside its calls: momentum update, checks, bookkeeping). Stages are timed
round-robin, `--repeats` rounds, and the minimum is kept, so that other load on the machine
(which only ever adds time) disturbs the figures as little as possible. Two-Lissajous sizes:
10 series x 1000 steps, K = 2 experts of M = 10 units, D = 2.
"""

import argparse
import time

import numba
import numpy as np
import torch
from bench_epochs import outside_pairs, trainers

from moex.config import Config
from moex.config.train import ExpertPhaseConfig
from moex.data import load_task
from moex.jobs import run_seeds
from moex.kernels.cpu import phases, threads
from moex.kernels.cpu.phases import _BACKWARD, _FORWARD, _MIXTURE, _RUNS, _expert_items
from moex.model import init_experts
from moex.tasks import task_config


def flops_per_lane_step(M: int, D: int) -> dict[str, int]:
    """Multiply-adds (2 flops each) and transcendental functions per lane and time step."""
    return {"forward": 2 * (M * (D + M) + D * M), "forward tanh": M + D,
            "backward": 2 * (D * M + M * M + M * M + M * D + M)}  # δ_o, δ_c, ∂W_rec, ∂W_in, ∂b


def best_times(R: int, repeats: int, cfg: Config, series: torch.Tensor, steps: int = 100
               ) -> dict[str, float]:
    """The minimum over `repeats` round-robin rounds of each stage's seconds, for R networks."""
    S, L, D = series.shape
    T, K = L - 1, cfg.model.num_experts
    gens = [torch.Generator().manual_seed(s) for s in run_seeds(0, R)]
    params = init_experts(cfg.model, S, D, gens, series.dtype)
    fixed = {"tau": params.pop("tau")}
    params["beta"] = torch.zeros(R, S, T, K, dtype=series.dtype)
    problem = phases.ExpertProblem(series[:, :-1], series[:, 1:], cfg.model, ExpertPhaseConfig(),
                                   num_runs=R)
    grads = {k: torch.zeros_like(v) for k, v in params.items()}
    net = {**params, **fixed}
    active = torch.ones(R, dtype=torch.bool)
    problem.value_and_grad(net, grads, active)  # compile or load, allocate
    p, g, lanes = problem.staging.load(net), problem.staging.outputs(grads), problem.lanes
    floor = float(cfg.model.sigma_min) ** 2
    args = (phases.per_network(p, True), p["u0"], p["log_sigma"], p["beta"], lanes.net,
            tuple(lanes.work), lanes.lane_grads, phases.per_network(g, True), g["u0"],
            g["log_sigma"], g["beta"], problem.inputs, problem.targets, floor,
            float(problem.phase.gate_prior_std), bool(problem.phase.attraction), True,
            np.ones(R, bool), np.ones(R, bool), lanes.block_runs, problem.chunk, lanes.out)
    NB = lanes.net[0].shape[0]
    stages = {
        "forward (Eqs. 1-3)": lambda: threads.over(_expert_items, NB, _FORWARD, *args),
        "mixture (Eqs. 9-13)": lambda: threads.over(_expert_items, R * S, _MIXTURE, *args),
        "backward (BPTT)": lambda: threads.over(_expert_items, NB, _BACKWARD, *args),
        "sums per run": lambda: _expert_items(0, R, _RUNS, *args),
        "whole value_and_grad": lambda: problem.value_and_grad(net, grads, active),
    }
    best = dict.fromkeys(stages, float("inf"))
    for _ in range(repeats):
        for name, call in stages.items():
            start = time.perf_counter()
            call()
            best[name] = min(best[name], time.perf_counter() - start)
    parts = sum(v for k, v in best.items() if k != "whole value_and_grad")
    best["staging and the rest"] = best["whole value_and_grad"] - parts
    best["training loop"] = loop_seconds(R, series.dtype, steps)
    return best


def loop_seconds(R: int, dtype: torch.dtype, steps: int, base: int = 10) -> float:
    """Seconds per fixed-rate epoch of `train_experts` outside its evaluations (`value_and_grad`,
    or the stepper's `evaluate`: the momentum update, checks and bookkeeping): the marginal time
    of `steps` epochs over `base` epochs (so that setting up the problem and the last evaluation
    cancel out), the least of 3 (`bench_epochs.outside_pairs`)."""
    epoch = trainers("lissajous2", R, "cpu", dtype=str(dtype).removeprefix("torch."))[0]
    base = max(1, min(base, steps // 2))
    pairs = outside_pairs(epoch["phase 1, fixed rate"], [(phases.ExpertProblem, "value_and_grad"),
                                                         (phases.ExpertProblem, "evaluate")],
                          steps - base, base, 3)
    return min(outside for _, outside in pairs)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 30])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--steps", type=int, default=100,
                        help="epochs of the timed training (the training loop's row)")
    parser.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    args = parser.parse_args(argv)
    numba.set_num_threads(1)
    torch.set_num_threads(1)
    cfg = Config(task=task_config("lissajous2"))
    series = torch.as_tensor(load_task(cfg).series).to(getattr(torch, args.dtype))
    S, L, D = series.shape
    K, M = cfg.model.num_experts, cfg.model.experts.context_size
    work = flops_per_lane_step(M, D)
    print("| R | stage | ms per network-epoch | ns per lane-step | flops per lane-step | "
          "Gflop/s |\n|---|---|---|---|---|---|")
    for R in args.runs:
        lane_steps = R * K * S * (L - 1)
        for name, seconds in best_times(R, args.repeats, cfg, series, args.steps).items():
            key = {"forward (Eqs. 1-3)": "forward", "backward (BPTT)": "backward"}.get(name)
            flops = work[key] if key else None
            ns = 1e9 * seconds / lane_steps
            rate = f"{flops / ns:.2f}" if flops else ""
            print(f"| {R} | {name} | {1e3 * seconds / R:.3f} | {ns:.2f} | {flops or ''} | "
                  f"{rate} |", flush=True)


if __name__ == "__main__":
    main()
