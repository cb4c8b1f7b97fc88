"""Every metric of a trained mixture (paper Sec. 3-4): teacher-forced E and E^g, closed-loop
E^closed and block KL from the trained initial states, and from random initial states the
Lyapunov exponents, the test-data block KL, switching statistics and periodicity."""

import collections
import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from tqdm.auto import tqdm

from moex import objectives
from moex.errors import check, check_positive
from moex.kernels import Backend, get_backend
from moex.metrics import switching
from moex.metrics.errors import closed_loop_mse
from moex.metrics.lyapunov import initial_tangents
from moex.metrics.symbols import block_kl, symbolize_argmax, symbolize_nearest
from moex.model import ClosedLoopState, expert_forward, gating_forward
from moex.tasks import Dataset


@dataclass
class EvalConfig:
    """Evaluation settings; the paper's protocol is 50 samples × 100000 steps (Lissajous) and
    200 × 10000 (Reber), after a discarded transient."""

    enabled: bool = True  # `moex train` ends by evaluating
    num_samples: int = 50  # closed-loop runs from random initial states, per network
    lyapunov_steps: int = 100000
    transient: int = 1000
    num_exponents: int = 1  # 1 = the maximum exponent only
    # gates in the Jacobian of the mixture: `real`, or `uniform` (1/K) as the authors'
    # mregn-lyapunov computes them (a bug, spec §5.3), to compare with its exponents
    jacobian_gates: str = "real"
    block_length: int = 5  # m of D_KL^(m) (3 for Reber)
    kl_floor: float = 1e-3  # model probability given to data blocks it never produced
    noise_var: float = 0.0  # ρ², Gaussian noise added to x_n each step (Sec. 4.3)
    max_period: int = 100  # periodicity test of the symbol sequence (Sec. 4.3)
    plot_steps: int = 2000  # closed-loop steps of the first sample kept for figures
    every: int = 0  # track block KL and λ_max every N gating-phase steps (0 = off)
    track_samples: int = 4  # random initial states per network when tracking
    track_steps: int = 5000  # Lyapunov steps per sample when tracking

    def __post_init__(self):
        check(self.every >= 0, f"eval.every={self.every} must be >= 0")
        for key in ("num_samples", "lyapunov_steps", "num_exponents", "block_length",
                    "max_period", "plot_steps", "track_samples", "track_steps"):
            check(getattr(self, key) >= 1, f"eval.{key}={getattr(self, key)} must be >= 1")
        check(self.transient >= 0, f"eval.transient={self.transient} must be >= 0")
        check(self.jacobian_gates in ("real", "uniform"),
              f"eval.jacobian_gates={self.jacobian_gates!r}; choose real or uniform")
        check(self.noise_var >= 0, f"eval.noise_var={self.noise_var} must be >= 0")
        check_positive("eval.kl_floor", self.kl_floor)


def trained_state(experts, gating, gate_estimates, series, delay) -> ClosedLoopState:
    """The trained initial state of every series (N = S): u_0, and data / ĝ in the delay lines."""
    R = gate_estimates.shape[0]
    experts_u = experts["u0"] if experts else series.new_zeros(R, series.shape[0], 0, 0)
    inputs = series[None, :, :delay].expand(R, -1, -1, -1)
    return ClosedLoopState(experts_u, gating["u0"], inputs, gate_estimates[:, :, :delay])


def random_state(experts, gating, num_samples, num_features, delay,
                 generator) -> ClosedLoopState:
    """Random initial states: u ~ U[-1, 1], x ~ U[-1, 1] and random probability vectors in the
    delay lines (Sec. 4; the C code fills the gate line with U(-1, 1) instead, spec §4.4)."""
    R, K, H = gating["w_out"].shape
    dtype = gating["w_out"].dtype

    def uniform(*shape):
        return (torch.rand(shape, generator=generator, dtype=dtype) * 2 - 1).to(
            gating["w_out"].device)

    M = experts["w_rec"].shape[-1] if experts else 0
    # normalised exponentials: uniform on the probability simplex
    e = -torch.log(torch.rand((R, num_samples, delay, K), generator=generator,
                              dtype=dtype).clamp_min(1e-300))
    gates = e / e.sum(-1, keepdim=True)
    return ClosedLoopState(uniform(R, num_samples, K if experts else 0, M),
                           uniform(R, num_samples, H), uniform(R, num_samples, delay,
                                                               num_features),
                           gates.to(gating["w_out"].device))


CHUNK = 500  # closed-loop steps per call of the time loop (bounds the memory of the records)


def _chunks(total: int):
    for start in range(0, total, CHUNK):
        yield min(CHUNK, total - start)


def _noise(state: ClosedLoopState, steps: int, noise_std: float, generator):
    """(R, N, steps, D) Gaussian noise on x_m, or None; drawn one step at a time so that the
    random stream does not depend on how the steps are chunked."""
    if noise_std <= 0:
        return None
    x = state.inputs[..., 0, :]
    return torch.stack([noise_std * torch.randn(x.shape, generator=generator, dtype=x.dtype)
                        for _ in range(steps)], 2).to(x.device)


def generate(experts, gating, state: ClosedLoopState, steps: int, noise_std: float = 0.0,
             generator=None, backend: Backend | None = None) -> dict[str, torch.Tensor]:
    """Run the closed loop for `steps` steps on `backend` (default: auto).

    Returns:
        outputs (R, N, T, D), gates (R, N, T, K) and gating potentials (R, N, T, H).
    """
    backend = backend or get_backend()
    parts = []
    for size in _chunks(steps):
        state, aux, _, _ = backend.closed_loop(experts, gating, state, size,
                                               _noise(state, size, noise_std, generator))
        parts.append(aux)
    return {name: torch.cat([p[i] for p in parts], 2)
            for i, name in enumerate(("outputs", "gates", "gating_u"))}


def closed_loop_lyapunov(experts, gating, state: ClosedLoopState, cfg: EvalConfig, generator,
                         on_chunk=None, backend: Backend | None = None,
                         keep_potentials: int = 0) -> torch.Tensor:
    """Lyapunov exponents (R, N, k) of the whole closed loop (spec §5.2, real gates).

    `on_chunk` receives (y, g, u^g), each (R, N, steps, ...), of every step after the transient;
    u^g is recorded only in the chunks that reach into the last `keep_potentials` steps (None in
    the others: at the paper's scale it would be gigabytes).
    """
    backend = backend or get_backend()
    noise_std = cfg.noise_var**0.5
    tangents = initial_tangents(state.flat(), cfg.num_exponents, generator)
    growth = 0
    with tqdm(total=cfg.transient + cfg.lyapunov_steps, desc="lyapunov", disable=None,
              mininterval=1.0, leave=False) as bar:
        for counted, total in ((False, cfg.transient), (True, cfg.lyapunov_steps)):
            done = 0
            for size in _chunks(total):
                keep = counted and done + size > total - keep_potentials
                state, aux, tangents, log_growth = backend.closed_loop(
                    experts, gating, state, size, _noise(state, size, noise_std, generator),
                    tangents, counted, cfg.jacobian_gates == "uniform", keep)
                growth = growth + log_growth
                if counted and on_chunk is not None:
                    on_chunk(aux)
                done += size
                bar.update(size)
    return growth / cfg.lyapunov_steps


def gate_estimates(beta: torch.Tensor | None, dataset: Dataset, num_runs: int,
                   dtype: torch.dtype) -> torch.Tensor:
    """ĝ (R, S, T, K): softmax(β) of phase 1 (Eq. 9), or the one-hot symbols of a task without
    experts (paper Sec. 3.1), shared by every run."""
    if beta is not None:
        return torch.softmax(beta, dim=-1)
    return torch.as_tensor(dataset.gate_targets, dtype=dtype).expand(num_runs, -1, -1, -1)


def _train_block_kl(estimates, closed_gates, cfg: EvalConfig) -> np.ndarray:
    """D_KL^(m)(ŝ ‖ s) per run, ŝ = argmax ĝ and s = argmax g of the closed loop from the
    trained initial states, averaged over series (Sec. 3)."""
    data, model = estimates.argmax(-1).cpu().numpy(), closed_gates.argmax(-1).cpu().numpy()
    return np.array([np.mean([block_kl(d, m, cfg.block_length, cfg.kl_floor)
                              for d, m in zip(data[r], model[r], strict=True)])
                     for r in range(len(data))])


def track_metrics(experts, estimates, gating, series, delay, cfg: EvalConfig,
                  generator, backend: Backend | None = None) -> dict[str, torch.Tensor]:
    """The cheap subset tracked during training (paper Figs. 3, 6, 11): the training-data block
    KL and the maximum Lyapunov exponent on `track_samples` × `track_steps`, per run (R,)."""
    with torch.no_grad():
        closed = generate(experts, gating,
                          trained_state(experts, gating, estimates, series, delay),
                          estimates.shape[2], backend=backend)
        small = dataclasses.replace(cfg, num_samples=cfg.track_samples,
                                    lyapunov_steps=cfg.track_steps, num_exponents=1,
                                    transient=min(cfg.transient, cfg.track_steps))
        state = random_state(experts, gating, small.num_samples, series.shape[-1], delay,
                             generator)
        lam = closed_loop_lyapunov(experts, gating, state, small, generator,
                                   backend=backend)[..., 0]
    kl = _train_block_kl(estimates, closed["gates"], cfg)
    return {"block_kl_train": torch.as_tensor(kl), "max_lyapunov": lam.mean(1).cpu()}


def _symbols(outputs, gates, dataset: Dataset, backend: Backend) -> np.ndarray:
    if dataset.prototypes is None:
        return symbolize_argmax(gates.numpy())
    return backend.nearest_symbols(outputs.numpy(), dataset.prototypes,
                                   dataset.prototype_symbols)


def evaluate(experts, beta, gating, dataset: Dataset, delay: int, period: float,
             cfg: EvalConfig, generator: torch.Generator,
             backend: Backend | None = None) -> tuple[list[dict], dict]:
    """All metrics of R trained networks, one row per run, and arrays for the figures.

    Args:
        experts, beta, gating: trained parameters (experts empty and beta None for D = 0).
        dataset: the task's data (training series, labels, test data, symbol rule).
        delay: τ; period: steps per primitive, to count repetitions (1 for symbolic tasks).
        cfg: evaluation settings; generator: random initial states and noise.

    Returns:
        rows (one dict per run) and samples (numpy arrays: the first random sample's last
        `plot_steps` outputs, gates and gating potentials, residence-time histograms).
    """
    backend = backend or get_backend()
    series = torch.as_tensor(dataset.series, dtype=gating["w_out"].dtype)
    R, K = gating["w_out"].shape[:2]
    S, L, D = series.shape
    # ---- teacher forcing: E and E^g (Sec. 3)
    estimates = gate_estimates(beta, dataset, R, series.dtype)
    if experts:
        inputs, targets = series[:, :-delay], series[:, delay:]
        outputs, _ = expert_forward(experts, inputs)
        error = objectives.mixture_mse(outputs, targets, estimates)
    else:
        inputs, error = series, torch.full((R,), float("nan"))
    T = estimates.shape[2]
    log_gates, _ = gating_forward(gating, estimates, inputs, delay)
    kl = objectives.gating_kl(log_gates, estimates[:, :, delay:])
    # ---- closed loop from the trained initial states (Sec. 4.2)
    closed = generate(experts, gating, trained_state(experts, gating, estimates, series, delay), T,
                      backend=backend)
    e_closed = (closed_loop_mse(closed["outputs"].numpy(), targets.numpy()) if experts
                else np.full(R, np.nan))
    kl_train = _train_block_kl(estimates, closed["gates"], cfg)
    # ---- random initial states: Lyapunov exponents and long symbol sequences
    recorded, kept = [], collections.deque(maxlen=-(-cfg.plot_steps // CHUNK) + 1)

    def on_chunk(aux):
        y, g, u_g = aux
        recorded.append(_symbols(y, g, dataset, backend).astype(np.int16))
        if u_g is not None:  # the first sample's last steps, (R, steps, ...), for the figures
            kept.append(tuple(a[:, 0].clone() for a in aux))

    state = random_state(experts, gating, cfg.num_samples, D, delay, generator)
    with torch.no_grad():
        exponents = closed_loop_lyapunov(experts, gating, state, cfg, generator, on_chunk,
                                         backend, keep_potentials=cfg.plot_steps)
    sampled = np.concatenate(recorded, -1)  # (R, N, steps)
    test = _test_symbols(dataset)
    rows, hist, transitions = [], [], []
    V = max(len(dataset.symbol_names), K)
    data_segments = [switching.segment_symbols(s, period) for s in _true_symbols(dataset)]
    data_switch = _switch_prob(data_segments)
    for r in range(R):
        segments = [switching.segment_symbols(s, period) for s in sampled[r]]
        lam = exponents[r].numpy()
        reps = np.concatenate([np.concatenate(list(switching.residence_times(s).values()) or
                                              [np.zeros(0, dtype=int)]) for s in segments])
        hist.append(np.bincount(reps, minlength=cfg.max_period + 1)[: cfg.max_period + 1])
        transitions.append(switching.transition_matrix(np.concatenate(segments), V))
        rows.append({
            "run": r, "E": error[r].item(), "E_g": kl[r].item() / (S * (T - delay) * K),
            "E_closed": float(e_closed[r]), "block_length": cfg.block_length,
            "block_kl_train": float(kl_train[r]),
            "block_kl_test": (block_kl(test, sampled[r], cfg.block_length, cfg.kl_floor)
                              if test is not None else float("nan")),
            "max_lyapunov": float(lam[:, 0].mean()),
            "lyapunov_positive": bool(lam[:, 0].mean() > 0),
            "positive_sample_fraction": float((lam[:, 0] > 0).mean()),
            **{f"lyapunov_{i + 1}": float(lam[:, i].mean()) for i in range(1, lam.shape[1])},
            "switch_prob": _switch_prob(segments), "data_switch_prob": data_switch,
            "mean_residence": float(reps.mean()) if len(reps) else float("nan"),
            "nonperiodic_fraction": float(np.mean([not switching.is_periodic(s, cfg.max_period)
                                                   for s in segments])),
            "noise_var": cfg.noise_var, "num_samples": cfg.num_samples,
            "lyapunov_steps": cfg.lyapunov_steps,
        })
    samples = {name: torch.cat([k[i] for k in kept], 1)[:, -cfg.plot_steps:].numpy()
               for i, name in enumerate(("outputs", "gates", "gating_u"))}
    samples.update(residence_hist=np.stack(hist), transition=np.stack(transitions),
                   closed_outputs=closed["outputs"][:, 0].numpy(),
                   symbols=sampled[:, 0, -cfg.plot_steps:])
    return rows, samples


def _switch_prob(segments) -> float:
    """Share of primitive completions followed by a different primitive."""
    changes = sum(int((s[1:] != s[:-1]).sum()) for s in segments)
    total = sum(max(len(s) - 1, 0) for s in segments)
    return changes / total if total else float("nan")


def _true_symbols(dataset: Dataset) -> list[np.ndarray]:
    if dataset.labels.min() < 0:
        return []
    return list(dataset.symbol_of[dataset.labels])


def _test_symbols(dataset: Dataset):
    """Symbols of the held-out series by the same rule as the model's outputs, or None."""
    test = dataset.test
    if test is None:
        return None
    if dataset.prototypes is None:
        return test.labels
    return symbolize_nearest(test.series, dataset.prototypes, dataset.prototype_symbols)
