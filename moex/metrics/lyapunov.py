"""Lyapunov exponents by tangent propagation with QR re-orthonormalisation (Benettin et al.
1980), batched over leading axes (runs × samples): `benettin` is the loop the closed loop of the
mixture (`moex.closed_loop.closed_loop_lyapunov`) and `lyapunov_exponents` of any map share."""

from collections.abc import Callable

import numpy as np
import torch

from moex.draws import Generators, draw
from moex.errors import never, stop_if_asked

# (tangents (B..., dim, k), steps, counted, done) -> (tangents, Σ ln |R_vv| over those steps)
Advance = Callable[[torch.Tensor, int, bool, int], tuple[torch.Tensor, torch.Tensor]]


def initial_tangents(state: torch.Tensor, num_exponents: int,
                     generator: Generators = None) -> torch.Tensor:
    """k random orthonormal tangent vectors (B..., dim, k) per trajectory of `state` (B..., dim);
    with a list of generators, one per entry of B's first axis (a run's own)."""
    shape = state.shape[:-1] + (state.shape[-1], num_exponents)
    tangents = draw(torch.randn, shape, generator).to(state)
    return torch.linalg.qr(tangents)[0]


def reorthonormalise(tangents: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """One Benettin step: QR of the tangents (B..., dim, k); returns Q and ln |R_vv| (B..., k),
    the log growth of each direction since the last step."""
    q, r = torch.linalg.qr(tangents)
    return q, torch.log(torch.diagonal(r, dim1=-2, dim2=-1).abs())


def chunks(total: int, size: int):
    """(steps done before, steps) of each chunk of at most `size` steps of `total`."""
    for done in range(0, total, size):
        yield done, min(size, total - done)


def benettin(advance: Advance, tangents: torch.Tensor, steps: int, *, transient: int, chunk: int,
             stop: Callable[[], bool] = never) -> torch.Tensor:
    """The first k exponents per trajectory (B..., k), per step (natural log): `transient` steps
    align the tangents, the log growth of the next `steps` is averaged.

    Args:
        advance: runs the map with its tangents for a number of steps (at most `chunk`),
            re-orthonormalising them (every step, or at least at the end), and returns the
            tangents and the summed ln |R_vv|; `counted` says whether the steps are averaged,
            `done` how many of this stretch came before.
        tangents: (B..., dim, k) orthonormal (`initial_tangents`).
        stop: asked before every chunk; `Interrupted` when it says so.
    """
    growth = 0
    for counted, total in ((False, transient), (True, steps)):
        for done, size in chunks(total, chunk):
            stop_if_asked(stop, "the Lyapunov exponents were")
            tangents, log_growth = advance(tangents, size, counted, done)
            if counted:
                growth = growth + log_growth
    return growth / steps


def lyapunov_exponents(step: Callable[[torch.Tensor], torch.Tensor], state: torch.Tensor,
                       num_steps: int, *, num_exponents: int = 1, transient: int = 0,
                       reorth_every: int = 1,
                       generator: torch.Generator | None = None) -> torch.Tensor:
    """The first k Lyapunov exponents of any map x_{n+1} = f(x_n), per trajectory, through the
    loop the mixture's exponents use (`benettin`); the Jacobian-vector products are exact
    forward-mode derivatives (`torch.func.jvp`).

    Args:
        step: f on (B..., dim).
        state: (B..., dim) initial states, one trajectory each.
        num_steps: steps averaged over, after `transient` steps that align the tangents.
        num_exponents: k <= dim; k = 1 gives the maximum exponent.
        reorth_every: steps between QR re-orthonormalisations.
        generator: draws the random initial tangent vectors.

    Returns:
        (B..., k) exponents per step (natural log), in descending order.
    """
    def advance(tangents, size, counted, done):
        nonlocal state
        for _ in range(size):
            columns = [torch.func.jvp(step, (state,), (v,)) for v in tangents.unbind(-1)]
            state, tangents = columns[0][0], torch.stack([c[1] for c in columns], -1)
        return reorthonormalise(tangents)

    return benettin(advance, initial_tangents(state, num_exponents, generator), num_steps,
                    transient=transient, chunk=reorth_every)


CHAOTIC, NOT_CHAOTIC, UNDETERMINED = "chaotic", "not chaotic", "undetermined"
CHAOS_LABELS = (CHAOTIC, UNDETERMINED, NOT_CHAOTIC)


def chaos_margin(se: float, steps: int, z: float = 2.0) -> float:
    """How far from 0 an estimate of λ_max must lie for its sign to count: z standard errors
    (sd of the samples' own exponents / √samples), and at least 1/steps, the resolution of a
    `steps`-step estimate (one e-fold over the whole trajectory: a tangent whose norm merely
    oscillates on a limit cycle moves the estimate by about that much). Infinite where the error
    is unknown (one sample)."""
    return max(z * se, 1.0 / steps) if np.isfinite(se) else np.inf


def chaos_label(mean: float, se: float, steps: int, z: float = 2.0) -> str:
    """*chaotic* where λ_max is above 0 by more than `chaos_margin`, *not chaotic* where below
    by as much, *undetermined* in between (the paper's own criterion, λ_max > 0, ignores the
    error: it is the column `lyapunov_positive`); "" for a network without an estimate."""
    if not np.isfinite(mean):
        return ""
    margin = chaos_margin(se, steps, z)
    return CHAOTIC if mean > margin else NOT_CHAOTIC if mean < -margin else UNDETERMINED


def standard_error(samples: np.ndarray) -> float:
    """sd of the samples' own exponents / √samples (NaN for one sample)."""
    return float(samples.std(ddof=1) / len(samples) ** 0.5) if len(samples) > 1 else np.nan


def chaos_labels(frame) -> "pd.Series":  # noqa: F821 (pandas is imported by the caller)
    """The label of every row of a metrics table: its `chaos` column where the evaluation wrote
    one, else computed from max_lyapunov, max_lyapunov_se and lyapunov_steps (older tables, or
    older rows of a table that gained the column; without a standard error a row is
    undetermined)."""
    import pandas as pd

    se = frame["max_lyapunov_se"] if "max_lyapunov_se" in frame else pd.Series(np.nan, frame.index)
    steps = frame["lyapunov_steps"] if "lyapunov_steps" in frame else pd.Series(100000,
                                                                                frame.index)
    computed = pd.Series([chaos_label(m, s, int(t) if np.isfinite(t) else 1) for m, s, t in
                          zip(frame["max_lyapunov"], se, steps.astype(float), strict=True)],
                         index=frame.index, dtype=object)
    if "chaos" not in frame:
        return computed
    written = frame["chaos"].astype(object)
    return written.where(written.notna() & (written != ""), computed)
