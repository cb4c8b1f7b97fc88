"""The two training phases of the GPU backend (Triton): a step is the forward kernel of
`moex.kernels.gpu.rnn` over every lane of every run (`moex.kernels.gpu.lanes`), the phase's
objective on the outputs o_t and its gradient ∂L/∂o_t — the reference's own functions
(`moex.objectives`) under autograd, with no time loop — then the backward kernel and a sum of the
per-lane gradients over each network's lanes. Parameters, gradients and the optimiser state stay
on the device; the per-run statistics (R values) are device tensors the host reads when it logs.
"""

import numpy as np
import torch

from moex import objectives
from moex.kernels.gpu.lanes import Net, weights
from moex.kernels.noise import input_noise


def _attraction(u0, sums, count, floor):
    """The C code's u_0 attraction from Σu and Σu² over {u_0..u_T} (statistics held constant),
    per run; u0 and sums are (R, lanes of a run, H)."""
    mean = sums[..., 0, :] / count
    var = (sums[..., 1, :] / count - mean * mean).clamp_min(floor)
    return (-(u0 - mean).square() / (2 * var)).flatten(1).sum(1)


class _Problem:
    """value_and_grad / value on device tensors; subclasses compute the objective from O."""

    STATS: tuple

    def __init__(self, device):
        self.device = torch.device(device)

    def resample(self, step: int) -> None:
        """Nothing to draw (see `GatingProblem`)."""

    def value_and_grad(self, params: dict, grads: dict, active) -> dict:
        """Objective statistics per run (R,); every gradient of an active run is written into
        `grads` (the others keep theirs)."""
        return self._call(params, grads, torch.as_tensor(active, device=self.device))

    def value(self, params: dict, active) -> dict:
        """The same statistics without gradients (every run is computed)."""
        with torch.no_grad():
            return self._call(params, None, None)

    @staticmethod
    def _write(grads, name, value, active):
        target = grads[name]
        mask = active.view((-1,) + (1,) * (target.dim() - 1))
        target.copy_(torch.where(mask, value.to(target.dtype), target))


class ExpertProblem(_Problem):
    """Phase 1 of R runs (Eqs. 9-13). Lane (r·K + k)·S + s runs expert k of run r on series s.

    Args:
        inputs, targets: (S, T, D) x_n and y_n = x_{n+τ}, or (R, S, T, D) per run.
        model: the `ModelConfig`; phase: the `ExpertPhaseConfig`; num_runs: R.
    """

    STATS = ("objective", "log_likelihood", "log_prior", "E")

    def __init__(self, inputs, targets, model, phase, num_runs, device="cuda"):
        super().__init__(device)
        S, T, D = targets.shape[-3:]
        R, K, M = num_runs, model.num_experts, model.experts.context_size
        dtype = getattr(torch, str(np.dtype(inputs.dtype)))
        self.shape, self.model, self.phase = (R, S, T, K, D, M), model, phase
        own = np.ndim(inputs) == 4  # data per run: X holds R·S series
        self.X = torch.as_tensor(np.ascontiguousarray(inputs), device=self.device).to(
            dtype).reshape(-1, T, D)
        self.targets = torch.as_tensor(np.ascontiguousarray(targets), device=self.device).to(dtype)
        lane = np.arange(R * K * S)
        r, k, s = lane // (K * S), lane // S % K, lane % S
        self.rnn = Net(len(lane), T, D, M, D, r * K + k, r * S * own + s, (r * S + s) * K + k,
                        model.learn_time_constants, phase.attraction, dtype, self.device)

    def _call(self, params, grads, active):
        R, S, T, K, D, M = self.shape
        want = grads is not None
        w, u0 = weights(params, 2), params["u0"].contiguous()
        out = self.rnn.forward(self.X, w, u0, want)
        with torch.enable_grad() if want else torch.no_grad():
            o = out.view(R, K, S, T, D).detach().requires_grad_(want)
            beta = params["beta"].detach().requires_grad_(want)
            log_sigma = params["log_sigma"].detach().requires_grad_(want)
            u0_leaf = params["u0"].detach().requires_grad_(want and self.phase.attraction)
            outputs = torch.tanh(o).permute(0, 2, 3, 1, 4)  # (R, S, T, K, D)
            log_ghat = torch.log_softmax(beta, -1)
            variances = torch.exp(2 * log_sigma) + self.model.sigma_min ** 2
            log_lik = objectives.mixture_log_likelihood(outputs, self.targets, log_ghat,
                                                        variances)
            log_prior = objectives.gate_prior_log_density(beta, self.phase.gate_prior_std)
            total = log_lik + log_prior
            if self.phase.attraction:
                sums = self.rnn.S.view(R, K, S, 2, M).transpose(1, 2).reshape(R, S * K, 2, M)
                total = total + _attraction(u0_leaf.reshape(R, S * K, M), sums, T + 1,
                                            self.model.sigma_min ** 2)
            error = objectives.mixture_mse(outputs, self.targets, log_ghat.exp())
            stats = {"objective": total, "log_likelihood": log_lik, "log_prior": log_prior,
                     "E": error}
            if want:
                leaves = [o, beta, log_sigma] + ([u0_leaf] if self.phase.attraction else [])
                d = torch.autograd.grad(total.sum(), leaves)
        if want:
            self._gradients(params, grads, active, w, u0, d)
        return {n: v.detach() for n, v in stats.items()}

    def _gradients(self, params, grads, active, w, u0, d):
        R, S, T, K, D, M = self.shape
        lane = self.rnn.backward(d[0].reshape(R * K * S, T, D), self.X, w, u0)
        g_wi, g_wr, g_wo, g_bc, g_bo, g_eps, g_u0 = (
            x.view((R, K, S) + x.shape[1:]) for x in lane)
        net = {"w_in": g_wi.sum(2), "w_rec": g_wr.sum(2), "w_out": g_wo.sum(2),
               "b_c": g_bc.sum(2), "b_o": g_bo.sum(2), "beta": d[1], "log_sigma": d[2]}
        net["u0"] = g_u0.transpose(1, 2) + (d[3] if self.phase.attraction else 0)
        if "tau" in grads:  # ∂/∂τ = -ε² ∂/∂ε
            net["tau"] = -g_eps.sum(2) * w["eps"].view(R, K, M) ** 2
        for name in grads:
            self._write(grads, name, net[name], active)


class GatingProblem(_Problem):
    """Phase 2 of R runs (Eqs. 14-16), the arguments of the CPU backend's `GatingProblem`.
    Lane r·S + s runs the gating RNN of run r on series s, reading [ĝ_n, x_n] and fitted to
    ĝ_{n+τ}; `resample(step)` draws the input noise of `phase.input_noise_var` per run seed."""

    STATS = ("objective", "log_likelihood", "kl", "E_g")

    def __init__(self, gate_targets, inputs, model, phase, seeds, device="cuda"):
        super().__init__(device)
        R, S, T, K = gate_targets.shape
        D, H, delay = inputs.shape[-1], model.gating.context_size, model.delay
        T_g = T - delay
        dtype = getattr(torch, str(np.dtype(gate_targets.dtype)))
        self.shape, self.model, self.phase, self.seeds = (R, S, T_g, K, D, H), model, phase, seeds
        ghat = torch.as_tensor(np.ascontiguousarray(gate_targets), device=self.device).to(dtype)
        x = torch.as_tensor(np.ascontiguousarray(inputs), device=self.device).to(dtype)
        self.targets = ghat[:, :, delay:].contiguous()
        feed = torch.cat([ghat[:, :, :T_g], x[..., :T_g, :].expand(R, -1, -1, -1)], -1)
        self.clean = feed.reshape(R * S, T_g, K + D).contiguous()
        self.X = self.clean.clone()
        self.entropy = torch.xlogy(self.targets, self.targets).sum((1, 2, 3))
        lane = np.arange(R * S)
        self.rnn = Net(len(lane), T_g, K + D, H, K, lane // S, lane, lane,
                        model.learn_time_constants, phase.attraction, dtype, self.device)

    def resample(self, step: int) -> None:
        """Fresh input noise on x_n for this training step (nothing without noise)."""
        if self.phase.input_noise_var <= 0:
            return
        R, S, T_g, K, D, H = self.shape
        noise = input_noise(self.seeds, step, (S, T_g + self.model.delay, D),
                            self.phase.input_noise_var, np.dtype(str(self.X.dtype)[6:]))
        noise = torch.as_tensor(noise[:, :, :T_g].reshape(R * S, T_g, D), device=self.device)
        self.X[:, :, K:] = self.clean[:, :, K:] + noise

    def _call(self, params, grads, active):
        R, S, T_g, K, D, H = self.shape
        want = grads is not None
        w, u0 = weights(params, 1), params["u0"].contiguous()
        out = self.rnn.forward(self.X, w, u0, want)
        with torch.enable_grad() if want else torch.no_grad():
            o = out.view(R, S, T_g, K).detach().requires_grad_(want)
            u0_leaf = params["u0"].detach().requires_grad_(want and self.phase.attraction)
            log_gates = torch.log_softmax(o, -1)
            log_lik = objectives.gating_log_likelihood(log_gates, self.targets)
            kl = self.entropy - log_lik
            total = log_lik
            if self.phase.attraction:
                total = total + _attraction(u0_leaf, self.rnn.S.view(R, S, 2, H), T_g + 1,
                                            self.model.sigma_min ** 2)
            stats = {"objective": total, "log_likelihood": log_lik, "kl": kl,
                     "E_g": kl / (S * T_g * K)}
            if want:
                leaves = [o] + ([u0_leaf] if self.phase.attraction else [])
                d = torch.autograd.grad(total.sum(), leaves)
        if want:
            lane = self.rnn.backward(d[0].reshape(R * S, T_g, K), self.X, w, u0)
            g_wi, g_wr, g_wo, g_bc, g_bo, g_eps, g_u0 = (
                x.view((R, S) + x.shape[1:]) for x in lane)
            net = {"w_in": g_wi.sum(1), "w_rec": g_wr.sum(1), "w_out": g_wo.sum(1),
                   "b_c": g_bc.sum(1), "b_o": g_bo.sum(1),
                   "u0": g_u0 + (d[1] if self.phase.attraction else 0)}
            if "tau" in grads:
                net["tau"] = -g_eps.sum(1) * w["eps"] ** 2
            for name in grads:
                self._write(grads, name, net[name], active)
        return {n: v.detach() for n, v in stats.items()}
