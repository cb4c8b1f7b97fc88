"""The mixture of RNN experts (paper Sec. 2, Eqs. 1-8) as R independent copies in one set of
tensors.

Notation (shape letters used in every signature and einsum):

    R  runs: independent networks trained side by side
    S  series (the paper's NT)          T  time steps (the paper's LT)
    D  signal features (paper d)        K  experts (paper N)
    M  context units of one expert      H  context units of the gating RNN (paper NC, M_g)

Expert k (Eqs. 1-3):   u_n = (1-ε) u_{n-1} + ε (W_1 x_n + W_2 c_{n-1}),  c_n = tanh(u_n + v_1),
                       y_n = tanh(W_3 c_n + v_2).
Mixture (Eq. 4):       y_n = Σ_k g_n^k y_n^k.
Gating RNN (Eqs. 5-8): u^g_n = (1-ε^g) u^g_{n-1}
                             + ε^g (W^g_1 g_{n-τ} + W^g_2 x_{n-τ} + W^g_3 c^g_{n-1}),
                       c^g_n = tanh(u^g_n + v^g_1),  g_n = softmax(W^g_4 c^g_n + v^g_2).

The gating RNN is stepped in its own time m = n - τ: its step m reads (g_m, x_m) and emits g_{m+τ}.
Parameters are plain dicts of tensors with a leading R axis, so they checkpoint as state dicts.
This module is the reference implementation (PyTorch, autograd): the only time loop of the
teacher-forced passes is `leaky_scan`, and the closed loop advances by `closed_loop_step` (the
reference backend, `moex.kernels.reference`, loops over it). The compiled backends compute the
same functions and are tested against these.
"""

from dataclasses import dataclass
from typing import NamedTuple

import torch

from moex.config.model import ModelConfig
from moex.draws import draw


def leaky_scan(drive: torch.Tensor, w_rec: torch.Tensor, eps: torch.Tensor, bias: torch.Tensor,
               u0: torch.Tensor) -> torch.Tensor:
    """Run the leaky-tanh recurrence of Eqs. 1-2 (or 5-6) over time.

    B are the batch axes of distinct networks and N the rows (series) that share a network's
    weights; keeping N as the row axis makes every step one plain batched matmul.

    Args:
        drive: (B..., T, N, M) the input term (W_1 x_n, or W^g_1 g + W^g_2 x) at each step.
        w_rec: (B..., M, M) recurrent weights W_2.
        eps: (B..., 1, M) time constants ε, per neuron.
        bias: (B..., 1, M) v_1, added inside the tanh.
        u0: (B..., N, M) initial internal potentials.

    Returns:
        u: (B..., T, N, M) internal potentials u_1..u_T, and c: (B..., T, N, M) the contexts
        tanh(u + v_1).
    """
    u, c = u0, torch.tanh(u0 + bias)
    decay, drive = 1 - eps, eps.unsqueeze(-3) * drive
    w_eff = (eps.transpose(-1, -2) * w_rec).transpose(-1, -2)  # (ε W_2)ᵀ, folded once
    us = []
    for drive_n in drive.unbind(-3):  # unbind, not indexing: one gradient buffer, not T
        u = decay * u + drive_n + c @ w_eff
        c = torch.tanh(u + bias)
        us.append(u)
    u = torch.stack(us, dim=-3)
    return u, torch.tanh(u + bias.unsqueeze(-3))


def _uniform(generator, shape, bound, dtype):
    return (torch.rand(shape, generator=generator, dtype=dtype) * 2 - 1) * bound


def _init_rnn(generator, *, inputs: int, hidden: int, outputs: int, num_series: int,
              epsilon: float, scheme: str, dtype) -> dict[str, torch.Tensor]:
    """One run's leaky RNN: w_in (H, inputs), w_rec (H, H), w_out (outputs, H), biases, τ, u_0."""
    paper = scheme == "paper"
    w_bound = 1 / hidden
    in_bound = w_bound if paper or inputs == 0 else 1 / inputs
    bias_bound = w_bound if paper else 1.0
    return {
        "w_in": _uniform(generator, (hidden, inputs), in_bound, dtype),
        "w_rec": _uniform(generator, (hidden, hidden), w_bound, dtype),
        "w_out": _uniform(generator, (outputs, hidden), w_bound, dtype),
        "b_c": _uniform(generator, (hidden,), bias_bound, dtype),
        "b_o": _uniform(generator, (outputs,), bias_bound, dtype),
        "tau": torch.full((hidden,), 1 / epsilon, dtype=dtype),
        "u0": _uniform(generator, (num_series, hidden), 1.0, dtype) if paper
        else torch.zeros((num_series, hidden), dtype=dtype),
    }


def _stack(per_run: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    return {name: torch.stack([p[name] for p in per_run]) for name in per_run[0]}


def init_experts(cfg: ModelConfig, num_series: int, num_features: int,
                 generators: list[torch.Generator], dtype=torch.float64) -> dict[str, torch.Tensor]:
    """Initial expert parameters, run r drawn from `generators[r]` alone.

    Returns:
        w_in (R, K, M, D), w_rec (R, K, M, M), w_out (R, K, D, M), b_c (R, K, M), b_o (R, K, D),
        tau (R, K, M) = 1/ε, log_sigma (R, K) = s with σ² = e^{2s} + σ̄² (σ ≈ 1 at s = 0),
        u0 (R, S, K, M).
    """
    runs = []
    for gen in generators:
        experts = _stack([
            _init_rnn(gen, inputs=num_features, hidden=cfg.experts.context_size,
                      outputs=num_features, num_series=num_series,
                      epsilon=cfg.experts.epsilon, scheme=cfg.init, dtype=dtype)
            for _ in range(cfg.num_experts)])
        experts["u0"] = experts["u0"].transpose(0, 1)  # (K, S, M) -> (S, K, M)
        experts["log_sigma"] = torch.zeros(cfg.num_experts, dtype=dtype)
        runs.append(experts)
    return _stack(runs)


def init_gating(cfg: ModelConfig, num_series: int, num_features: int,
                generators: list[torch.Generator], dtype=torch.float64) -> dict[str, torch.Tensor]:
    """Initial gating-RNN parameters, run r drawn from `generators[r]` alone.

    Returns:
        w_in (R, H, K + D) acting on [g_{n-τ}, x_{n-τ}] (W^g_1 | W^g_2), w_rec (R, H, H),
        w_out (R, K, H), b_c (R, H), b_o (R, K), tau (R, H) = 1/ε^g, u0 (R, S, H).
    """
    return _stack([
        _init_rnn(gen, inputs=cfg.num_experts + num_features, hidden=cfg.gating.context_size,
                  outputs=cfg.num_experts, num_series=num_series,
                  epsilon=cfg.gating.epsilon, scheme=cfg.init, dtype=dtype)
        for gen in generators])


def expert_variances(experts: dict[str, torch.Tensor], sigma_min: float) -> torch.Tensor:
    """σ_k² = e^{2 s_k} + σ̄², (R, K): a soft floor at σ̄ (the C code's form)."""
    return torch.exp(2 * experts["log_sigma"]) + sigma_min**2


def gate_estimates(beta: torch.Tensor, temperature: float = 1.0) -> torch.Tensor:
    """ĝ_n = softmax(β_n) (Eq. 9), (R, S, T, K). `temperature` gives softmax(β_n / temperature)
    instead, sharper below 1 and the one-hot argmax at 0 (phase-2 targets that are not the
    paper's: `train.gating.target_temperature`)."""
    if temperature == 0:
        return torch.nn.functional.one_hot(beta.argmax(-1), beta.shape[-1]).to(beta.dtype)
    return torch.softmax(beta / temperature, dim=-1)


def expert_forward(experts: dict[str, torch.Tensor],
                   inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Teacher-forced outputs of every expert on every series (Eqs. 1-3).

    Args:
        experts: parameters from `init_experts`.
        inputs: (S, T, D) the inputs x_n (the series shifted by the delay), or (R, S, T, D)
            when every run has data of its own.

    Returns:
        outputs (R, S, T, K, D), y^k_n for each run, series, step and expert, and the internal
        potentials (R, S, K, T, M) that produced them.
    """
    per_run = "rstd" if inputs.ndim == 4 else "std"
    drive = torch.einsum(f"rkmd,{per_run}->rktsm", experts["w_in"], inputs)
    bias = experts["b_c"][:, :, None]  # (R, K, 1, M)
    u, c = leaky_scan(drive, experts["w_rec"], 1 / experts["tau"][:, :, None], bias,
                      experts["u0"].transpose(1, 2))  # (R, K, T, S, M), time-major inside
    outputs = torch.tanh(torch.einsum("rkdm,rktsm->rstkd", experts["w_out"], c)
                         + experts["b_o"][:, None, None])
    return outputs, u.permute(0, 3, 1, 2, 4)


def gating_forward(gating: dict[str, torch.Tensor], gate_targets: torch.Tensor,
                   inputs: torch.Tensor, delay: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Teacher-forced gate openings (Eqs. 5-8), fed ĝ_{n-τ} instead of g_{n-τ}.

    Args:
        gating: parameters from `init_gating`.
        gate_targets: (R, S, T, K) the estimates ĝ_n.
        inputs: (S, T, D) the inputs x_n aligned with ĝ_n (D may be 0), or (R, S, T, D) when
            every run sees its own (e.g. noisy) inputs.
        delay: τ.

    Returns:
        log_gates (R, S, T - τ, K), ln g_n for n = τ..T-1 (for n < τ, g_n = ĝ_n by definition),
        and the internal potentials (R, S, T - τ, H).
    """
    R, S, T, K = gate_targets.shape
    inputs = inputs.expand((R,) + inputs.shape[-3:])
    feed = torch.cat([gate_targets[:, :, : T - delay], inputs[:, :, : T - delay]], dim=-1)
    drive = torch.einsum("rhi,rsti->rtsh", gating["w_in"], feed)
    bias = gating["b_c"][:, None]  # (R, 1, H)
    u, c = leaky_scan(drive, gating["w_rec"], 1 / gating["tau"][:, None], bias,
                      gating["u0"])  # (R, T - τ, S, H)
    logits = torch.einsum("rkh,rtsh->rstk", gating["w_out"], c) + gating["b_o"][:, None, None]
    return torch.log_softmax(logits, dim=-1), u.transpose(1, 2)


@dataclass
class ClosedLoopState:
    """State of the autonomous mixture (Sec. 2.2) for R runs × N samples.

    experts_u (R, N, K, M) and gating_u (R, N, H) are internal potentials; inputs (R, N, τ, D)
    holds x_m..x_{m+τ-1} (the last τ mixture outputs) and gates (R, N, τ, K) holds g_m..g_{m+τ-1}.
    """

    experts_u: torch.Tensor
    gating_u: torch.Tensor
    inputs: torch.Tensor
    gates: torch.Tensor

    def flat(self, lead: int = 2) -> torch.Tensor:
        """(R, N, dim) with dim = K·M + H + τ·D + τ·K, the phase space of the Lyapunov analysis
        (`lead` = 3 for tangents (k, R, N, ...))."""
        parts = (self.experts_u, self.gating_u, self.inputs, self.gates)
        return torch.cat([p.flatten(lead) for p in parts], dim=-1)

    def like(self, flat: torch.Tensor) -> "ClosedLoopState":
        """Unpack (R, N, ..., dim) — extra axes before dim allowed — into this state's layout."""
        parts, start, lead = [], 0, flat.shape[:-1]
        for p in (self.experts_u, self.gating_u, self.inputs, self.gates):
            size = p[0, 0].numel()
            parts.append(flat[..., start:start + size].reshape(lead + p.shape[2:]))
            start += size
        return ClosedLoopState(*parts)


def _mv(w: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return (w @ x.unsqueeze(-1)).squeeze(-1)


def _leaky(u, drive, d_drive, du, *, w_rec, eps, bias):
    """One step of Eqs. 1-2 / 5-6 and, when `du` is given, its tangent (forward derivative)."""
    c = torch.tanh(u + bias)
    u_next = (1 - eps) * u + eps * (drive + _mv(w_rec, c))
    if du is None:
        return u_next, None
    return u_next, (1 - eps) * du + eps * (d_drive + _mv(w_rec, (1 - c.square()) * du))


class Step(NamedTuple):
    """One closed-loop step: the next state, the mixture output y_m (R, N, D), the gates g_m
    that mixed it (R, N, K), the gating potentials (R, N, H) and the next tangents (or None)."""

    state: ClosedLoopState
    output: torch.Tensor
    gates: torch.Tensor
    gating_u: torch.Tensor
    tangents: ClosedLoopState | None


class ClosedLoopRun(NamedTuple):
    """What a backend's `closed_loop` returns for `steps` steps: the next state, the records
    y (R, N, steps, D), g (R, N, steps, K) and u^g (R, N, steps, H) (None when not kept), the
    re-orthonormalised tangents (R, N, dim, k) or None, and the summed log growth (R, N, k)."""

    state: ClosedLoopState
    outputs: torch.Tensor
    gates: torch.Tensor
    gating_u: torch.Tensor | None
    tangents: torch.Tensor | None
    growth: torch.Tensor


def closed_loop_step(experts: dict[str, torch.Tensor], gating: dict[str, torch.Tensor],
                     state: ClosedLoopState, *, noise: torch.Tensor | None = None,
                     tangents: ClosedLoopState | None = None, uniform_gates: bool = False):
    """Advance the closed loop one step: x_m = y_{m-τ} (+ noise), experts, gating, mixture.

    With `tangents` it also propagates tangent vectors through the exact Jacobian of the whole
    system (all contexts and both delay lines, with the real gates), written out by hand.

    Args:
        experts, gating: parameters (R leading); experts is empty for symbolic tasks (D = 0).
        state: the current `ClosedLoopState` (R, N, ...).
        noise: (R, N, D) Gaussian noise added to x_m (Sec. 4.3), or None.
        tangents: a `ClosedLoopState` of tangent vectors (k, R, N, ...), or None.
        uniform_gates: differentiate Σ_k g_k y^k with g_k = 1/K in place of the real gates, as
            the authors' `mregn-lyapunov` does (a bug in that tool); the dynamics are unchanged.

    Returns:
        a `Step`.
    """
    R = state.gates.shape[0]
    x, g = state.inputs[..., 0, :], state.gates[..., 0, :]
    dx = dg = None
    if tangents is not None:
        dx, dg = tangents.inputs[..., 0, :], tangents.gates[..., 0, :]
    if noise is not None:
        x = x + noise
    experts_u, d_experts_u, y, dy = state.experts_u, None, x, dx
    if experts:  # Eqs. 1-4, every expert on the same input
        w = {k: v.view((R, 1) + v.shape[1:]) for k, v in experts.items() if k != "u0"}
        dxe = None if dx is None else _mv(w["w_in"], dx[..., None, :])
        experts_u, d_experts_u = _leaky(
            state.experts_u, _mv(w["w_in"], x[..., None, :]), dxe,
            None if tangents is None else tangents.experts_u, w_rec=w["w_rec"], eps=1 / w["tau"],
            bias=w["b_c"])
        c = torch.tanh(experts_u + w["b_c"])
        outputs = torch.tanh(_mv(w["w_out"], c) + w["b_o"])  # (R, N, K, D)
        y = (g[..., None] * outputs).sum(-2)
        if tangents is not None:
            d_out = (1 - outputs.square()) * _mv(w["w_out"], (1 - c.square()) * d_experts_u)
            weight = torch.full_like(g, 1 / g.shape[-1]) if uniform_gates else g
            dy = (dg[..., None] * outputs + weight[..., None] * d_out).sum(-2)
    # Eqs. 5-8: the gating RNN reads (g_m, x_m) and emits g_{m+τ}
    w = {k: v.view((R, 1) + v.shape[1:]) for k, v in gating.items() if k != "u0"}
    d_drive = None if tangents is None else _mv(w["w_in"], torch.cat([dg, dx], -1))
    gating_u, d_gating_u = _leaky(state.gating_u, _mv(w["w_in"], torch.cat([g, x], -1)), d_drive,
                                  None if tangents is None else tangents.gating_u, w_rec=w["w_rec"],
                                  eps=1 / w["tau"], bias=w["b_c"])
    c_g = torch.tanh(gating_u + w["b_c"])
    new_gates = torch.softmax(_mv(w["w_out"], c_g) + w["b_o"], -1)

    def shifted(s, y_new, g_new):
        return ClosedLoopState(s.experts_u, s.gating_u,
                               torch.cat([s.inputs[..., 1:, :], y_new[..., None, :]], -2),
                               torch.cat([s.gates[..., 1:, :], g_new[..., None, :]], -2))

    nxt = shifted(ClosedLoopState(experts_u, gating_u, state.inputs, state.gates), y, new_gates)
    d_nxt = None
    if tangents is not None:
        d_logits = _mv(w["w_out"], (1 - c_g.square()) * d_gating_u)
        d_gates = new_gates * (d_logits - (new_gates * d_logits).sum(-1, keepdim=True))
        d_nxt = shifted(ClosedLoopState(d_experts_u if experts else tangents.experts_u,
                                        d_gating_u, tangents.inputs, tangents.gates), dy, d_gates)
    return Step(nxt, y, g, gating_u, d_nxt)


def random_state(experts, gating, num_samples, *, num_features, delay,
                 generator) -> ClosedLoopState:
    """Random initial states: u ~ U[-1, 1], x ~ U[-1, 1] and random probability vectors in the
    delay lines (Sec. 4; the C code fills the gate line with U(-1, 1) instead)."""
    R, K, H = gating["w_out"].shape
    dtype = gating["w_out"].dtype

    def uniform(*shape):
        return draw(torch.rand, shape, generator, dtype) * 2 - 1

    M = experts["w_rec"].shape[-1] if experts else 0
    # normalised exponentials: uniform on the probability simplex
    e = -torch.log(draw(torch.rand, (R, num_samples, delay, K), generator,
                        dtype).clamp_min(1e-300))
    return ClosedLoopState(uniform(R, num_samples, K if experts else 0, M),
                           uniform(R, num_samples, H),
                           uniform(R, num_samples, delay, num_features),
                           e / e.sum(-1, keepdim=True))
