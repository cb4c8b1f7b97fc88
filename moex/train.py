"""The two training phases (paper Sec. 2.1): experts with gate estimates, then the gating RNN.

Both phases are gradient ascent with momentum (Eqs. 17-18) on R independent runs at once, with
the C code's per-group learning-rate scaling and the adaptive learning rate of
Sec. 2.1.4, which each run applies to itself: it accepts or retries its own step. The objective
and its gradients come from a backend (`moex.kernels`); the loop here is the same for all.
"""

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from moex import progress
from moex.config.model import ModelConfig
from moex.config.train import ExpertPhaseConfig, GatingPhaseConfig, TrainConfig
from moex.errors import Interrupted, never
from moex.kernels import Backend
from moex.model import gate_estimates
from moex.tasks import Dataset

log = logging.getLogger(__name__)

Monitor = Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]]


@dataclass
class Hooks:
    """Side channels of a training phase: tracking, checkpoints, interruption and resuming."""

    monitor: Monitor | None = None  # params -> extra statistics per run (R,)
    monitor_every: int = 0
    monitor_from: int = 0  # the first step the monitor sees
    save: Callable[[dict], None] | None = None  # receives the resumable state of the phase
    save_every: int = 0
    stop: Callable[[], bool] = never  # e.g. a SIGTERM arrived (`moex.stop.StopRequest`)
    resume: dict | None = None  # a state from `save`, to continue from


class TrainingInterrupted(Interrupted):
    """Training stopped on request after saving its state; re-run to resume."""


class _Flat:
    """Named parameter groups of R runs side by side in one (R, P) tensor on the backend's
    device, so that a momentum step is a few in-place passes over preallocated memory."""

    def __init__(self, params: dict[str, torch.Tensor], device: torch.device):
        self.shapes = {k: v.shape[1:] for k, v in params.items()}
        sizes = [int(np.prod(s)) for s in self.shapes.values()]
        self.bounds = dict(zip(self.shapes, zip(np.cumsum([0] + sizes[:-1]).tolist(),
                                                np.cumsum(sizes).tolist(), strict=True),
                               strict=True))
        first = next(iter(params.values()))
        self.num_runs, self.size, self.dtype = first.shape[0], sum(sizes), first.dtype
        self.device = device

    def zeros(self, *copies: int) -> torch.Tensor:
        """(*copies, R, P) zeros."""
        return torch.zeros((*copies, self.num_runs, self.size), dtype=self.dtype,
                           device=self.device)

    def views(self, flat: torch.Tensor) -> dict[str, torch.Tensor]:
        return {k: flat[:, a:b].view((-1,) + self.shapes[k]) for k, (a, b) in
                self.bounds.items()}

    def per_entry(self, values: dict[str, float]) -> torch.Tensor:
        """(P,): each group's value repeated over its entries."""
        out = torch.empty(self.size, dtype=self.dtype, device=self.device)
        for k, (a, b) in self.bounds.items():
            out[a:b] = values[k]
        return out


def _host(arrays: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.detach().cpu().clone() for k, v in arrays.items()}


def _ascend(params: dict[str, torch.Tensor], fixed: dict[str, torch.Tensor],
            rates: dict[str, float], problem, *, backend: Backend, criterion: str, steps: int,
            momentum: float, adaptive: bool, rule: TrainConfig, phase: str, log_every: int,
            hooks: Hooks | None = None, error: str | None = None
            ) -> tuple[dict[str, torch.Tensor], list[dict]]:
    """Momentum gradient ascent (Eqs. 17-18), optionally with the adaptive rate of Sec. 2.1.4.

    Parameters, gradients, momentum and the candidate points of the adaptive retry live in
    preallocated (R, P) tensors on the problem's device (`problem.device`); a step is one
    `problem.value_and_grad` call, in-place updates, and with the adaptive rate one
    `problem.value` call per trial, or one `problem.value_of_candidates` call per `trials`
    trials where the backend evaluates several at once (gpu); the update is the backend's
    `momentum_step` (one compiled call or launch on cpu and gpu) and a trial of one candidate is
    judged by its `adaptive_trial` (one compiled call on cpu). The host reads one flag per such
    call and per-run statistics when it logs. A run whose objective or gradient becomes
    non-finite is marked failed and frozen; the other runs go on untouched. Without the adaptive
    rate, a step that makes a run's parameters non-finite is rolled back and the run marked failed.

    Args:
        params: learned parameters (R, ...) per group; fixed: the others (e.g. τ).
        rates: the scaled learning rate of each group (C code).
        problem: a backend's `ExpertProblem` or `GatingProblem` (`moex.kernels.Problem`).
        backend: whose `momentum_step` and `apply_step` update the buffers.
        criterion: statistic whose ratio r drives the adaptive rate (E or the KL).
        rule: supplies the adaptive thresholds and the momentum form.
        hooks: tracking, checkpointing and resuming (see `Hooks`).
        error: the statistic the progress lines of the log report (default: the criterion).

    Returns:
        the trained parameters (on the host) and history rows (one per run every `log_every`
        steps, and a last one at step `steps` with the statistics of the trained parameters).
    """
    hooks = hooks or Hooks()
    device = torch.device(problem.device)
    layout = _Flat(params, device)
    R = layout.num_runs
    batch = problem.trials if adaptive else 1  # candidate steps per call
    paper_form = rule.momentum_form == "paper"
    theta, grad, delta = (layout.zeros() for _ in range(3))
    # the paper form's momentum term is the last step Δθ itself (Eq. 17): one buffer holds
    # both, each backend reading a run's Δθ_prev before it writes the new Δθ (a pass over the
    # (R, P) buffer fewer in each of a step's two updates, and the copy of Δθ gone)
    velocity = delta if paper_form else layout.zeros()
    candidates = layout.zeros(batch)  # the first is also scratch space
    shrunk = layout.zeros(batch + 1) if batch > 1 else None  # Δθ·α_dec^j, j <= batch
    scratch, shrinks = candidates.unbind(0)[0], () if shrunk is None else shrunk.unbind(0)
    views, grads, moments = layout.views(theta), layout.views(grad), layout.views(velocity)
    fixed = {name: v.to(device) for name, v in fixed.items()}
    net = {**views, **fixed}
    candidate_net = {**layout.views(candidates.view(batch * R, -1)),
                     **{name: v.repeat(batch, *[1] * (v.dim() - 1)) for name, v in fixed.items()}}
    evaluate = problem.value if batch == 1 else (
        lambda params, _: problem.value_of_candidates(params))
    for k, v in params.items():
        views[k].copy_(v)
    lr_scale = torch.ones(R, dtype=torch.float64, device=device)
    # the adaptive rule's factors α_dec, α_inc, 1 (float64: exact), and α_dec for Δθ
    dec, inc, one = torch.tensor([rule.adaptive.decrease, rule.adaptive.increase, 1.0],
                                 dtype=torch.float64, device=device).unbind(0)
    decrease = dec.to(layout.dtype)
    failed, rows, start = torch.zeros(R, dtype=torch.bool, device=device), [], 0
    if hooks.resume:
        state = hooks.resume
        for k in params:
            views[k].copy_(state["params"][k])
            moments[k].copy_(state["velocity"][k])
        lr_scale.copy_(state["lr_scale"])
        failed.copy_(state["failed"])
        rows, start = state["rows"], state["step"]
    rate = layout.per_entry(rates)
    tau = layout.bounds.get("tau")  # (its columns: ε <= 1 kept, as in the C code)
    no_retries, tries = (torch.zeros(R, dtype=torch.int64, device=device) for _ in range(2))

    def save(step):
        hooks.save({"step": step, "params": _host(views), "velocity": _host(moments),
                    "lr_scale": lr_scale.cpu().clone(), "failed": failed.cpu().clone(),
                    "rows": rows})

    def statistics(values: dict) -> dict[str, torch.Tensor]:
        return {k: torch.as_tensor(v, device=device) for k, v in values.items()}

    # the whole step as one compiled call, where the backend has one for this problem (cpu)
    whole = problem.stepper(
        dict(theta=theta, grad=grad, velocity=velocity, delta=delta, scratch=scratch),
        layout.bounds, fixed, rate=rate, lr_scale=lr_scale, failed=failed, retries=tries,
        criterion=criterion, momentum=momentum, paper_form=paper_form, adaptive=adaptive,
        max_retries=rule.adaptive.max_retries, decrease=rule.adaptive.decrease,
        increase=rule.adaptive.increase, max_ratio=rule.adaptive.max_ratio,
        tau=tau, steps=steps - start) if batch == 1 else None

    def calls() -> tuple[dict, torch.Tensor]:
        """One step as separate calls: the statistics at θ and the retries per run."""
        stats = statistics(problem.value_and_grad(net, grads, ~failed))
        # ---- the step Δθ (Eq. 17 keeps Δθ in the buffer, the C code the sum of raw gradients),
        # failed runs frozen; at a fixed rate also taken (non-finite results rolled back)
        backend.momentum_step(theta, grad, velocity, delta, rate=rate, lr_scale=lr_scale,
                              objective=stats["objective"], failed=failed, momentum=momentum,
                              paper_form=paper_form, apply=not adaptive, tau=tau)
        retries = no_retries
        # ---- adaptive rate: each run shrinks its own step until r <= r_th (Sec. 2.1.4). The
        # backend evaluates k candidate steps Δθ·α_dec^j (j < k) per call, each run takes its
        # first accepted one, as trying them one by one would; the host reads one flag per
        # call (whether any run rejected all k), nothing else
        pending = ~failed if adaptive else None
        base, left = stats[criterion], rule.adaptive.max_retries if adaptive else 0
        if left > 0:
            retries = tries.zero_()  # (read into the history at once when logged)
        while left > 0:
            n = min(batch, left)
            torch.add(theta, delta, out=scratch)
            if n == 1:  # one candidate per run: the backend judges it (one call on cpu)
                values = evaluate(candidate_net, pending)[criterion].view(batch, R)[0]
                left -= 1
                if not backend.adaptive_trial(
                        delta, values, base, pending, lr_scale, retries=retries,
                        decrease=rule.adaptive.decrease, increase=rule.adaptive.increase,
                        max_ratio=rule.adaptive.max_ratio):
                    break
                continue
            # k candidates: the shrunk steps Δθ·α_dec^j, multiplied in the order one by one would
            shrunk[0].copy_(delta)
            for j in range(n):
                torch.mul(shrinks[j], decrease, out=shrinks[j + 1])
            torch.add(theta, shrunk[1:n], out=candidates[1:n])
            values = evaluate(candidate_net, pending)[criterion].view(batch, R)[:n]
            ratio = values / base
            accepted = ratio <= rule.adaptive.max_ratio  # NaN fails too
            first = torch.where(pending, torch.where(
                accepted.any(0), accepted.to(torch.uint8).argmax(0), n), 0)  # (argmax: the first)
            for j in range(n):  # α·α_dec per rejection, in the order one by one would take
                lr_scale.mul_(torch.where(first > j, dec, one))
            took = pending & (first < n)
            lr_scale.mul_(torch.where(took & (ratio.gather(0, first.clamp(max=n - 1)[None])[0]
                                              < 1), inc, one))
            # each run's accepted step, or Δθ·α_dec^n
            delta.copy_(shrunk.gather(0, first.view(1, R, 1).expand(1, R, layout.size))[0])
            retries += first
            pending &= ~took
            left -= n
            if not bool(pending.any()):
                break
        if adaptive:  # ---- the update; runs still rejected give up their step
            backend.apply_step(theta, delta, velocity, pending | failed, paper_form=paper_form,
                               tau=tau)
        return stats, retries

    for step in progress.steps(start, steps, desc=phase):
        if hooks.stop() and hooks.save is not None:
            save(step)
            raise TrainingInterrupted(f"{phase} phase stopped at step {step}")
        # ---- gradient of ln L at the current parameters (a noisy objective draws its noise),
        # the step, the adaptive rate's trials, the update
        problem.resample(step)
        if whole is None:
            stats, retries = calls()
        else:
            whole()
            stats = None  # (read from the stepper only where this step reports them)
            retries = tries if adaptive and rule.adaptive.max_retries > 0 else no_retries
        tracked = hooks.monitor_every > 0 and step >= hooks.monitor_from and (
            step % hooks.monitor_every == 0 or step == steps - 1)
        told = start < step < steps - 1 and (step + 1) % max(steps // 10, 1) == 0  # a log line
        if stats is None and (tracked or told or step % log_every == 0):
            stats = statistics(whole.statistics())
        if tracked:
            stats = {**stats, **statistics(hooks.monitor(_host(net)))}
        if tracked or step % log_every == 0:  # (the last row: the trained parameters, below)
            rows += _rows(phase, step, stats, lr_scale=lr_scale, retries=retries, failed=failed)
        if step == start:  # the rate leaves out the first step, which compiles the kernels
            started = time.perf_counter()
        elif told:  # progress in the log
            speed = (step - start) / (time.perf_counter() - started)  # steps per second
            log.info("%s: step %d/%d, %s mean %.4g over %s; %.1f steps/s, %s left",
                     phase, step + 1, steps, error or criterion,
                     stats[error or criterion][~failed].mean().item(),
                     progress.counted(int((~failed).sum()), "run"), speed,
                     _duration((steps - step - 1) / speed), extra={"progress": True})
        if hooks.save is not None and hooks.save_every and (step + 1) % hooks.save_every == 0:
            save(step + 1)
    final = statistics(problem.value(net, ~failed))  # the trained parameters, as evaluation sees
    for values in final.values():
        values[failed] = float("nan")  # not computed for frozen runs
    rows += _rows(phase, steps, final, lr_scale=lr_scale, retries=torch.zeros_like(lr_scale),
                  failed=failed)
    if steps > start:  # the last line states the trained parameters' value, as history.csv
        values = final[error or criterion][~failed]
        if len(values):
            log.info("%s: step %d/%d (final), %s mean %.4g (min %.3g, max %.3g) over %s",
                     phase, steps, steps, error or criterion, values.mean().item(),
                     values.min().item(), values.max().item(), progress.counted(len(values), "run"))
    return _host(views), rows


def _duration(seconds: float) -> str:
    """h:mm:ss."""
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def _rows(phase, step, stats, *, lr_scale, retries, failed) -> list[dict]:
    """One history row per run, read from the device at once."""
    values = {k: v.tolist() for k, v in stats.items()}
    lr, tries, bad = lr_scale.tolist(), retries.tolist(), failed.tolist()
    return [{"run": r, "phase": phase, "step": step, **{k: float(v[r]) for k, v in
                                                        values.items()},
             "lr_scale": float(lr[r]), "retries": int(tries[r]), "failed": bool(bad[r])}
            for r in range(len(lr))]


def train_experts(experts: dict[str, torch.Tensor], series: torch.Tensor, model: ModelConfig,
                  cfg: ExpertPhaseConfig, rule: TrainConfig, *, backend: Backend,
                  hooks: Hooks | None = None
                  ) -> tuple[dict[str, torch.Tensor], torch.Tensor, list[dict]]:
    """Phase 1 (Sec. 2.1.2-2.1.3): maximum likelihood of the experts and the gate logits β.

    Args:
        experts: initial parameters from `init_experts` (R runs).
        series: (S, L, D) training series; inputs x_n = series[n], targets series[n + τ]; or
            (R, S, L, D) when every run has series of its own (packed jobs).
        model: the model config (delay, σ̄, whether τ = 1/ε is learned).
        cfg: this phase's settings; rule: adaptive thresholds and momentum form.
        hooks: checkpointing, interruption and resuming (see `Hooks`).
        backend: where the time loops run (`moex.kernels.get_backend`).

    Returns:
        trained experts, gate logits β (R, S, T, K) with T = L - τ (ĝ = softmax β, Eq. 9), and
        history rows with the columns objective, log_likelihood, log_prior, E.
    """
    data = series.detach()
    inputs, targets = data[..., : -model.delay, :], data[..., model.delay:, :]
    S, T, D = targets.shape[-3:]
    R, K = experts["log_sigma"].shape
    params = {k: v.detach().cpu() for k, v in experts.items()}
    fixed = {} if model.learn_time_constants else {"tau": params.pop("tau")}
    params["beta"] = torch.zeros((R, S, T, K), dtype=series.dtype)
    # the C code's scaling: weights, biases, τ and σ at α̃/(T d), initial states at α̃/d, β at α̃
    alpha = cfg.learning_rate
    rates = {k: alpha / (S * T * D) for k in params}
    rates.update(u0=alpha / D, beta=alpha)
    problem = backend.expert_problem(inputs, targets, model, cfg, R)
    trained, rows = _ascend(params, fixed, rates, problem, backend=backend, criterion="E",
                            steps=cfg.steps, momentum=cfg.momentum, adaptive=cfg.adaptive_lr,
                            rule=rule, phase="experts", log_every=cfg.log_every, hooks=hooks,
                            error="E")
    beta = trained.pop("beta")
    return {**trained, **fixed}, beta, rows


def phase2_targets(beta: torch.Tensor | None, dataset: Dataset, num_runs: int,
                   dtype: torch.dtype, temperature: float = 1.0) -> torch.Tensor:
    """The targets the gating RNN is fitted to, (R, S, T, K): ĝ from β (Eq. 9, at
    `temperature`), or the one-hot symbols of a task without experts (Sec. 3.1)."""
    if beta is None:
        return torch.as_tensor(dataset.gate_targets, dtype=dtype).expand(num_runs, -1, -1, -1)
    return gate_estimates(beta, temperature)


def train_gating(gating: dict[str, torch.Tensor], gate_targets: torch.Tensor,
                 inputs: torch.Tensor, model: ModelConfig, cfg: GatingPhaseConfig, *,
                 rule: TrainConfig, backend: Backend, hooks: Hooks | None = None,
                 seeds: list[int] | None = None) -> tuple[dict[str, torch.Tensor], list[dict]]:
    """Phase 2 (Sec. 2.1.2-2.1.4): fit the gating RNN to the estimates ĝ by teacher forcing.

    Args:
        gating: initial parameters from `init_gating` (R runs).
        gate_targets: (R, S, T, K) ĝ_n, soft targets from phase 1 (or one-hot symbols).
        inputs: (S, T, D) inputs x_n aligned with ĝ_n (D = 0 for symbolic tasks), or
            (R, S, T, D) per run.
        model: the model config; cfg: this phase's settings; rule: adaptive thresholds.
        hooks: tracking (its monitor sees the full gating parameters), checkpointing, resuming.
        backend: where the time loops run (`moex.kernels.get_backend`).
        seeds: one per run, for the input noise of `cfg.input_noise_var` (default 0, 1, ...).

    Returns:
        trained gating parameters and history rows with objective, log_likelihood, kl, E_g.
    """
    R, S, T, K = gate_targets.shape
    T_g = T - model.delay
    params = {k: v.detach().cpu() for k, v in gating.items()}
    fixed = {} if model.learn_time_constants else {"tau": params.pop("tau")}
    # the C code's scaling: weights at α̃/(T_g N), initial states at α̃/N
    rates = {k: cfg.learning_rate / (S * T_g * K) for k in params}
    rates["u0"] = cfg.learning_rate / K
    problem = backend.gating_problem(gate_targets.detach(), inputs.detach(), model, cfg,
                                     list(range(R)) if seeds is None else seeds)
    trained, rows = _ascend(params, fixed, rates, problem, backend=backend, criterion="kl",
                            steps=cfg.steps, momentum=cfg.momentum, adaptive=cfg.adaptive_lr,
                            rule=rule, phase="gating", log_every=cfg.log_every, hooks=hooks,
                            error="E_g")
    return {**trained, **fixed}, rows
