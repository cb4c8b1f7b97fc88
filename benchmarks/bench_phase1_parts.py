"""Where a phase-1 (or phase-2) step's time goes on the cpu backend: each stage of the compiled
step timed alone, one thread, with its arithmetic per element.

    python benchmarks/bench_phase1_parts.py [--runs 1 30] [--repeats 30] [--dtype float32]
    python benchmarks/bench_phase1_parts.py --phase 2 --runs 30

The step (`moex.kernels.cpu.phases.ExpertProblem`, which takes chunks of series through the
first three stages in turn) is called stage by stage: the forward pass of every block of lanes
(Eqs. 1-3 teacher-forced), the mixture likelihood and its gradient per (run, series) (Eqs. 9-13),
BPTT per block, and the sums per run; plus the staging of parameters into lanes and back (the whole
`value_and_grad` minus its stages) and the training loop around the call (`train_experts`
outside its calls: momentum update, checks, bookkeeping). Stages are timed
round-robin, `--repeats` rounds, and the minimum is kept, so that other load on the machine
(which only ever adds time) disturbs the figures as little as possible. Two-Lissajous sizes:
10 series x 1000 steps, K = 2 experts of M = 10 units, D = 2.

`--phase 2`: the gating RNN's step (`GatingProblem`, M_g = 15 units, inputs ĝ and x: K + D = 4,
fitted to random ĝ targets), each stage over every block: its forward pass, the softmax
objective and its gradient (Eq. 15), BPTT, the sums per run, and the whole `value_and_grad`.
"""

import argparse
import time

import numba
import numpy as np
import torch
from bench_epochs import gate_targets, outside_pairs, trainers

from moex.config import Config
from moex.config.train import ExpertPhaseConfig, GatingPhaseConfig
from moex.data import load_task
from moex.jobs import run_seeds
from moex.kernels.cpu import phases, threads
from moex.kernels.cpu.phases import _BACKWARD, _FORWARD, _MIXTURE, _RUNS, _expert_items
from moex.kernels.cpu.rnn import backward_pass, forward_pass
from moex.model import init_experts, init_gating
from moex.tasks import task_config


def flops_per_lane_step(M: int, NI: int, NO: int, squash: bool = True) -> dict[str, int]:
    """Multiply-adds (2 flops each) and transcendental functions per lane and time step of an RNN
    of M units, NI inputs and NO outputs (squashed by tanh: the experts)."""
    return {"forward": 2 * (M * (NI + M) + NO * M), "forward tanh": M + NO * squash,
            "backward": 2 * (NO * M + M * M + M * M + M * NI + M)}  # δ_o, δ_c, ∂W_rec, ∂W_in, ∂b


def best_of(stages: dict, repeats: int, rest: bool = True) -> dict[str, float]:
    """The least seconds of each stage's call over `repeats` round-robin rounds, and with `rest`
    the whole `value_and_grad` minus the stages as "staging and the rest"."""
    best = dict.fromkeys(stages, float("inf"))
    for _ in range(repeats):
        for name, call in stages.items():
            start = time.perf_counter()
            call()
            best[name] = min(best[name], time.perf_counter() - start)
    if rest:
        parts = sum(v for k, v in best.items() if k != "whole value_and_grad")
        best["staging and the rest"] = best["whole value_and_grad"] - parts
    return best


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
    p, g = problem.staging.load(net), problem.staging.outputs(grads)
    args = problem.kernel_args(p, g, True, np.ones(R, bool), np.ones(R, bool))
    NB = problem.lanes.net[0].shape[0]
    stages = {
        "forward (Eqs. 1-3)": lambda: threads.over(_expert_items, NB, _FORWARD, *args),
        "mixture (Eqs. 9-13)": lambda: threads.over(_expert_items, R * S, _MIXTURE, *args),
        "backward (BPTT)": lambda: threads.over(_expert_items, NB, _BACKWARD, *args),
        "sums per run": lambda: _expert_items(0, R, _RUNS, *args),
        "whole value_and_grad": lambda: problem.value_and_grad(net, grads, active),
    }
    best = best_of(stages, repeats)
    best["training loop"] = loop_seconds(R, series.dtype, steps)
    return best


def gating_best_times(R: int, repeats: int, cfg: Config, series: torch.Tensor
                      ) -> dict[str, float]:
    """`best_times` for phase 2: the gating RNN's stages, block by block."""
    S, L, D = series.shape
    gens = [torch.Generator().manual_seed(s) for s in run_seeds(0, R)]
    params = init_gating(cfg.model, S, D, gens, series.dtype)
    targets = gate_targets(R, S, L - 1, cfg.model.num_experts)
    problem = phases.GatingProblem(targets.to(series.dtype), series[:, :-1], cfg.model,
                                   GatingPhaseConfig(), seeds=run_seeds(0, R))
    grads = {k: torch.zeros_like(v) for k, v in params.items()}
    active = np.ones(R, bool)
    problem.value_and_grad(params, grads, active)  # compile or load, allocate
    p, g, lanes = problem.staging.load(params), problem.staging.outputs(grads), problem.lanes
    C0, C, Y, U, S1, S2, DY, log_lik = lanes.work
    net, lg, X, Z = lanes.net, lanes.lane_grads, problem.inputs, problem.targets
    args = problem.kernel_args(p, g, True, active, active)
    blocks = range(net[0].shape[0])

    def forward():
        for i in blocks:
            forward_pass(X[i], *(w[i] for w in net), False, C0[i], C[i], Y[i], U[i], S1[i],
                         S2[i], lanes.sizes)

    def objective():
        for i in blocks:
            phases._softmax_objective(Y[i], Z[i], True, DY[i], log_lik[i])

    def backward():
        for i in blocks:
            backward_pass(DY[i], X[i], C0[i], C[i], U[i], net[6][i], net[1][i], net[2][i],
                          net[5][i], *(w[i] for w in lg), lanes.sizes)

    # no "staging and the rest": the whole step takes each block through its stages while its
    # histories are in cache, each stage alone passes over every block (their sum exceeds it)
    return best_of({"forward (Eqs. 5-8)": forward, "softmax objective (Eq. 15)": objective,
                    "backward (BPTT)": backward,
                    "sums per run": lambda: phases.gating_items(0, R, False, *args),
                    "whole value_and_grad": lambda: problem.value_and_grad(params, grads,
                                                                           active)},
                   repeats, rest=False)


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
    parser.add_argument("--phase", type=int, default=1, choices=[1, 2])
    args = parser.parse_args(argv)
    numba.set_num_threads(1)
    torch.set_num_threads(1)
    cfg = Config(task=task_config("lissajous2"))
    series = torch.as_tensor(load_task(cfg).series).to(getattr(torch, args.dtype))
    S, L, D = series.shape
    K, M, M_g = cfg.model.num_experts, cfg.model.experts.context_size, cfg.model.gating.context_size
    work = flops_per_lane_step(M, D, D) if args.phase == 1 else flops_per_lane_step(
        M_g, K + D, K, squash=False)
    print("| R | stage | ms per network-epoch | ns per lane-step | flops per lane-step | "
          "Gflop/s |\n|---|---|---|---|---|---|")
    for R in args.runs:
        lane_steps = R * (K if args.phase == 1 else 1) * S * (L - 1)
        times = best_times(R, args.repeats, cfg, series, args.steps) if args.phase == 1 else \
            gating_best_times(R, args.repeats, cfg, series)
        for name, seconds in times.items():
            flops = work.get(name.split(" (")[0])  # the forward's and backward's rows
            ns = 1e9 * seconds / lane_steps
            rate = f"{flops / ns:.2f}" if flops else ""
            print(f"| {R} | {name} | {1e3 * seconds / R:.3f} | {ns:.2f} | {flops or ''} | "
                  f"{rate} |", flush=True)


if __name__ == "__main__":
    main()
