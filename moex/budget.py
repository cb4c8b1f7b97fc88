"""Memory a command will need, estimated from its config before any work starts, so that an
impossible size (task.length=10**9, num_runs=100000, generate steps=10**10) is refused at once
with the estimate and the limit, instead of failing with MemoryError minutes later."""

import os

from moex.errors import check

GIB = 2**30


def available_bytes() -> int:
    """Memory the system can give this process now (MemAvailable), else the physical memory."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _refuse_beyond(needed: float, what: str, advice: str) -> None:
    limit = available_bytes()
    check(needed <= limit, f"{what} needs about {needed / GIB:.3g} GiB of memory, more than the "
                           f"{limit / GIB:.3g} GiB available; {advice}")


def train_bytes(cfg, num_series: int, length: int, num_features: int) -> float:
    """Peak memory of `moex train`, dominated by the per-step histories of the time loops (kept
    for backpropagation through time), β and its optimiser copies, and the symbol records of
    the evaluation (int16 per sample step)."""
    item = 8 if cfg.precision == "float64" else 4
    R, S, T, D = cfg.num_runs, num_series, length, num_features
    K, M, H = cfg.model.num_experts, cfg.model.experts.context_size, cfg.model.gating.context_size
    data = S * T * (D * 8 + 8) * (2 if cfg.task.num_test_series else 1)
    # per lane-step 3 M + 3 D, and 2 D more: the outputs and ∂L/∂o again by lane (the cpu
    # mixture's rows); then β and its copies
    phase1 = R * K * S * T * (3 * M + 5 * D) * item + R * S * T * K * item * 10 if D else 0
    phase2 = R * S * T * (2 * H + 5 * K + 2 * D) * item
    records = R * cfg.eval.num_samples * cfg.eval.lyapunov_steps * 8 if cfg.eval.enabled else 0
    return data + phase1 + phase2 + records


def check_train(cfg, num_series: int, length: int, num_features: int) -> None:
    _refuse_beyond(train_bytes(cfg, num_series, length, num_features),
                   f"training {cfg.num_runs} runs on {num_series} series x {length} steps",
                   "reduce num_runs, task.num_series, task.length or eval.lyapunov_steps x "
                   "eval.num_samples")


def check_evaluate(cfg) -> None:
    needed = cfg.num_runs * cfg.eval.num_samples * cfg.eval.lyapunov_steps * 8
    _refuse_beyond(needed, f"evaluating {cfg.num_runs} runs x {cfg.eval.num_samples} samples "
                           f"x {cfg.eval.lyapunov_steps} steps",
                   "reduce eval.num_samples or eval.lyapunov_steps")


def check_generate(cfg, steps: int, num_samples: int) -> None:
    item = 8 if cfg.precision == "float64" else 4
    K, H = cfg.model.num_experts, cfg.model.gating.context_size
    per_step = (K + H + 8) * item * 2  # outputs, gates and potentials, chunks and their join
    _refuse_beyond(cfg.num_runs * num_samples * steps * per_step,
                   f"generating {cfg.num_runs} runs x {num_samples} samples x {steps} steps",
                   "reduce steps or num_samples")
