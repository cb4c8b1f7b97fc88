"""The reference backend: the model's equations (`moex.model`, `moex.objectives`) in PyTorch,
gradients by autograd, on any device. Every other backend is tested against it."""

from collections.abc import Callable

import numpy as np
import torch

from moex import objectives
from moex.metrics.symbols import symbolize_nearest
from moex.model import closed_loop_run, expert_forward, expert_variances, gating_forward

Objective = Callable[[dict[str, torch.Tensor]], tuple[torch.Tensor, dict[str, torch.Tensor]]]


def expert_objective(inputs: torch.Tensor, targets: torch.Tensor, model, phase) -> Objective:
    """ln L(D, θ) of phase 1 (Eqs. 11-13) as a function of the experts' parameters and β.

    Args:
        inputs, targets: (S, T, D) x_n and y_n = x_{n+τ}.
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
        gate_targets: (R, S, T, K) ĝ_n; inputs: (S, T, D) x_n aligned with ĝ_n.
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

    def __init__(self, objective: Objective, device: str):
        self.objective, self.device = objective, torch.device(device)

    def _tensors(self, params, grads):
        return {k: torch.from_numpy(np.ascontiguousarray(v)).to(self.device).requires_grad_(
            k in grads) for k, v in params.items()}

    def value_and_grad(self, params: dict, grads: dict, active: np.ndarray) -> dict:
        """Objective statistics per run (R,); every gradient is written into `grads`."""
        leaves = self._tensors(params, grads)
        total, stats = self.objective(leaves)
        values = torch.autograd.grad(total.sum(), [leaves[k] for k in grads])
        for name, value in zip(grads, values, strict=True):
            grads[name][...] = value.cpu().numpy()
        return {n: v.detach().cpu().numpy() for n, v in {"objective": total, **stats}.items()}

    def value(self, params: dict, active: np.ndarray) -> dict:
        """The same statistics without gradients (`active` is ignored: every run is computed)."""
        with torch.no_grad():
            total, stats = self.objective(self._tensors(params, {}))
        return {n: v.cpu().numpy() for n, v in {"objective": total, **stats}.items()}


class ExpertProblem(_Problem):
    """Phase 1 of R runs; see `expert_objective`."""

    def __init__(self, inputs, targets, model, phase, num_runs, device="cpu"):
        def tensor(x):
            return torch.from_numpy(np.ascontiguousarray(x)).to(device)

        super().__init__(expert_objective(tensor(inputs), tensor(targets), model, phase), device)


class GatingProblem(_Problem):
    """Phase 2 of R runs; see `gating_objective`."""

    def __init__(self, gate_targets, inputs, model, phase, device="cpu"):
        def tensor(x):
            return torch.from_numpy(np.ascontiguousarray(x)).to(device)

        super().__init__(gating_objective(tensor(gate_targets), tensor(inputs), model, phase),
                         device)


closed_loop = closed_loop_run
nearest_symbols = symbolize_nearest
