"""The reference backend: the model's equations (`moex.model`, `moex.objectives`) in PyTorch,
gradients by autograd, on any device. Every other backend is tested against it."""

from collections.abc import Callable

import torch

from moex import objectives
from moex.kernels.noise import input_noise
from moex.metrics.lyapunov import reorthonormalise
from moex.metrics.symbols import symbolize_nearest
from moex.model import (
    ClosedLoopRun,
    ClosedLoopState,
    closed_loop_step,
    expert_forward,
    expert_variances,
    gating_forward,
)

Objective = Callable[[dict[str, torch.Tensor]], tuple[torch.Tensor, dict[str, torch.Tensor]]]


def expert_objective(inputs: torch.Tensor, targets: torch.Tensor, model, phase) -> Objective:
    """ln L(D, θ) of phase 1 (Eqs. 11-13) as a function of the experts' parameters and β.

    Args:
        inputs, targets: (S, T, D) x_n and y_n = x_{n+τ}, or (R, S, T, D) per run.
        model: the `ModelConfig`; phase: the `ExpertPhaseConfig`.

    Returns:
        params -> (ln L per run (R,), {log_likelihood, log_prior, E} per run).
    """

    def objective(p):
        outputs, potentials = expert_forward(p, inputs)
        log_ghat = torch.log_softmax(p["beta"], dim=-1)
        log_lik = objectives.mixture_log_likelihood(
            outputs, targets, log_ghat, expert_variances(p, model.sigma_min))
        log_prior = objectives.gate_prior_log_density(p["beta"], phase.gate_prior_std)
        total = log_lik + log_prior
        if phase.attraction:
            total = total + objectives.initial_state_attraction(p["u0"], potentials,
                                                                model.sigma_min**2)
        error = objectives.mixture_mse(outputs, targets, log_ghat.exp())
        return total, {"log_likelihood": log_lik, "log_prior": log_prior, "E": error}

    return objective


def gating_objective(gate_targets: torch.Tensor, inputs: torch.Tensor, model,
                     phase) -> Objective:
    """ln L(D^g, θ^g) of phase 2 (Eqs. 14-15) up to ln Z, as a function of the gating parameters.

    Args:
        gate_targets: (R, S, T, K) ĝ_n; inputs: (S, T, D) x_n aligned with ĝ_n, or (R, S, T, D).
        model: the `ModelConfig`; phase: the `GatingPhaseConfig`.

    Returns:
        params -> (ln L per run (R,), {log_likelihood, kl, E_g} per run).
    """
    R, S, T, K = gate_targets.shape
    targets = gate_targets[:, :, model.delay:]

    def objective(p):
        log_gates, potentials = gating_forward(p, gate_targets, inputs, model.delay)
        log_lik = objectives.gating_log_likelihood(log_gates, targets)
        kl = objectives.gating_kl(log_gates, targets)
        total = log_lik
        if phase.attraction:
            total = total + objectives.initial_state_attraction(p["u0"], potentials,
                                                                model.sigma_min**2)
        return total, {"log_likelihood": log_lik, "kl": kl,
                       "E_g": kl / (S * (T - model.delay) * K)}

    return objective


class _Problem:
    """An objective on numpy parameters: values and autograd gradients, on `device`."""

    trials = 1  # adaptive-rate candidates per call

    def __init__(self, objective: Objective, device: str):
        self.objective, self.device = objective, torch.device(device)

    def resample(self, step: int) -> None:
        """Nothing to draw (see `GatingProblem`)."""

    def stepper(self, buffers, columns, fixed, **settings) -> None:
        """No whole step in one call: the training loop makes its calls."""

    def _tensors(self, params, grads):
        return {k: torch.as_tensor(v, device=self.device).detach().requires_grad_(k in grads)
                for k, v in params.items()}

    def value_and_grad(self, params: dict, grads: dict, active) -> dict:
        """Objective statistics per run (R,); every gradient is written into `grads`."""
        leaves = self._tensors(params, grads)
        total, stats = self.objective(leaves)
        values = torch.autograd.grad(total.sum(), [leaves[k] for k in grads])
        for name, value in zip(grads, values, strict=True):
            grads[name].copy_(value)
        return {n: v.detach() for n, v in {"objective": total, **stats}.items()}

    def value(self, params: dict, active) -> dict:
        """The same statistics without gradients (`active` is ignored: every run is computed)."""
        with torch.no_grad():
            total, stats = self.objective(self._tensors(params, {}))
        return {"objective": total, **stats}


def _on(x, device) -> torch.Tensor:
    """A tensor of the problem's data (a tensor, or an array) on `device`, contiguous."""
    return torch.as_tensor(x).to(device).contiguous()


class ExpertProblem(_Problem):
    """Phase 1 of R runs; see `expert_objective`."""

    def __init__(self, inputs, targets, model, phase, *, num_runs, device="cpu"):
        super().__init__(expert_objective(_on(inputs, device), _on(targets, device), model,
                                          phase), device)


class GatingProblem(_Problem):
    """Phase 2 of R runs; see `gating_objective`. With `phase.input_noise_var`, every
    `resample(step)` adds fresh noise to the inputs x_n (`moex.kernels.noise`)."""

    def __init__(self, gate_targets, inputs, model, phase, *, seeds, device="cpu"):
        self.targets, self.inputs = _on(gate_targets, device), _on(inputs, device)
        self.model, self.phase, self.seeds = model, phase, seeds
        super().__init__(gating_objective(self.targets, self.inputs, model, phase), device)

    def resample(self, step: int) -> None:
        if self.phase.input_noise_var > 0:
            noise = input_noise(self.seeds, step, self.inputs.shape[-3:],
                                self.phase.input_noise_var, self.inputs.dtype)
            self.objective = gating_objective(
                self.targets, self.inputs + torch.from_numpy(noise).to(self.device), self.model,
                self.phase)


def closed_loop(experts: dict[str, torch.Tensor], gating: dict[str, torch.Tensor],
                state: ClosedLoopState, steps: int, *, noise: torch.Tensor | None = None,
                tangents: torch.Tensor | None = None, count: bool = False,
                uniform_gates: bool = False, potentials: bool = True,
                device: str = "cpu") -> ClosedLoopRun:
    """`steps` closed-loop steps (`moex.model.closed_loop_step`) with tangent vectors
    re-orthonormalised by QR after every step (Benettin et al. 1980).

    Args:
        experts, gating, state: as for `closed_loop_step`.
        noise: (R, N, steps, D) noise added to x_m at each step, or None.
        tangents: (R, N, dim, k) tangent vectors in the layout of `state.flat()`, or None.
        device: unused: the reference computes where the tensors of `state` are.
        count: sum ln |R_vv| of every QR step into the returned growth.
        uniform_gates: see `closed_loop_step`.
        potentials: record the gating potentials u^g (else None is returned in their place).
    """
    growth = state.gates.new_zeros(state.gates.shape[:2] + (
        0 if tangents is None else tangents.shape[-1],))
    record = []
    for t in range(steps):
        tg = None if tangents is None else state.like(tangents.movedim(-1, 0))
        step = closed_loop_step(experts, gating, state,
                                noise=None if noise is None else noise[:, :, t], tangents=tg,
                                uniform_gates=uniform_gates)
        state = step.state
        record.append((step.output, step.gates, step.gating_u))
        if tangents is not None:
            tangents, log_r = reorthonormalise(step.tangents.flat(lead=3).movedim(0, -1))
            if count:
                growth += log_r
    y, g, u_g = (torch.stack(column, 2) for column in zip(*record, strict=True))
    return ClosedLoopRun(state, y, g, u_g if potentials else None, tangents, growth)


def nearest_symbols(points: torch.Tensor, prototypes: torch.Tensor,
                    prototype_symbols: torch.Tensor, device: str = "cpu") -> torch.Tensor:
    """`moex.metrics.symbols.symbolize_nearest` itself (computed on the host), on `device`."""
    def host(x):
        return torch.as_tensor(x).detach().cpu().numpy()

    return torch.as_tensor(symbolize_nearest(host(points), host(prototypes),
                                             host(prototype_symbols)), device=device)


def warm_up(precision: str, gating: tuple[int, int, int]) -> None:
    """Nothing to compile (PyTorch's eager operators)."""


def momentum_step(theta, grad, velocity, delta, *, rate, lr_scale, objective, failed,
                  momentum: float, paper_form: bool, apply: bool, tau=None) -> None:
    """The step Δθ of momentum ascent (Eqs. 17-18), in place on the training loop's (R, P)
    buffers: a run whose objective or gradient is not finite joins `failed` (R,) and its gradient
    is zeroed; then Δθ = α ∘ g·s_r + η Δθ_prev in `delta` (paper form: `velocity` holds Δθ_prev)
    or, the C code's form, v ← η v + g and Δθ = α ∘ v·s_r, where α is `rate` (P,) and s_r the
    run's adaptive factor `lr_scale` (R,, float64). With `apply` (a fixed rate) the step is also
    taken (`apply_step`), a run whose θ + Δθ would not be finite joining `failed` first.
    `tau`: the (start, end) columns of τ, kept >= 1. The other backends' versions give these
    bits exactly (each operation rounded as here)."""
    failed |= ~(torch.isfinite(objective) & torch.isfinite(grad).all(1))
    grad.masked_fill_(failed[:, None], 0.0)
    if paper_form:
        kept = velocity * momentum
        torch.mul(grad, rate, out=delta)
        delta *= lr_scale[:, None]
        delta += kept
    else:
        velocity *= momentum
        velocity += grad
        torch.mul(velocity, rate, out=delta)
        delta *= lr_scale[:, None]
    if apply:
        failed |= ~torch.isfinite(theta + delta).all(1)
        apply_step(theta, delta, velocity, failed, paper_form=paper_form, tau=tau)


def adaptive_trial(delta, values, base, pending, lr_scale, *, retries, decrease: float,
                   increase: float, max_ratio: float) -> bool:
    """One trial of the adaptive rate (Sec. 2.1.4) for the runs still `pending` (R,) whose
    candidate θ + Δθ scored `values` (R,) against the current point's `base` (R,): r = values /
    base; a run accepts where r <= r_th = `max_ratio` (NaN does not), its rate factor `lr_scale`
    (R,, float64) × α_inc where r < 1, and leaves `pending`; a run that rejects takes α_dec =
    `decrease` on its rate factor and on its Δθ (its step shrunk whole, momentum included), and
    counts a retry in `retries` (R,). Returns whether a run is still pending. The other backends'
    versions give these bits exactly. (With the momentum term left whole, a strict reading of
    Sec. 2.1.4, r can stay above r_th for every α: the rate collapsed to 0.7^1000 in a measured
    two-Lissajous run.)"""
    dec, inc, one = torch.tensor([decrease, increase, 1.0], dtype=torch.float64,
                                 device=lr_scale.device).unbind(0)
    ratio = values / base
    accepted = ratio <= max_ratio  # NaN fails too
    rejected = pending & ~accepted
    lr_scale.mul_(torch.where(rejected, dec, one))
    took = pending & accepted
    lr_scale.mul_(torch.where(took & (ratio < 1), inc, one))
    retries += rejected
    pending &= ~took
    if not bool(pending.any()):
        return False
    delta.mul_(torch.where(pending, dec, one).to(delta.dtype)[:, None])
    return True


def apply_step(theta, delta, velocity, frozen, *, paper_form: bool, tau=None) -> None:
    """θ += Δθ for the runs not `frozen` (R,) (their Δθ zeroed); the paper form keeps Δθ as the
    next step's momentum, the C code's form zeroes a frozen run's v; τ's columns kept >= 1 (ε <=
    1, as in the C code)."""
    delta.masked_fill_(frozen[:, None], 0.0)
    theta += delta
    if paper_form:
        velocity.copy_(delta)
    else:
        velocity.masked_fill_(frozen[:, None], 0.0)
    if tau is not None:
        theta[:, tau[0]:tau[1]].clamp_(min=1.0)
