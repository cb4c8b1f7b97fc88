"""The metric table of a trained mixture (paper Sec. 3-4), one row per run: teacher-forced E and
E^g; E^closed and the block KL from the trained initial states; from random initial states the
Lyapunov exponents, the test-data block KL, switching statistics and periodicity. Metrics a task
cannot have (E without experts, E^closed without a signal, test KL without held-out series,
switching of the data without true labels) are left out of its table."""

import collections
from typing import NamedTuple

import numpy as np
import torch

from moex import objectives, segment
from moex.closed_loop import (
    CHUNK,
    closed_loop_lyapunov,
    generate,
    trained_state,
)
from moex.config.evaluation import SYMBOL_RULES, EvalConfig
from moex.draws import Generators
from moex.errors import never
from moex.kernels import Backend
from moex.metrics import switching
from moex.metrics.errors import closed_loop_mse
from moex.metrics.lyapunov import UNDETERMINED, chaos_label, standard_error
from moex.metrics.symbols import (
    symbolize_argmax,
    symbolize_threshold,
)
from moex.metrics.table import NOISY
from moex.model import expert_forward, gate_estimates, gating_forward, random_state
from moex.tasks import Dataset
from moex.train import phase2_targets

SYMBOLIZERS = dict(zip(SYMBOL_RULES, (symbolize_argmax, symbolize_threshold), strict=True))


class Evaluation(NamedTuple):
    """rows: one dict of metrics per run; samples: numpy arrays for the figures and
    samples.npz (the first sample's last `plot_steps` steps of every run, residence-time
    histograms, transition matrices, the closed loop from series 0's trained state)."""

    rows: list[dict]
    samples: dict


def _train_block_kl(targets, closed_gates, cfg: EvalConfig) -> np.ndarray:
    """D_KL^(m)(ŝ ‖ s) per run, ŝ = argmax ĝ and s = argmax g of the closed loop from the
    trained initial states, averaged over series (Sec. 3)."""
    rule = SYMBOLIZERS[cfg.symbol_rule]
    data, model = rule(targets.cpu().numpy()), rule(closed_gates.cpu().numpy())
    return np.array([np.mean([cfg.block_kl(d, m) for d, m in zip(data[r], model[r],
                                                                  strict=True)])
                     for r in range(len(data))])


def track_metrics(experts, targets, gating, series, delay, *, cfg: EvalConfig, generator,
                  backend: Backend) -> dict[str, torch.Tensor]:
    """The cheap subset tracked during training (paper Figs. 3, 6, 11): the training-data block
    KL and the maximum Lyapunov exponent on `track_samples` × `track_steps` with its standard
    error over those samples (NaN for one sample), per run (R,)."""
    with torch.no_grad():
        closed = generate(experts, gating, trained_state(experts, gating, targets, series,
                                                         delay=delay),
                          targets.shape[2], backend=backend)
        state = random_state(experts, gating, cfg.track_samples, num_features=series.shape[-1],
                             delay=delay, generator=generator)
        lam = closed_loop_lyapunov(experts, gating, state, cfg.track_steps,
                                   min(cfg.transient, cfg.track_steps), generator=generator,
                                   backend=backend)[..., 0]
    kl = _train_block_kl(targets, closed["gates"], cfg)
    lam = lam.cpu()
    se = torch.tensor([standard_error(row.numpy()) for row in lam], dtype=lam.dtype)
    return {"block_kl_train": torch.as_tensor(kl), "max_lyapunov": lam.mean(1),
            "max_lyapunov_se": se}


def _teacher_forced(experts, beta, gating, series, *, delay, targets):
    """E (Sec. 3, with ĝ) per run, or None without experts, and E^g against the phase-2
    targets."""
    R, S, T, K = targets.shape
    if experts:
        outputs, _ = expert_forward(experts, series[:, :-delay])
        error = objectives.mixture_mse(outputs, series[:, delay:], gate_estimates(beta))
    inputs = series[:, :-delay] if experts else series
    log_gates, _ = gating_forward(gating, targets, inputs, delay)
    kl = objectives.gating_kl(log_gates, targets[:, :, delay:])
    return (error if experts else None), kl / (S * (T - delay) * K)


def _switching_columns(symbols, winners, dataset: Dataset, cfg: EvalConfig) -> tuple:
    """Per run: switching probability per completed lap (Table 2) from the outputs and from the
    winning gates, switches per period of time, repetitions, periodicity (Sec. 4.3) of the
    samples with enough laps to judge it; then the laps, the completed stays and the stays cut
    off by a sample's end."""
    period = dataset.period
    segments = [switching.segment_symbols(s, period) for s in symbols]

    def stays(censored):
        return np.concatenate([np.zeros(0, dtype=np.int64)] + [
            length for s in segments
            for length in switching.residence_times(s, censored).values()])

    reps, cut = stays(False), stays(True)
    every = np.concatenate([reps, cut])
    nonperiodic, judged = switching.nonperiodic_share(segments, cfg.max_period)
    return {
        "switch_prob": switching.switch_probability(segments),
        "switch_prob_gates": switching.switch_probability(
            [switching.segment_symbols(s, period) for s in winners]),
        "switch_rate": switching.switch_rate(symbols, period),
        # every stay, those cut off by a sample's end at their observed length (a lower bound)
        "mean_residence": float(every.mean()) if len(every) else float("nan"),
        "censored_stays": len(cut),
        "nonperiodic_fraction": nonperiodic,
        "periodicity_samples": judged,
    }, segments, reps, cut


def evaluate(experts, beta, gating, dataset: Dataset, delay: int, *, cfg: EvalConfig,
             generator: Generators, backend: Backend, target_temperature: float = 1.0,
             stop=never, sigma_min: float = 0.05, gate_prior_std: float = 10.0
             ) -> Evaluation:
    """All metrics of R trained networks, one row per run, and arrays for the figures.

    Args:
        experts, beta, gating: trained parameters (experts empty and beta None for D = 0).
        dataset: the task's data (training series, labels, test data, symbol rule, period).
        delay: τ; cfg: evaluation settings; generator: random initial states, tangents and
            noise (a list of one per run: run r's then do not depend on the other runs).
        backend: where the closed loop runs; target_temperature: that of the phase-2 targets
            (E^g is measured against the targets the gating RNN was fitted to).
        stop: asked between chunks of the closed loop (`Interrupted` when True).
        sigma_min, gate_prior_std: σ̄ and ς of the trained model (the held-out series'
            segmentation, `moex.segment`).
    """
    series = torch.as_tensor(dataset.series, dtype=gating["w_out"].dtype)
    R, K = gating["w_out"].shape[:2]
    S, L, D = series.shape
    targets = phase2_targets(beta, dataset, R, series.dtype, target_temperature)
    error, error_g = _teacher_forced(experts, beta, gating, series, delay=delay, targets=targets)
    # ---- closed loop from the trained initial states (Sec. 4.2)
    closed = generate(experts, gating, trained_state(experts, gating, targets, series, delay=delay),
                      targets.shape[2], backend=backend, stop=stop)
    kl_train = _train_block_kl(targets, closed["gates"], cfg)
    # ---- random initial states: Lyapunov exponents and long symbol sequences
    recorded, winners = [], []  # per-step symbols and winning gates, (R, N, steps) per chunk
    kept = collections.deque(maxlen=-(-cfg.plot_steps // CHUNK) + 1)

    def on_chunk(run):
        recorded.append((dataset.symbolize(run.outputs.numpy(), run.gates.numpy(),
                                           backend.nearest_symbols)
                         if dataset.prototypes is not None else SYMBOLIZERS[cfg.symbol_rule](
                             run.gates.numpy())).astype(np.int16))
        winners.append(symbolize_argmax(run.gates.numpy()).astype(np.int16))
        if run.gating_u is not None:  # the first sample's last steps, for the figures
            kept.append(tuple(a[:, 0].clone() for a in (run.outputs, run.gates, run.gating_u)))

    if cfg.initial_states == "trained":  # sample n from series n mod S's trained state
        state = trained_state(experts, gating, targets, series, delay=delay,
                              rows=[n % S for n in range(cfg.num_samples)])
    else:
        state = random_state(experts, gating, cfg.num_samples, num_features=D, delay=delay,
                             generator=generator)
    uniform = cfg.jacobian_gates == "uniform"
    with torch.no_grad():  # the paper's λ_max is that of the noiseless loop; with noise (which
        # only judges periodicity, Sec. 4.3) a second pass from the same initial states records
        # the symbols: the first pass draws exactly what an evaluation without noise draws
        common = dict(generator=generator, num_exponents=cfg.num_exponents,
                      uniform_gates=uniform, keep_potentials=cfg.plot_steps, backend=backend,
                      stop=stop)
        exponents = closed_loop_lyapunov(
            experts, gating, state.like(state.flat().clone()), cfg.lyapunov_steps, cfg.transient,
            on_chunk=None if cfg.noise_var > 0 else on_chunk, **common).numpy()
        noisy = None if cfg.noise_var == 0 else closed_loop_lyapunov(
            experts, gating, state, cfg.lyapunov_steps, cfg.transient,
            noise_std=cfg.noise_var**0.5, on_chunk=on_chunk, **common).numpy()
        exponents = _decided(exponents, cfg, lambda: closed_loop_lyapunov(
            experts, gating, random_state(experts, gating, cfg.num_samples, num_features=D,
                                          delay=delay, generator=generator),
            cfg.lyapunov_steps, cfg.transient, **common).numpy())
    sampled, gate_winners = np.concatenate(recorded, -1), np.concatenate(winners, -1)
    test = _test_symbols(dataset, backend)
    truth = _true_symbols(dataset)
    rows, hist, censored_hist, transitions = [], [], [], []
    # (the threshold rule's symbol K: no gate above 0.5)
    V = max(len(dataset.symbol_names), K) + (cfg.symbol_rule == "threshold"
                                             and dataset.prototypes is None)
    for r in range(R):
        lam = exponents[r]
        columns, segments, reps, cut = _switching_columns(sampled[r], gate_winners[r], dataset,
                                                          cfg)
        hist.append(_histogram(reps, cfg.max_period))
        censored_hist.append(_histogram(cut, cfg.max_period))
        transitions.append(switching.transition_matrix(np.concatenate(segments), V))
        row = {"run": r}
        if error is not None:
            row["E"] = error[r].item()
        row["E_g"] = error_g[r].item()
        if D > 0:
            row["E_closed"] = float(closed_loop_mse(closed["outputs"][r].numpy(),
                                                    series[:, delay:].numpy()))
        row.update(block_length=cfg.block_length, block_kl_train=float(kl_train[r]))
        if test is not None:
            row["block_kl_test"] = cfg.block_kl(test, sampled[r])
        se = standard_error(lam[:, 0])
        row.update({
            "max_lyapunov": float(lam[:, 0].mean()),
            "max_lyapunov_se": se,
            "chaos": chaos_label(lam[:, 0].mean(), se, cfg.lyapunov_steps, cfg.chaos_z),
            "lyapunov_positive": bool(lam[:, 0].mean() > 0),
            "positive_sample_fraction": float((lam[:, 0] > 0).mean()),
            **{f"lyapunov_{i + 1}": float(lam[:, i].mean()) for i in range(1, lam.shape[1])},
            **columns,
        })
        if noisy is not None:
            row.update(max_lyapunov_noisy=float(noisy[r, :, 0].mean()),
                       noise_enters=" ".join(NOISY))
        if truth:
            row["data_switch_prob"] = switching.switch_probability(
                [switching.segment_symbols(s, dataset.period) for s in truth])
        row.update(noise_var=cfg.noise_var, num_samples=cfg.num_samples,
                   lyapunov_samples=len(lam), lyapunov_steps=cfg.lyapunov_steps)
        rows.append(row)
    scores, stays = segment.evaluation_scores(experts, beta, gating, dataset, delay=delay,
                                              sigma_min=sigma_min, prior_std=gate_prior_std,
                                              closed_winners=gate_winners, block_kl=cfg.block_kl)
    for row, more in zip(rows, scores, strict=True):
        row.update(more)
    samples = {name: torch.cat([k[i] for k in kept], 1)[:, -cfg.plot_steps:].numpy()
               for i, name in enumerate(("outputs", "gates", "gating_u"))}
    samples.update(residence_hist=np.stack(hist), residence_censored_hist=np.stack(censored_hist),
                   transition=np.stack(transitions),
                   closed_outputs=closed["outputs"][:, 0].numpy(),
                   symbols=sampled[:, 0, -cfg.plot_steps:])
    if stays is not None:  # per label: (R, labels + 1, 4), label_stays.csv
        samples["label_stays"] = stays
    return Evaluation(rows, samples)


def _decided(exponents: np.ndarray, cfg: EvalConfig, more) -> list[np.ndarray]:
    """Each run's exponents (samples, k), with further samples for the runs whose chaos label
    is undetermined: `more()` draws num_samples more per run, (R, num_samples, k), until every
    label is decided or a run holds eval.decide_samples samples (those more samples only judge
    λ_max; the symbol statistics keep the first num_samples)."""
    runs = list(exponents)

    def undetermined(lam):
        return chaos_label(lam[:, 0].mean(), standard_error(lam[:, 0]), cfg.lyapunov_steps,
                           cfg.chaos_z) == UNDETERMINED

    while True:
        open_runs = [r for r, lam in enumerate(runs)
                     if undetermined(lam) and len(lam) + cfg.num_samples <= cfg.decide_samples]
        if not open_runs:
            return runs
        extra = more()
        for r in open_runs:
            runs[r] = np.concatenate([runs[r], extra[r]])


def _histogram(lengths: np.ndarray, top: int) -> np.ndarray:
    """(top + 1,) counts of each length, lengths beyond `top` in the last bin."""
    return np.bincount(np.minimum(lengths, top), minlength=top + 1)


def _true_symbols(dataset: Dataset) -> list[np.ndarray]:
    """The true symbol of every step of every training series ([] when unknown)."""
    if dataset.labels.min() < 0 or not len(dataset.symbol_of):  # a user's labels: no symbols
        return []
    return list(dataset.symbol_of[dataset.labels])


def _test_symbols(dataset: Dataset, backend: Backend):
    """Symbols of the held-out series by the same rule as the model's outputs, or None."""
    test = dataset.test
    if test is None:
        return None
    if dataset.prototypes is None:
        return test.labels
    return dataset.symbolize(test.series, None, backend.nearest_symbols)
