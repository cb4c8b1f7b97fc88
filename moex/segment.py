"""Which expert explains which stretch of a recording: responsibilities on data the model has
not seen, the table of them (segments.csv) and their scores against labels.

On the training data the segmentation is the phase-1 estimate ĝ_n = softmax(β_n) (Eq. 9). New
data are segmented from each expert's one-step prediction y^k_n (Eqs. 1-3, teacher-forced on
the data) in one of two ways:

- `smooth` (the default): the training data's own estimate. β of the new series maximises
  Σ_n ln Σ_k softmax(β_n)_k N(y_{n+τ}; y^k_n, σ_k² I) + ln φ(β) (Eqs. 10-13) with the trained
  experts held fixed (Adam, a fixed number of steps from β = 0), and ĝ_n = softmax(β_n). It
  uses the whole series: the Brownian prior φ (scale ς) ties each step to its neighbours.
  ς is the run's own, a number, or `auto`: chosen per run by cross-validation on the data
  being segmented, the ς of PRIOR_GRID under which the steps left out of the fit are best
  predicted. The steps are split into FOLDS sets by n mod FOLDS; β is fitted with one set's
  likelihoods left out (the prior alone bridges those steps), and a left-out step scores
  ln Σ_k softmax(β_n)_k N(y_{n+τ}; y^k_n, σ_k² I). Too small a ς cannot follow the switches,
  too large a one follows every step's noise and bridges the gaps badly.
- `filter`: causal, with the gating network's opening g_n (Eqs. 5-8) run on the data as the
  prior of the mixture's posterior,

      r^k_n = g^k_n N(y_{n+τ}; y^k_n, σ_k² I) / Σ_j g^j_n N(y_{n+τ}; y^j_n, σ_j² I),

  where r_n takes the place of ĝ_n in the gating network's feedback (it is fed r_{n-τ} and
  x_{n-τ} as it was fed ĝ_{n-τ} and x_{n-τ} in phase 2); g_n = 1/K for n < τ. Usable online;
  it follows a switch only once the data tell the experts apart, so it lags where primitives
  meet.

Both networks start from the mean of their trained initial states over the training series, so
the first steps are a transient.
"""

import math
from typing import NamedTuple

import numpy as np
import pandas as pd
import torch

from moex.metrics import switching
from moex.metrics.segmentation import scores
from moex.model import expert_forward, expert_variances, gate_estimates, leaky_scan
from moex.objectives import expert_log_densities, gate_prior_log_density


def _from_mean_state(params: dict[str, torch.Tensor], num_series: int) -> dict:
    """The parameters with u0 (R, S, ...) replaced by its mean over the S training series,
    repeated for `num_series` new ones."""
    u0 = params["u0"].mean(1, keepdim=True)
    return {**params, "u0": u0.expand(u0.shape[0], num_series, *u0.shape[2:]).contiguous()}


def log_likelihoods(experts, series: torch.Tensor, delay: int,
                    sigma_min: float) -> torch.Tensor:
    """ln N(y_{n+τ}; y^k_n, σ_k² I) of every expert (R, S, T - τ, K) on series (S, T, D)."""
    experts = _from_mean_state(experts, series.shape[0])
    outputs, _ = expert_forward(experts, series[:, :-delay])  # (R, S, N, K, D)
    return expert_log_densities(outputs, series[:, delay:],
                                expert_variances(experts, sigma_min))


METHODS = ("smooth", "filter")
PRIOR_GRID = 2.0 ** np.arange(-2, 5)  # the ς `auto` tries: 0.25, 0.5, ..., 16
FOLDS = 2  # `auto`'s cross-validation: step n is left out in fold n mod FOLDS


class Responsibilities(NamedTuple):
    """Each expert's responsibility (R, S, N, K) and, for `smooth`, the ς each run used (R,)."""

    gates: torch.Tensor
    prior_std: np.ndarray | None


def responsibilities(experts, gating, series: torch.Tensor, delay: int, *, sigma_min: float,
                     method: str = "smooth", prior_std: float | str = 10.0,
                     steps: int = 500) -> Responsibilities:
    """Each expert's responsibility (R, S, T - τ, K) for the steps of series (S, T, D) in
    model units, by `method` (the module's docstring): `prior_std` is ς (a number, or `auto`)
    and `steps` the optimiser's steps of `smooth`."""
    with torch.no_grad():
        log_p = log_likelihoods(experts, series.to(experts["w_in"].dtype), delay, sigma_min)
    if method == "smooth":
        stds = (chosen_prior_std(log_p, steps)[0] if prior_std == "auto"
                else np.full(len(log_p), float(prior_std)))
        gates = torch.empty_like(log_p)
        for std in np.unique(stds):  # one fit for the runs of one ς
            runs = torch.as_tensor(np.flatnonzero(stds == std))
            gates[runs] = smoothed(log_p[runs], float(std), steps)
        return Responsibilities(gates, stds)
    with torch.no_grad():
        R, S, N, K = log_p.shape
        gating = _from_mean_state(gating, S)
        eps, bias = 1 / gating["tau"][:, None], gating["b_c"][:, None]
        inputs = series.to(log_p.dtype).expand(R, *series.shape)
        u, log_g = gating["u0"], torch.full((R, S, K), -math.log(K), dtype=log_p.dtype)
        out = torch.empty_like(log_p)
        for n in range(N):
            if n >= delay:  # the gating network fed r_{n-τ} and x_{n-τ} (Eqs. 5-8)
                feed = torch.cat([out[:, :, n - delay], inputs[:, :, n - delay]], -1)
                drive = torch.einsum("rhi,rsi->rsh", gating["w_in"], feed)[:, None]
                u, c = leaky_scan(drive, gating["w_rec"], eps, bias, u)
                u, c = u[:, 0], c[:, 0]
                log_g = torch.log_softmax(torch.einsum("rkh,rsh->rsk", gating["w_out"], c)
                                          + gating["b_o"][:, None], -1)
            out[:, :, n] = torch.softmax(log_g + log_p[:, :, n], -1)
        return Responsibilities(out, None)


def smoothed(log_p: torch.Tensor, prior_std: float, steps: int = 500) -> torch.Tensor:
    """ĝ (R, S, N, K) of the `smooth` method from the experts' log-likelihoods (R, S, N, K)."""
    return torch.softmax(_map_beta(log_p, prior_std, steps), -1)


def chosen_prior_std(log_p: torch.Tensor, steps: int = 500) -> tuple[np.ndarray, np.ndarray]:
    """`auto`'s ς per run (R,) from the experts' log-likelihoods (R, S, N, K), and the
    cross-validation's table (R, len(PRIOR_GRID)): the left-out steps' summed ln Σ_k ĝ^k p^k
    (the module's docstring)."""
    R, S, N, K = log_p.shape
    held = torch.arange(N) % FOLDS == torch.arange(FOLDS)[:, None]  # (F, N)
    masked = torch.where(held[:, None, None, :, None], 0.0, log_p).reshape(FOLDS * R, S, N, K)
    every = log_p.repeat(FOLDS, 1, 1, 1)
    scored = held.repeat_interleave(R, 0)[:, None]  # (F R, 1, N)
    table = []
    for std in PRIOR_GRID:
        beta = _map_beta(masked, float(std), steps)
        predicted = torch.logsumexp(torch.log_softmax(beta, -1) + every, -1)  # (F R, S, N)
        table.append((predicted * scored).reshape(FOLDS, R, S, N).sum((0, 2, 3)))
    table = torch.stack(table, 1).numpy()
    return PRIOR_GRID[table.argmax(1)], table


def _map_beta(log_p: torch.Tensor, prior_std: float, steps: int,
              rate: float = 0.1) -> torch.Tensor:
    """β (R, S, N, K) maximising Σ ln Σ_k softmax(β_n)_k p^k_n + ln φ(β) (Eqs. 10-13), Adam
    from β = 0, for log-likelihoods (R, S, N, K)."""
    beta = torch.zeros_like(log_p, requires_grad=True)
    adam = _Adam(beta, rate)
    for _ in range(steps):
        objective = (torch.logsumexp(torch.log_softmax(beta, -1) + log_p, -1).sum()
                     + gate_prior_log_density(beta, prior_std).sum())
        adam.step(torch.autograd.grad(-objective, beta)[0])
    return beta.detach()


class _Adam:
    """`torch.optim.Adam(params=[x], lr=rate)`'s step, bit for bit (its single-tensor form,
    the one it takes on the CPU; tests/test_segment.py compares them), without the optimiser:
    constructing any `torch.optim` optimiser imports TorchDynamo, 2 s of every evaluation."""

    BETAS, EPS = (0.9, 0.999), 1e-8

    def __init__(self, x: torch.Tensor, rate: float):
        self.x, self.rate, self.steps = x, rate, 0
        self.mean, self.square = torch.zeros_like(x), torch.zeros_like(x)

    @torch.no_grad()
    def step(self, grad: torch.Tensor) -> None:
        (b1, b2), self.steps = self.BETAS, self.steps + 1
        self.mean.lerp_(grad, 1 - b1)
        self.square.mul_(b2).addcmul_(grad, grad, value=1 - b2)
        size = self.rate / (1 - b1 ** float(self.steps))
        denom = (self.square.sqrt() / (1 - b2 ** float(self.steps)) ** 0.5).add_(self.EPS)
        self.x.addcdiv_(self.mean, denom, value=-size)


def table(gates: np.ndarray, labels: np.ndarray | None, delay: int) -> pd.DataFrame:
    """segments.csv: one row per run, series and step (the data step the gates explain, n + τ),
    the winning expert, every expert's responsibility (gate_k) and the label where known."""
    R, S, N, K = gates.shape
    run, series, step = np.meshgrid(np.arange(R), np.arange(S), np.arange(N) + delay,
                                    indexing="ij")
    frame = pd.DataFrame({"run": run.ravel(), "series": series.ravel(), "step": step.ravel(),
                          "expert": gates.argmax(-1).ravel()})
    if labels is not None and (labels >= 0).any():
        frame["label"] = np.broadcast_to(labels[None, :, delay:], (R, S, N)).ravel()
    for k in range(K):
        frame[f"gate_{k}"] = gates[..., k].ravel()
    return frame


def _scored(gates: np.ndarray, labels: np.ndarray, delay: int) -> list[dict]:
    """Per run: `moex.metrics.segmentation.scores` of the winning expert against the labels of
    the steps it explains (labels (S, T), -1 unknown), the matching included; [] where no step
    is labelled."""
    truth = labels[:, delay:]
    if not (truth >= 0).any():
        return []
    return [scores(truth, run_gates.argmax(-1), run_gates.shape[-1]) for run_gates in gates]


def _numbers(run: dict, suffix: str = "") -> dict:
    """A run's scores as metrics.csv columns (the matching left out)."""
    return {f"{k}{suffix}": float(v) for k, v in run.items() if k != "label_of_expert"}


def run_scores(gates: np.ndarray, labels: np.ndarray, delay: int,
               suffix: str = "") -> list[dict]:
    """Per run: ARI, NMI and matched accuracy of the winning expert against the labels of the
    steps it explains (labels (S, T), -1 unknown); an empty dict per run where no step is
    labelled."""
    return [_numbers(run, suffix) for run in _scored(gates, labels, delay) or [{} for _ in gates]]


def evaluation_scores(experts, beta, gating, dataset, *, delay: int, sigma_min: float,
                      prior_std: float, closed_winners: np.ndarray | None = None,
                      block_kl=None) -> tuple[list[dict], np.ndarray | None]:
    """Per run, where the data have labels: the segmentation of the training series by ĝ
    (segment_ari, segment_nmi, segment_accuracy), of the held-out series by the `smooth`
    method (the same with _test) and, given the closed loop's winning experts (R, N, steps)
    and the evaluation's block KL, the closed loop read as labels (`closed_loop_labels`): its
    scores join the rows, its stays per label come back as (R, labels + 1, 4) (else None)."""
    R = len(gating["w_out"])
    found = [] if beta is None else _scored(gate_estimates(beta).numpy(), dataset.labels, delay)
    if not found:  # no labelled step the experts explain
        return [{} for _ in range(R)], None
    rows = [_numbers(run) for run in found]
    test = dataset.test
    if test is not None and (test.labels >= 0).any():
        gates, _ = responsibilities(experts, gating, torch.as_tensor(test.series), delay,
                                    sigma_min=sigma_min, prior_std=prior_std)
        for row, more in zip(rows, run_scores(gates.numpy(), test.labels, delay, "_test"),
                             strict=True):
            row.update(more)
    if closed_winners is None:
        return rows, None
    stays = []
    for r, (row, run) in enumerate(zip(rows, found, strict=True)):
        closed, per_label = closed_loop_labels(closed_winners[r], dataset.labels,
                                               run["label_of_expert"], block_kl)
        row.update(closed)
        stays.append(per_label)
    return rows, np.stack(stays)


def _known_stretches(labels: np.ndarray) -> list[np.ndarray]:
    """The stretches of each series (S, T) between unknown (-1) steps."""
    out = []
    for series in labels:
        parts = (part[part >= 0] for part in np.split(series, np.flatnonzero(series < 0)))
        out += [part for part in parts if len(part)]
    return out


def closed_loop_labels(winners: np.ndarray, labels: np.ndarray, label_of_expert: np.ndarray,
                       block_kl) -> tuple[dict, np.ndarray]:
    """The closed loop's winning experts (N, steps) read as labels through the training data's
    matching of experts to labels (an unmatched expert a label of its own): the block KL of the
    data's label sequence (S, T) against them (data first, Eq. 21 on per-step labels), and the
    mean stay on one label in steps, the closed loop's beside the data's (every stay counted,
    those cut by a sequence's end at their observed length); and per label (the last row: the
    unmatched experts), (labels + 1, 4): the data's and the closed loop's mean stay and their
    shares of the steps (NaN stays where a label never occurs)."""
    unmatched = int(labels.max()) + 1
    read = np.where(label_of_expert >= 0, label_of_expert, unmatched)[winners]
    data = _known_stretches(labels)
    both = [_stays(data), _stays(read)]  # (label of each stay, its length): data, closed loop

    def of_label(k):
        mean = [n[v == k].mean() if (v == k).any() else np.nan for v, n in both]
        return mean + [n[v == k].sum() / n.sum() for v, n in both]

    return ({"label_block_kl": block_kl(data, list(read)),
             "label_mean_stay": float(both[1][1].mean()),
             "data_label_mean_stay": float(both[0][1].mean())},
            np.array([of_label(k) for k in range(unmatched + 1)]))


def _stays(sequences) -> tuple[np.ndarray, np.ndarray]:
    """The label and the length of every stay in some label sequences."""
    values, lengths = zip(*map(switching.rle, sequences), strict=True)
    return np.concatenate(values), np.concatenate(lengths)


LABEL_STAYS = ("data_mean_stay", "loop_mean_stay", "data_share", "loop_share")


def label_stays_table(stays: np.ndarray) -> pd.DataFrame:
    """label_stays.csv: per run and label (the last, "unmatched", the experts no label was
    matched to) the data's and the closed loop's mean stay in steps and share of the steps."""
    R, L, _ = stays.shape
    return pd.DataFrame([{"run": r, "label": "unmatched" if k == L - 1 else str(k),
                          **dict(zip(LABEL_STAYS, stays[r, k].tolist(), strict=True))}
                         for r in range(R) for k in range(L)])


class Segmentation(NamedTuple):
    """segments.csv's table and, where labels are known, one row of scores per run and each
    run's matching of experts to labels (the label of expert k, -1 unmatched); else an empty
    frame and an empty list."""

    table: pd.DataFrame
    scores: pd.DataFrame
    label_of_expert: list[np.ndarray]


def segmentation(gates: np.ndarray, labels: np.ndarray | None, delay: int) -> Segmentation:
    """The table and scores of responsibilities (R, S, N, K) against labels (S, T) or None."""
    found = _scored(gates, labels, delay) if labels is not None else []
    scores_ = pd.DataFrame([{"run": r, **_numbers(run)} for r, run in enumerate(found)])
    return Segmentation(table(gates, labels, delay), scores_,
                        [run["label_of_expert"] for run in found])
