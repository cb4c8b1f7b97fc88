"""GPU backend (Triton): both training phases with the time loops in `moex.kernels.gpu_rnn`.

A training step is the forward kernel (every lane of every run), the phase's objective on the
outputs o_t and its gradient ∂L/∂o_t — the reference's own functions (`moex.objectives`) under
autograd, with no time loop — then the backward kernel and a sum of the per-lane gradients over
each network's lanes. Parameters, gradients and the optimiser state stay on the device; only the
per-run statistics (R values) reach the host.

The closed loop with its Lyapunov tangents (generation, λ_max or a spectrum) is one Triton kernel
per chunk of steps (`moex.kernels.gpu_closed`), as is the symbol readout (nearest prototype). With
`TRITON_INTERPRET=1` Triton runs the kernels on the CPU (slowly), which is how the tests check
them without a GPU.
"""

import os

import numpy as np
import torch
import triton

from moex import objectives
from moex.kernels import input_noise
from moex.kernels.gpu_closed import closed_loop_kernel, grid, nearest_kernel
from moex.kernels.gpu_rnn import rnn_backward, rnn_forward
from moex.model import ClosedLoopRun

INTERPRET = os.environ.get("TRITON_INTERPRET") == "1"
LANE_BUDGET = 2048  # weight-tile entries per program: BL · HP², the registers a tile may take


def available(device: str) -> bool:
    """The kernels run on CUDA, or anywhere in Triton's interpreter."""
    return INTERPRET or (device.startswith("cuda") and torch.cuda.is_available())


def _pow2(n: int) -> int:
    return triton.next_power_of_2(max(n, 1))


class _Net:
    """One leaky RNN per network (B networks) and its lanes: which network, input row and u_0 row
    each lane reads, and the buffers the two kernels fill."""

    def __init__(self, num_lanes, T, NI, H, NO, net, xrow, u0row, learn_eps, sums, dtype, device):
        self.L, self.T, self.NI, self.H, self.NO = num_lanes, T, NI, H, NO
        self.learn_eps, self.sums = learn_eps, sums

        def index(x):
            return torch.as_tensor(np.asarray(x), dtype=torch.int64, device=device)

        self.net, self.xrow, self.u0row = index(net), index(xrow), index(u0row)
        self.pad = dict(NIP=_pow2(NI), HP=_pow2(H), NOP=_pow2(NO))
        self.block = max(1, min(32, LANE_BUDGET // self.pad["HP"] ** 2))

        def empty(*shape):
            return torch.zeros(shape, dtype=dtype, device=device)

        self.O, self.C = empty(num_lanes, T, NO), empty(num_lanes, T, H)
        self.U = empty(num_lanes, T, H) if learn_eps else empty(1)
        self.S = empty(num_lanes, 2, H) if sums else empty(1)
        self.grads = (empty(num_lanes, H, NI), empty(num_lanes, H, H), empty(num_lanes, NO, H),
                      empty(num_lanes, H), empty(num_lanes, NO), empty(num_lanes, H),
                      empty(num_lanes, H))

    def _launch(self, kernel, *args, **flags):
        grid = (triton.cdiv(self.L, self.block),)
        kernel[grid](*args, self.L, T=self.T, NI=self.NI, H=self.H, NO=self.NO, BL=self.block,
                     **self.pad, **flags)

    def forward(self, X, w, u0, keep):
        """O (L, T, NO); with `keep` also the histories the backward pass reads."""
        self._launch(rnn_forward, X, self.xrow, self.net, self.u0row, w["w_in"], w["w_rec"],
                     w["w_out"], w["b_c"], w["b_o"], w["eps"], u0, self.O, self.C, self.U,
                     self.S, KEEP_C=keep, KEEP_U=keep and self.learn_eps, KEEP_SUMS=self.sums)
        return self.O

    def backward(self, dO, X, w, u0):
        """Per-lane gradients (w_in, w_rec, w_out, b_c, b_o, ε, u_0) for ∂L/∂O = dO."""
        self._launch(rnn_backward, dO.contiguous(), X, self.xrow, self.net, self.u0row,
                     w["w_in"], w["w_rec"], w["w_out"], w["b_c"], w["eps"], u0, self.C, self.U,
                     *self.grads, LEARN_EPS=self.learn_eps)
        return self.grads


def _weights(params: dict, lead: int) -> dict:
    """Contiguous weights (B, ...) and ε = 1/τ of the B networks in the first `lead` axes."""
    out = {k: params[k].flatten(0, lead - 1).contiguous()
           for k in ("w_in", "w_rec", "w_out", "b_c", "b_o")}
    out["eps"] = (1 / params["tau"]).flatten(0, lead - 1).contiguous()
    return out


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
        inputs, targets: (S, T, D) x_n and y_n = x_{n+τ}.
        model: the `ModelConfig`; phase: the `ExpertPhaseConfig`; num_runs: R.
    """

    STATS = ("objective", "log_likelihood", "log_prior", "E")

    def __init__(self, inputs, targets, model, phase, num_runs, device="cuda"):
        super().__init__(device)
        S, T, D = targets.shape
        R, K, M = num_runs, model.num_experts, model.experts.context_size
        dtype = getattr(torch, str(np.dtype(inputs.dtype)))
        self.shape, self.model, self.phase = (R, S, T, K, D, M), model, phase
        self.X = torch.as_tensor(np.ascontiguousarray(inputs), device=self.device).to(dtype)
        self.targets = torch.as_tensor(np.ascontiguousarray(targets), device=self.device).to(dtype)
        lane = np.arange(R * K * S)
        r, k, s = lane // (K * S), lane // S % K, lane % S
        self.rnn = _Net(len(lane), T, D, M, D, r * K + k, s, (r * S + s) * K + k,
                        model.learn_time_constants, phase.attraction, dtype, self.device)

    def _call(self, params, grads, active):
        R, S, T, K, D, M = self.shape
        want = grads is not None
        w, u0 = _weights(params, 2), params["u0"].contiguous()
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
        feed = torch.cat([ghat[:, :, :T_g], x[None, :, :T_g].expand(R, -1, -1, -1)], -1)
        self.clean = feed.reshape(R * S, T_g, K + D).contiguous()
        self.X = self.clean.clone()
        self.entropy = torch.xlogy(self.targets, self.targets).sum((1, 2, 3))
        lane = np.arange(R * S)
        self.rnn = _Net(len(lane), T_g, K + D, H, K, lane // S, lane, lane,
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
        w, u0 = _weights(params, 1), params["u0"].contiguous()
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


_NET = ("w_in", "w_rec", "w_out", "b_c", "b_o")


def closed_loop(experts, gating, state, steps: int, noise=None, tangents=None,
                count: bool = False, uniform_gates: bool = False,
                potentials: bool = True) -> ClosedLoopRun:
    """`moex.kernels.reference.closed_loop` as one kernel launch: same arguments and results (on
    the device of `state`)."""
    num_tangents = 0 if tangents is None else tangents.shape[-1]
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    home, dtype = state.gates.device, state.gates.dtype
    R, N, TAU, K = state.gates.shape
    D, H = state.inputs.shape[-1], state.gating_u.shape[-1]
    M = state.experts_u.shape[-1] if experts else 0
    dummy = torch.zeros(1, dtype=dtype, device=device)

    def put(x):  # a contiguous copy on the device (kernels write into some of them)
        x = x.detach().to(device=device, dtype=dtype).contiguous().clone()
        return x if x.numel() else dummy

    def weights(net):
        if not net:
            return [dummy] * 6
        return [put(net[n]) for n in _NET] + [put(1 / net["tau"])]

    parts = [put(x) for x in (state.experts_u, state.gating_u, state.inputs, state.gates)]
    sizes = [K * M, H, TAU * D, TAU * K]
    # tangents (R, N, dim, KT) -> per piece (R, N, KT, size): one vector's piece is contiguous
    vec = ([put(p.transpose(-1, -2)) for p in tangents.split(sizes, dim=-2)] if num_tangents
           else [dummy] * 4)
    out_y = torch.zeros((R, N, steps, D), dtype=dtype, device=device)
    out_g = torch.zeros((R, N, steps, K), dtype=dtype, device=device)
    out_u = torch.zeros((R, N, steps, H), dtype=dtype, device=device) if potentials else dummy
    growth = torch.zeros((R, N, num_tangents), dtype=dtype, device=device)
    pad = {name: _pow2(size) for name, size in (("KP", K), ("MP", M), ("DP", D), ("HP", H),
                                                 ("TP", TAU), ("KTP", num_tangents))}
    per_lane = max(pad["KP"] * pad["MP"] * max(pad["MP"], pad["DP"]), pad["HP"] ** 2)
    samples = max(1, min(16, 8192 // (per_lane * pad["KTP"])))  # per program (a power of 2)
    closed_loop_kernel[grid(R, N, samples)](
        *weights(experts), *weights(gating), *parts, *vec,
        put(noise) if noise is not None else dummy, out_y, out_g, out_u, growth, N,
        STEPS=steps, K=K, M=M, D=D, H=H, TAU=TAU, BN=samples * pad["KTP"],
        KT=max(num_tangents, 1), EXPERTS=bool(experts), TANGENT=bool(num_tangents),
        NOISY=noise is not None, COUNT=bool(count and num_tangents),
        UNIFORM=bool(uniform_gates), KEEP_U=bool(potentials), **pad)

    def back(x, shape):
        return x.reshape(shape).to(home) if x is not dummy else torch.zeros(shape, dtype=dtype)

    nxt = type(state)(back(parts[0], state.experts_u.shape), back(parts[1], (R, N, H)),
                      back(parts[2], (R, N, TAU, D)), back(parts[3], (R, N, TAU, K)))
    new_tangents = None
    if num_tangents:
        new_tangents = torch.cat([back(v, (R, N, num_tangents, size)).transpose(-1, -2)
                                  for v, size in zip(vec, sizes, strict=True)], -2)
    return ClosedLoopRun(nxt, back(out_y, (R, N, steps, D)), back(out_g, (R, N, steps, K)),
                         back(out_u, (R, N, steps, H)) if potentials else None, new_tangents,
                         growth.to(home))


def nearest_symbols(points: np.ndarray, prototypes: np.ndarray,
                    prototype_symbols: np.ndarray) -> np.ndarray:
    """`moex.metrics.symbols.symbolize_nearest` as one kernel: (..., T, D) -> (..., T)."""
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    D = points.shape[-1]
    flat = torch.as_tensor(np.ascontiguousarray(points, np.float64).reshape(-1, D), device=device)
    proto = torch.as_tensor(np.ascontiguousarray(prototypes, np.float64), device=device)
    symbols = torch.as_tensor(np.asarray(prototype_symbols, np.int64), device=device)
    out = torch.empty(len(flat), dtype=torch.int64, device=device)
    P, block = len(proto), 128
    nearest_kernel[(triton.cdiv(len(flat), block),)](flat, proto, symbols, out, len(flat), P=P,
                                                     D=D, PP=_pow2(P), DP=_pow2(D), BLOCK=block)
    return out.cpu().numpy().reshape(points.shape[:-1])
