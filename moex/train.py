"""The two training phases (paper Sec. 2.1): experts with gate estimates, then the gating RNN.

Both phases are gradient ascent with momentum (Eqs. 17-18) on R independent runs at once, with
the C code's per-group learning-rate scaling (spec §2.2, §3.3) and the adaptive learning rate of
Sec. 2.1.4, which each run applies to itself: it accepts or retries its own step.
"""

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from tqdm.auto import tqdm

from moex import objectives
from moex.errors import check, check_positive, check_range
from moex.model import ModelConfig, expert_forward, expert_variances, gating_forward

log = logging.getLogger(__name__)

MOMENTUM_FORMS = ("paper", "mregn")


@dataclass
class AdaptiveLRConfig:
    """The adaptive rule of Sec. 2.1.4: while r > max_ratio retry with α·decrease and the whole
    step (momentum part included) shrunk alike; α·increase after a step with r < 1; give up
    (reject the step, zero the momentum) after max_retries."""

    max_ratio: float = 1.1  # r_th
    decrease: float = 0.7  # α_dec
    increase: float = 1.05  # α_inc
    max_retries: int = 1000


@dataclass
class PhaseConfig:
    steps: int = 10000
    learning_rate: float = 0.01  # α̃
    momentum: float = 0.9  # η
    adaptive_lr: bool = True  # Sec. 2.1.4; criterion: the teacher-forced KL (phase 2)
    attraction: bool = False  # the C code's u_0 attraction term (spec §9.5)
    log_every: int = 100


@dataclass
class ExpertPhaseConfig(PhaseConfig):
    steps: int = 30000
    adaptive_lr: bool = False  # spec §2.4; criterion: the mixture MSE E
    gate_prior_std: float = 10.0  # ς of the Brownian prior on β (Eq. 13)


@dataclass
class GatingPhaseConfig(PhaseConfig):
    pass


@dataclass
class TrainConfig:
    """Both phases. `momentum_form`: `paper` keeps the step Δθ = αg + ηΔθ in the momentum
    buffer (Eq. 17); `mregn` keeps the raw gradient sum and scales the whole step by the adaptive
    rate (spec §2.2, §2.4). The two agree whenever the rate is constant."""

    experts: ExpertPhaseConfig = field(default_factory=ExpertPhaseConfig)
    gating: GatingPhaseConfig = field(default_factory=GatingPhaseConfig)
    adaptive: AdaptiveLRConfig = field(default_factory=AdaptiveLRConfig)
    momentum_form: str = "paper"
    checkpoint_every: int = 1000  # steps between resumable checkpoints (0 = only at the end)

    def __post_init__(self):
        check(self.checkpoint_every >= 0,
              f"train.checkpoint_every={self.checkpoint_every} must be >= 0")
        for key, phase in (("train.experts", self.experts), ("train.gating", self.gating)):
            check(phase.steps >= 0, f"{key}.steps={phase.steps} must be >= 0")
            check_positive(f"{key}.learning_rate", phase.learning_rate)
            check_range(f"{key}.momentum", phase.momentum, 0.0, 1.0)
            check(phase.log_every >= 1, f"{key}.log_every={phase.log_every} must be >= 1")
        check_positive("train.experts.gate_prior_std", self.experts.gate_prior_std)
        check(self.adaptive.max_ratio >= 1,
              f"train.adaptive.max_ratio={self.adaptive.max_ratio} must be >= 1")
        check_range("train.adaptive.decrease", self.adaptive.decrease, 0.0, 1.0, low_open=True)
        check(self.adaptive.increase >= 1,
              f"train.adaptive.increase={self.adaptive.increase} must be >= 1")
        check(self.adaptive.max_retries >= 1,
              f"train.adaptive.max_retries={self.adaptive.max_retries} must be >= 1")
        check(self.momentum_form in MOMENTUM_FORMS,
              f"train.momentum_form={self.momentum_form!r}; choose paper or mregn")


Objective = Callable[[dict[str, torch.Tensor]], tuple[torch.Tensor, dict[str, torch.Tensor]]]
Monitor = Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]]


def _per_run(scale: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return scale.view((-1,) + (1,) * (like.dim() - 1))


def _stepper(grads, velocity, rates, momentum, paper_form):
    """The step Δθ as a function of the per-run rate scale and of the share `shrink` of the step
    kept after retries (Eq. 17, or the C code's form that scales its whole buffer)."""
    if paper_form:
        return lambda scale, shrink: {
            k: rates[k] * _per_run(scale, g) * g + momentum * _per_run(shrink, g) * velocity[k]
            for k, g in grads.items()}
    return lambda scale, shrink: {k: rates[k] * _per_run(scale, v) * v
                                  for k, v in velocity.items()}


@dataclass
class Hooks:
    """Side channels of a training phase: tracking, checkpoints, interruption and resuming."""

    monitor: Monitor | None = None  # params -> extra statistics per run (R,)
    monitor_every: int = 0
    save: Callable[[dict], None] | None = None  # receives the resumable state of the phase
    save_every: int = 0
    should_stop: Callable[[], bool] = lambda: False  # e.g. a SIGTERM arrived
    resume: dict | None = None  # a state from `save`, to continue from


class TrainingInterrupted(Exception):
    """Training stopped on request after saving its state; re-run to resume."""


def _finite_per_run(*tensors: torch.Tensor) -> torch.Tensor:
    return torch.stack([t.isfinite().reshape(t.shape[0], -1).all(1) for t in tensors]).all(0)


def _ascend(params: dict[str, torch.Tensor], rates: dict[str, float], objective: Objective,
            criterion: str, steps: int, momentum: float, adaptive: bool,
            rule: TrainConfig, phase: str, log_every: int,
            hooks: Hooks | None = None) -> tuple[dict, list[dict]]:
    """Momentum gradient ascent on `objective` (Eqs. 17-18), optionally with the adaptive rate.

    A run whose objective or gradient becomes non-finite is marked failed and frozen; the other
    runs go on untouched (their tensors never mix). Without the adaptive rate, a step that makes
    a run's parameters non-finite is rolled back and the run marked failed.

    Args:
        params: leaf tensors with a leading run axis R; the dict is updated in place.
        rates: the scaled learning rate of each parameter (spec §2.2).
        objective: params -> (ln L per run (R,), named statistics per run (R,)).
        criterion: statistic whose ratio r drives the adaptive rate (E or the KL).
        rule: supplies the adaptive thresholds and the momentum form.
        hooks: tracking, checkpointing and resuming (see `Hooks`).

    Returns:
        the trained parameters and history rows (one per run every `log_every` steps).
    """
    hooks = hooks or Hooks()
    first = next(iter(params.values()))
    R, device = first.shape[0], first.device
    state = hooks.resume or {
        "step": 0, "rows": [], "lr_scale": torch.ones(R, dtype=first.dtype, device=device),
        "failed": torch.zeros(R, dtype=torch.bool, device=device),
        "velocity": {k: torch.zeros_like(p) for k, p in params.items()}}
    if hooks.resume:
        params.update({k: v.to(device) for k, v in hooks.resume["params"].items()})
    lr_scale, failed = state["lr_scale"].to(device), state["failed"].to(device)
    velocity, rows = {k: v.to(device) for k, v in state["velocity"].items()}, state["rows"]
    paper_form = rule.momentum_form == "paper"
    for step in tqdm(range(state["step"], steps), desc=phase, disable=None, mininterval=1.0,
                     leave=False, initial=state["step"], total=steps):
        if hooks.should_stop() and hooks.save is not None:
            hooks.save({"step": step, "params": params, "velocity": velocity,
                        "lr_scale": lr_scale, "failed": failed, "rows": rows})
            raise TrainingInterrupted(f"{phase} phase stopped at step {step}")
        # ---- gradient of ln L at the current parameters
        leaves = {k: p.detach().requires_grad_(True) for k, p in params.items()}
        log_l, stats = objective(leaves)
        grads = dict(zip(leaves, torch.autograd.grad(log_l.sum(), list(leaves.values())),
                         strict=True))
        with torch.no_grad():
            failed = failed | ~_finite_per_run(log_l, *grads.values())
            grads = {k: torch.where(_per_run(failed, g), 0.0, g) for k, g in grads.items()}
            if not paper_form:  # mregn: the buffer sums raw gradients
                velocity = {k: grads[k] + momentum * velocity[k] for k in params}
            propose = _stepper(grads, velocity, rates, momentum, paper_form)
            shrink = torch.ones_like(lr_scale)
            delta = propose(lr_scale, shrink)
            retries = torch.zeros(R, dtype=torch.long, device=device)
            # ---- adaptive rate: each run shrinks its own rate until r <= r_th (Sec. 2.1.4)
            pending = ~failed if adaptive else torch.zeros_like(failed)
            base = stats[criterion]
            for _ in range(rule.adaptive.max_retries if pending.any() else 0):
                _, trial = objective({k: params[k] + delta[k] for k in params})
                ratio = trial[criterion] / base
                rejected = pending & ~(ratio <= rule.adaptive.max_ratio)  # NaN fails too
                lr_scale = torch.where(pending & (ratio < 1), lr_scale * rule.adaptive.increase,
                                       lr_scale)
                pending = rejected
                if not pending.any():
                    break
                # a retry shrinks the whole step, momentum included: with the momentum term left
                # whole (a strict reading of Sec. 2.1.4) r can stay above r_th for every α, and
                # the rate collapsed to 0.7^1000 in a measured two-Lissajous run
                lr_scale = torch.where(rejected, lr_scale * rule.adaptive.decrease, lr_scale)
                shrink = torch.where(rejected, shrink * rule.adaptive.decrease, shrink)
                retries += rejected
                retry = propose(lr_scale, shrink)
                delta = {k: torch.where(_per_run(rejected, d), retry[k], d)
                         for k, d in delta.items()}
            # ---- update; give up the step of runs still rejected, roll back non-finite runs
            updated = {k: params[k] + delta[k] for k in params}
            if not adaptive:
                failed = failed | ~_finite_per_run(*updated.values())
            frozen = pending | failed
            params.update({k: torch.where(_per_run(frozen, p), params[k], p)
                           for k, p in updated.items()})
            delta = {k: torch.where(_per_run(frozen, d), 0.0, d) for k, d in delta.items()}
            velocity = delta if paper_form else {
                k: torch.where(_per_run(frozen, v), 0.0, v) for k, v in velocity.items()}
            if "tau" in params:
                params["tau"] = params["tau"].clamp_min(1.0)  # ε <= 1 (spec §1.3)
        tracked = hooks.monitor_every > 0 and (step % hooks.monitor_every == 0
                                               or step == steps - 1)
        if tracked:
            stats = {**stats, **hooks.monitor(params)}
        if tracked or step % log_every == 0 or step == steps - 1:
            for r in range(R):
                rows.append({"run": r, "phase": phase, "step": step, "objective": log_l[r].item(),
                             **{k: v[r].item() for k, v in stats.items()},
                             "lr_scale": lr_scale[r].item(), "retries": retries[r].item(),
                             "failed": bool(failed[r])})
        if (step + 1) % max(steps // 10, 1) == 0:  # progress in the log (tqdm only on a tty)
            log.info("%s: step %d/%d, %s mean %.4g over %d runs", phase, step + 1, steps,
                     criterion, base[~failed].mean().item(), int((~failed).sum()))
        if hooks.save is not None and hooks.save_every and (step + 1) % hooks.save_every == 0:
            hooks.save({"step": step + 1, "params": params, "velocity": velocity,
                        "lr_scale": lr_scale, "failed": failed, "rows": rows})
    return {k: p.detach() for k, p in params.items()}, rows


def expert_objective(inputs: torch.Tensor, targets: torch.Tensor, fixed: dict[str, torch.Tensor],
                     model: ModelConfig, cfg: ExpertPhaseConfig) -> Objective:
    """ln L(D, θ) of phase 1 (Eqs. 11-13) as a function of the learned parameters (and β).

    Args:
        inputs, targets: (S, T, D) x_n and y_n = x_{n+τ}.
        fixed: parameters held constant (τ unless time constants are learned).
    """

    def objective(p):
        net = {**p, **fixed}
        outputs, potentials = expert_forward(net, inputs)
        log_ghat = torch.log_softmax(p["beta"], dim=-1)
        log_lik = objectives.mixture_log_likelihood(
            outputs, targets, log_ghat, expert_variances(net, model.sigma_min))
        log_prior = objectives.gate_prior_log_density(p["beta"], cfg.gate_prior_std)
        total = log_lik + log_prior
        if cfg.attraction:
            total = total + objectives.initial_state_attraction(p["u0"], potentials,
                                                                model.sigma_min**2)
        error = objectives.mixture_mse(outputs, targets, log_ghat.exp())
        return total, {"log_likelihood": log_lik, "log_prior": log_prior, "E": error}

    return objective


def gating_objective(gate_targets: torch.Tensor, inputs: torch.Tensor,
                     fixed: dict[str, torch.Tensor], model: ModelConfig,
                     cfg: GatingPhaseConfig) -> Objective:
    """ln L(D^g, θ^g) of phase 2 (Eqs. 14-15) up to ln Z, as a function of the gating parameters.

    Args:
        gate_targets: (R, S, T, K) ĝ_n; inputs: (S, T, D) x_n aligned with ĝ_n.
        fixed: parameters held constant (τ unless time constants are learned).
    """
    R, S, T, K = gate_targets.shape
    targets = gate_targets[:, :, model.delay:]

    def objective(p):
        log_gates, potentials = gating_forward({**p, **fixed}, gate_targets, inputs, model.delay)
        log_lik = objectives.gating_log_likelihood(log_gates, targets)
        kl = objectives.gating_kl(log_gates, targets)
        total = log_lik
        if cfg.attraction:
            total = total + objectives.initial_state_attraction(p["u0"], potentials,
                                                                model.sigma_min**2)
        return total, {"log_likelihood": log_lik, "kl": kl,
                       "E_g": kl / (S * (T - model.delay) * K)}

    return objective


def train_experts(experts: dict[str, torch.Tensor], series: torch.Tensor, model: ModelConfig,
                  cfg: ExpertPhaseConfig, rule: TrainConfig, hooks: Hooks | None = None
                  ) -> tuple[dict[str, torch.Tensor], torch.Tensor, list[dict]]:
    """Phase 1 (Sec. 2.1.2-2.1.3): maximum likelihood of the experts and the gate logits β.

    Args:
        experts: initial parameters from `init_experts` (R runs).
        series: (S, L, D) training series; inputs x_n = series[n], targets series[n + τ].
        model: the model config (delay, σ̄, whether τ = 1/ε is learned).
        cfg: this phase's settings; rule: adaptive thresholds and momentum form.
        hooks: checkpointing, interruption and resuming (see `Hooks`).

    Returns:
        trained experts, gate logits β (R, S, T, K) with T = L - τ (ĝ = softmax β, Eq. 9), and
        history rows with the columns objective, log_likelihood, log_prior, E.
    """
    inputs, targets = series[:, : -model.delay], series[:, model.delay:]
    S, T, D = targets.shape
    R, K = experts["log_sigma"].shape
    fixed = {} if model.learn_time_constants else {"tau": experts["tau"]}
    params = {k: v for k, v in experts.items() if k not in fixed}
    params["beta"] = torch.zeros((R, S, T, K), dtype=series.dtype, device=series.device)
    # spec §2.2: weights, biases, τ and σ at α̃/(T d), initial states at α̃/d, β at α̃
    alpha = cfg.learning_rate
    rates = {k: alpha / (S * T * D) for k in params}
    rates.update(u0=alpha / D, beta=alpha)

    objective = expert_objective(inputs, targets, fixed, model, cfg)
    trained, rows = _ascend(params, rates, objective, "E", cfg.steps, cfg.momentum,
                            cfg.adaptive_lr, rule, "experts", cfg.log_every, hooks)
    beta = trained.pop("beta")
    return {**trained, **fixed}, beta, rows


def train_gating(gating: dict[str, torch.Tensor], gate_targets: torch.Tensor,
                 inputs: torch.Tensor, model: ModelConfig, cfg: GatingPhaseConfig,
                 rule: TrainConfig, hooks: Hooks | None = None
                 ) -> tuple[dict[str, torch.Tensor], list[dict]]:
    """Phase 2 (Sec. 2.1.2-2.1.4): fit the gating RNN to the estimates ĝ by teacher forcing.

    Args:
        gating: initial parameters from `init_gating` (R runs).
        gate_targets: (R, S, T, K) ĝ_n, soft targets from phase 1 (or one-hot symbols).
        inputs: (S, T, D) inputs x_n aligned with ĝ_n (D = 0 for symbolic tasks).
        model: the model config; cfg: this phase's settings; rule: adaptive thresholds.
        hooks: tracking (its monitor sees the full gating parameters), checkpointing, resuming.

    Returns:
        trained gating parameters and history rows with objective, log_likelihood, kl, E_g.
    """
    R, S, T, K = gate_targets.shape
    T_g = T - model.delay
    fixed = {} if model.learn_time_constants else {"tau": gating["tau"]}
    params = {k: v for k, v in gating.items() if k not in fixed}
    # spec §3.3: weights at α̃/(T_g N), initial states at α̃/N
    rates = {k: cfg.learning_rate / (S * T_g * K) for k in params}
    rates["u0"] = cfg.learning_rate / K

    objective = gating_objective(gate_targets, inputs, fixed, model, cfg)
    if hooks is not None and hooks.monitor is not None:
        monitor = hooks.monitor
        hooks = dataclasses.replace(hooks, monitor=lambda p: monitor({**p, **fixed}))
    trained, rows = _ascend(params, rates, objective, "kl", cfg.steps, cfg.momentum,
                            cfg.adaptive_lr, rule, "gating", cfg.log_every, hooks)
    return {**trained, **fixed}, rows
