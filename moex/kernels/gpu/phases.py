"""The two training phases of the GPU backend (Triton), each step four launches: the forward
kernel of `moex.kernels.gpu.rnn` over every lane of every run (`moex.kernels.gpu.lanes`), the
phase's objective kernel here (one program per run: the statistics, ∂L/∂o_t for every lane and
the gradients of the objective's own parameters), and the two backward kernels, which sum each
network's lanes into the training loop's gradient buffer. A value without gradients (the
adaptive rate's trial) is the first two. Nothing is synchronised with the host: the statistics
are device tensors (R,) the host reads when it logs.

Phase 1's objective (Eqs. 9-13), per run, with y^k = tanh(o^k), ĝ = softmax β, σ_k² = e^{2 ln σ_k}
+ σ̄², z_k = ln ĝ_k + ln N(y; y^k, σ_k² I) and π = softmax z (the posterior of the experts):
    ln L = Σ_{s,n} logsumexp_k z_k + Σ_{s,n<T,k} [-(β_{n+1} - β_n)²/(2ς²) - ln(√(2π) ς)],
    ∂/∂o^k = π_k (y - y^k)/σ_k² (1 - (y^k)²),  ∂/∂β = π - ĝ + (β_{n+1} - 2β_n + β_{n-1})/ς²
    (the neighbours that exist),  ∂/∂ln σ_k = Σ π_k (‖y - y^k‖²/σ_k² - D) e^{2 ln σ_k}/σ_k²,
and E = ½ Σ ‖y - Σ_k ĝ_k y^k‖² / (S T D). Phase 2's (Eqs. 14-16), with ln g = log_softmax o:
    ln L = Σ ĝ ln g,  KL = Σ ĝ ln ĝ - ln L,  ∂/∂o = ĝ - g Σ_k ĝ_k.
The C code's u_0 attraction adds Σ_lanes -(u_0 - μ)²/(2v) (its gradient: in the backward kernel).
"""

import math

import numpy as np
import torch
import triton
import triton.language as tl

from moex.kernels.gpu.lanes import TRIALS, Net, launch, pow2, strides
from moex.kernels.gpu.noise import DeviceNoise
from moex.kernels.gpu.rnn import device, divide, exp, lane_moments, load_rows, log, stable_tanh

BT = 64  # time steps per tile of the objective kernels, at most
TILE = 1024  # entries of an objective kernel's (BT, K, D) tiles, at most (`time_tile`)
BJ = 16  # lanes per tile of the attraction sum


def time_tile(T: int, *widths: int) -> int:
    """Time steps per tile of an objective kernel: BT, fewer where its (BT, KP, DP) tiles would
    hold more than TILE entries (24 experts: 16 steps; at 64 the phase-1 objective spilled 1.2-1.7
    KB per thread in its compile for an H200, `benchmarks/gpu_aot.py`)."""
    return min(BT, pow2(T), max(8, TILE // math.prod(pow2(w) for w in widths)))


@device
def _attraction(SUMS, U0, U0J, first, floor, LPR: tl.constexpr, T: tl.constexpr,
                H: tl.constexpr, HP: tl.constexpr, BJ: tl.constexpr):
    """Σ over the LPR lanes first.. of Σ_h -(u_0 - μ)²/(2v), μ and v = max(var, floor) from the
    forward kernel's Σu, Σu² over {u_0..u_T}."""
    h = tl.arange(0, HP)
    total = tl.zeros((BJ, HP), dtype=floor.dtype)
    for jb in range(tl.cdiv(LPR, BJ)):
        j = jb * BJ + tl.arange(0, BJ)
        ok = j < LPR
        lane = first + j
        u0 = load_rows(U0, tl.load(U0J + lane, mask=ok, other=0), ok, h, H)
        mean, var = lane_moments(SUMS, lane, ok, h, floor, T, H)
        dev = u0 - mean
        total += tl.where(ok[:, None] & (h < H)[None, :], -divide(dev * dev, 2.0 * var), 0.0)
    return tl.sum(tl.sum(total, axis=1), axis=0)


@device
def _log_softmax(x, ok):
    """(BT, KP) log-softmax over the K entries where `ok` ((KP,) bools); also the softmax."""
    m = tl.max(tl.where(ok[None, :], x, -float("inf")), axis=1)
    e = tl.where(ok[None, :], exp(x - m[:, None]), 0.0)
    total = tl.sum(e, axis=1)
    return x - m[:, None] - log(total)[:, None], divide(e, total[:, None])


@triton.jit
def mixture_objective(OUT, TARGETS, BETA, LOG_SIGMA, SUMS, U0, U0J, CONST, ACTIVE, DO, G_BETA,
                      G_LOG_SIGMA, sBETA, sLOG_SIGMA, sU0, sG_BETA, sG_LOG_SIGMA, num_runs,
                      data_runs, STATS,
                      S: tl.constexpr, T: tl.constexpr, K: tl.constexpr, D: tl.constexpr,
                      KP: tl.constexpr, DP: tl.constexpr, H: tl.constexpr, HP: tl.constexpr,
                      OWN: tl.constexpr, BT: tl.constexpr, BJ: tl.constexpr,
                      WANT: tl.constexpr, ATTRACT: tl.constexpr):
    """Phase 1 of run r = program: STATS (4, R) = objective, ln L, ln prior, E; with WANT also
    DO (∂L/∂o of lane (r·K + k)·S + s), G_BETA and G_LOG_SIGMA where ACTIVE[r]. CONST holds
    σ̄², 2π, ς² and ln(√(2π) ς). Run r reads the data of run r mod data_runs (candidates)."""
    r = tl.program_id(0).to(tl.int64)
    k, d, t = tl.arange(0, KP), tl.arange(0, DP), tl.arange(0, BT)
    k_ok, d_ok = k < K, d < D
    floor, two_pi = tl.load(CONST), tl.load(CONST + 1)
    prior_var, prior_norm = tl.load(CONST + 2), tl.load(CONST + 3)
    on = tl.load(ACTIVE + r + 0 * k) != 0  # (KP,): the interpreter's masks need a vector
    log_sigma = tl.load(LOG_SIGMA + r * sLOG_SIGMA + k, mask=k_ok, other=0.0)
    spread = exp(2.0 * log_sigma)
    var = spread + floor
    log_norm = (-0.5 * D) * log(two_pi * var)
    log_lik = tl.zeros((BT,), dtype=var.dtype)
    log_prior, sq_error = log_lik, log_lik
    g_log_sigma = tl.zeros((KP,), dtype=var.dtype)
    for s in range(S):
        lanes = (r * K + k) * S + s
        for tb in range(tl.cdiv(T, BT)):
            n = tb * BT + t
            n_ok, next_ok = n < T, n + 1 < T
            m2 = n_ok[:, None] & k_ok[None, :]
            m3 = m2[:, :, None] & d_ok[None, None, :]
            at = (lanes[None, :, None] * T + n[:, None, None]) * D + d[None, None, :]
            y = stable_tanh(tl.load(OUT + at, mask=m3, other=0.0))
            row = (r % data_runs) * S * OWN + s
            target = tl.load(TARGETS + (row * T + n[:, None]) * D + d[None, :],
                             mask=n_ok[:, None] & d_ok[None, :], other=0.0)
            err = y - target[:, None, :]
            e = tl.sum(err * err, axis=2)
            b_at = BETA + r * sBETA + (s * T + n[:, None]) * K + k[None, :]
            beta = tl.load(b_at, mask=m2, other=0.0)
            log_gate, gate = _log_softmax(beta, k_ok)
            z = tl.where(k_ok[None, :],
                         log_gate + (log_norm[None, :] - divide(e, 2.0 * var[None, :])),
                         -float("inf"))
            z_max = tl.max(z, axis=1)
            w = exp(z - z_max[:, None])
            w_sum = tl.sum(w, axis=1)
            log_lik += tl.where(n_ok, z_max + log(w_sum), 0.0)
            mix = tl.sum(gate[:, :, None] * y, axis=1) - target
            sq_error += tl.where(n_ok, tl.sum(mix * mix, axis=1), 0.0)
            step = tl.load(b_at + K, mask=next_ok[:, None] & k_ok[None, :], other=0.0) - beta
            log_prior += tl.where(next_ok, tl.sum(tl.where(
                k_ok[None, :], -divide(step * step, 2.0 * prior_var) - prior_norm, 0.0), axis=1),
                0.0)
            if WANT:
                post = divide(w, w_sum[:, None])
                tl.store(DO + at,
                         post[:, :, None] * divide(-err, var[None, :, None]) * (1.0 - y * y),
                         mask=m3 & on[None, :, None])
                g_log_sigma += tl.sum(tl.where(m2, post * (divide(e, var[None, :]) - D), 0.0),
                                      axis=0)
                back = beta - tl.load(b_at - K, mask=(n > 0)[:, None] & k_ok[None, :], other=0.0)
                g_beta = post - gate + divide(tl.where(next_ok[:, None], step, 0.0)
                                              - tl.where((n > 0)[:, None], back, 0.0), prior_var)
                tl.store(G_BETA + r * sG_BETA + (s * T + n[:, None]) * K + k[None, :], g_beta,
                         mask=m2 & on[None, :])
    total_lik, total_prior = tl.sum(log_lik, axis=0), tl.sum(log_prior, axis=0)
    objective = total_lik + total_prior
    if ATTRACT:
        objective += _attraction(SUMS, U0 + r * sU0, U0J, r * (K * S), floor, K * S, T, H, HP, BJ)
    tl.store(STATS + r, objective)
    tl.store(STATS + num_runs + r, total_lik)
    tl.store(STATS + 2 * num_runs + r, total_prior)
    tl.store(STATS + 3 * num_runs + r, 0.5 * tl.sum(sq_error, axis=0) / (S * T * D))
    if WANT:
        tl.store(G_LOG_SIGMA + r * sG_LOG_SIGMA + k, divide(g_log_sigma * spread, var),
                 mask=k_ok & on)


@triton.jit
def softmax_objective(OUT, TARGETS, ENTROPY, SUMS, U0, U0J, CONST, ACTIVE, DO, sU0, num_runs,
                      data_runs, STATS, S: tl.constexpr, T: tl.constexpr, K: tl.constexpr,
                      KP: tl.constexpr, H: tl.constexpr, HP: tl.constexpr, BT: tl.constexpr,
                      BJ: tl.constexpr, WANT: tl.constexpr, ATTRACT: tl.constexpr):
    """Phase 2 of run r = program: STATS (4, R) = objective, ln L, KL, E_g; with WANT also
    DO (∂L/∂o of lane r·S + s) where ACTIVE[r]. CONST holds σ̄². Run r reads the targets of run
    r mod data_runs (candidates)."""
    r = tl.program_id(0).to(tl.int64)
    k, t = tl.arange(0, KP), tl.arange(0, BT)
    k_ok = k < K
    on = tl.load(ACTIVE + r + 0 * k) != 0
    floor = tl.load(CONST)
    log_lik = tl.zeros((BT,), dtype=floor.dtype)
    for s in range(S):
        for tb in range(tl.cdiv(T, BT)):
            n = tb * BT + t
            m2 = (n < T)[:, None] & k_ok[None, :]
            at = ((r * S + s) * T + n[:, None]) * K + k[None, :]
            log_gate, gate = _log_softmax(tl.load(OUT + at, mask=m2, other=0.0), k_ok)
            target = tl.load(TARGETS + (((r % data_runs) * S + s) * T + n[:, None]) * K
                             + k[None, :], mask=m2, other=0.0)
            log_lik += tl.sum(tl.where(m2, target * log_gate, 0.0), axis=1)
            if WANT:
                tl.store(DO + at, target - gate * tl.sum(target, axis=1)[:, None],
                         mask=m2 & on[None, :])
    total = tl.sum(log_lik, axis=0)
    objective = total
    if ATTRACT:
        objective += _attraction(SUMS, U0 + r * sU0, U0J, r * S, floor, S, T, H, HP, BJ)
    kl = tl.load(ENTROPY + r % data_runs) - total
    tl.store(STATS + r, objective)
    tl.store(STATS + num_runs + r, total)
    tl.store(STATS + 2 * num_runs + r, kl)
    tl.store(STATS + 3 * num_runs + r, kl / (S * T * K))


class _Problem:
    """value_and_grad / value / value_of_candidates on device tensors; a subclass builds its
    lanes (`_net`) and launches its objective kernel (`_objective`)."""

    STATS: tuple
    trials = TRIALS  # candidate steps of the adaptive rate evaluated in one call

    def __init__(self, num_runs):
        """After a subclass has set its device, shape, model, phase and dtype."""
        self.num_runs, self.candidates = num_runs, None
        self.everyone = torch.ones(num_runs * self.trials, dtype=torch.bool, device=self.device)
        self.rnn = self._net(1)

    def resample(self, step: int) -> None:
        """Nothing to draw (see `GatingProblem`)."""

    def stepper(self, buffers, columns, fixed, **settings) -> None:
        """No whole step in one launch: the training loop makes its calls."""

    def value_and_grad(self, params: dict, grads: dict, active) -> dict:
        """Objective statistics per run (R,); every gradient of an active run is written into
        `grads` (the others keep theirs)."""
        return self._call(self.rnn, params, grads, torch.as_tensor(active, device=self.device))

    def value(self, params: dict, active) -> dict:
        """The same statistics without gradients (every run is computed)."""
        return self._call(self.rnn, params, None, self.everyone[:self.num_runs])

    def value_of_candidates(self, params: dict) -> dict:
        """Statistics (k·R,) of k = `trials` parameter sets per run in one forward and one
        objective launch: params are (k·R, ...) groups, candidate j of run r in row j·R + r."""
        if self.candidates is None:
            self.candidates = self._net(self.trials)
        return self._call(self.candidates, params, None, self.everyone)

    def _call(self, rnn, params, grads, active):
        want = grads is not None
        stats = torch.empty((len(self.STATS), len(active)), dtype=rnn.O.dtype,
                            device=self.device)
        rnn.forward(self.X, params, want)
        self._objective(rnn, params, grads, active, stats=stats, want=want)
        if want:
            rnn.backward(self.X, params, grads, active, attract=self.phase.attraction,
                         floor=self.const)
        return dict(zip(self.STATS, stats.unbind(0), strict=True))


class ExpertProblem(_Problem):
    """Phase 1 of R runs (Eqs. 9-13). Lane (r·K + k)·S + s runs expert k of run r on series s.

    Args:
        inputs, targets: (S, T, D) x_n and y_n = x_{n+τ}, or (R, S, T, D) per run.
        model: the `ModelConfig`; phase: the `ExpertPhaseConfig`; num_runs: R.
    """

    STATS = ("objective", "log_likelihood", "log_prior", "E")

    def __init__(self, inputs, targets, model, phase, *, num_runs, device="cuda"):
        S, T, D = targets.shape[-3:]
        K, M = model.num_experts, model.experts.context_size
        self.device = torch.device(device)
        inputs, self.targets = (torch.as_tensor(x).to(self.device).contiguous()
                                for x in (inputs, targets))
        self.dtype, self.own = inputs.dtype, inputs.dim() == 4  # own: X holds R·S series
        self.shape, self.model, self.phase = (S, T, K, D, M), model, phase
        self.X = inputs.reshape(-1, T, D)
        std = phase.gate_prior_std
        self.const = torch.tensor([model.sigma_min ** 2, 2 * math.pi, std ** 2,
                                   0.5 * math.log(2 * math.pi * std ** 2)], dtype=self.dtype,
                                  device=self.device)
        self.meta = dict(S=S, T=T, K=K, D=D, KP=pow2(K), DP=pow2(D), H=M, HP=pow2(M),
                         OWN=int(self.own), BT=time_tile(T, K, D), BJ=BJ)
        super().__init__(num_runs)

    def _net(self, copies):
        """The lanes of `copies` x R runs; run r' reads the data of run r' mod R."""
        S, T, K, D, M = self.shape
        lane = np.arange(copies * self.num_runs * K * S)
        r, k, s = lane // (K * S) % self.num_runs, lane // S % K, lane % S
        return Net(copies * self.num_runs * K, K, S, T=T, NI=D, H=M, NO=D,
                   xrow=r * S * self.own + s, u0j=s * K + k,
                   learn_eps=self.model.learn_time_constants, sums=self.phase.attraction,
                   dtype=self.dtype, device=self.device, keep=copies == 1)

    def _objective(self, rnn, params, grads, active, *, stats, want):
        g = grads if want else params  # (not written without WANT)
        launch(mixture_objective, len(active), rnn.O, self.targets, params["beta"],
               params["log_sigma"], rnn.S, params["u0"], rnn.u0j, self.const, active,
               rnn.DO, g["beta"], g["log_sigma"],
               *strides(params, ("beta", "log_sigma", "u0")), *strides(g, ("beta", "log_sigma")),
               len(active), self.num_runs, STATS=stats, WANT=want,
               ATTRACT=self.phase.attraction, **self.meta)


class GatingProblem(_Problem):
    """Phase 2 of R runs (Eqs. 14-16), the arguments of the CPU backend's `GatingProblem`.
    Lane r·S + s runs the gating RNN of run r on series s, reading [ĝ_n, x_n] and fitted to
    ĝ_{n+τ}; `resample(step)` draws the input noise of `phase.input_noise_var` per run seed, on
    the device (`moex.kernels.gpu.noise`)."""

    STATS = ("objective", "log_likelihood", "kl", "E_g")

    def __init__(self, gate_targets, inputs, model, phase, *, seeds, device="cuda"):
        R, S, T, K = gate_targets.shape
        D, H, delay = inputs.shape[-1], model.gating.context_size, model.delay
        T_g = T - delay
        self.shape, self.model, self.phase = (R, S, T_g, K, D, H), model, phase
        self.device = torch.device(device)
        ghat = torch.as_tensor(gate_targets).to(self.device)
        self.dtype = ghat.dtype
        x = torch.as_tensor(inputs).to(self.device, self.dtype)
        self.targets = ghat[:, :, delay:].contiguous()
        feed = torch.cat([ghat[:, :, :T_g], x[..., :T_g, :].expand(R, -1, -1, -1)], -1)
        self.clean = feed.reshape(R * S, T_g, K + D).contiguous()
        self.X = self.clean.clone()
        self.noise = None if phase.input_noise_var <= 0 else DeviceNoise(
            seeds, phase.input_noise_var, S=S, T_FULL=T, device=self.device)
        self.entropy = torch.xlogy(self.targets, self.targets).sum((1, 2, 3))
        self.const = torch.tensor([model.sigma_min ** 2], dtype=self.dtype, device=self.device)
        self.meta = dict(S=S, T=T_g, K=K, KP=pow2(K), H=H, HP=pow2(H), BT=time_tile(T_g, K),
                         BJ=BJ)
        super().__init__(R)

    def _net(self, copies):
        """The lanes of `copies` x R runs; run r' reads the inputs of run r' mod R."""
        R, S, T_g, K, D, H = self.shape
        lane = np.arange(copies * R * S)
        return Net(copies * R, 1, S, T=T_g, NI=K + D, H=H, NO=K, xrow=lane % (R * S),
                   u0j=lane % S, learn_eps=self.model.learn_time_constants,
                   sums=self.phase.attraction, dtype=self.dtype, device=self.device,
                   keep=copies == 1)

    def resample(self, step: int) -> None:
        """Fresh input noise on x_n for this training step (nothing without noise)."""
        if self.noise is not None:
            self.noise.add(self.X, self.clean, step, K=self.shape[3])

    def _objective(self, rnn, params, grads, active, *, stats, want):
        launch(softmax_objective, len(active), rnn.O, self.targets, self.entropy, rnn.S,
               params["u0"], rnn.u0j, self.const, active, rnn.DO, *strides(params, ("u0",)),
               len(active), self.num_runs, STATS=stats, WANT=want,
               ATTRACT=self.phase.attraction, **self.meta)
