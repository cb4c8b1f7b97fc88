"""Lyapunov exponents of any step map by tangent propagation with QR re-orthonormalisation
(Benettin et al. 1980), batched over leading axes (runs × samples)."""

from collections.abc import Callable

import torch

TangentStep = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


def jvp_step(step: Callable[[torch.Tensor], torch.Tensor]) -> TangentStep:
    """Lift a map x_{n+1} = f(x_n) on (B..., dim) to (x, V) -> (f(x), J_f(x) V).

    V is (B..., dim, k); the Jacobian-vector products are exact forward-mode derivatives
    (torch.func.jvp). The closed loop of the mixture has its own hand-written tangent map
    (`moex.model.closed_loop_step`).
    """

    def tangent_step(state, tangents):
        columns = [torch.func.jvp(step, (state,), (v,)) for v in tangents.unbind(-1)]
        return columns[0][0], torch.stack([c[1] for c in columns], dim=-1)

    return tangent_step


def initial_tangents(state: torch.Tensor, num_exponents: int,
                     generator: torch.Generator | None = None) -> torch.Tensor:
    """k random orthonormal tangent vectors (B..., dim, k) per trajectory of `state` (B..., dim)."""
    shape = state.shape[:-1] + (state.shape[-1], num_exponents)
    tangents = torch.randn(shape, generator=generator, dtype=torch.float64).to(state)
    return torch.linalg.qr(tangents)[0]


def reorthonormalise(tangents: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """One Benettin step: QR of the tangents (B..., dim, k); returns Q and ln |R_vv| (B..., k),
    the log growth of each direction since the last step."""
    q, r = torch.linalg.qr(tangents)
    return q, torch.log(torch.diagonal(r, dim1=-2, dim2=-1).abs())


def lyapunov_exponents(tangent_step: TangentStep, state: torch.Tensor, num_steps: int,
                       num_exponents: int = 1, transient: int = 0, reorth_every: int = 1,
                       generator: torch.Generator | None = None) -> torch.Tensor:
    """The first k Lyapunov exponents of x_{n+1} = f(x_n), per trajectory.

    Args:
        tangent_step: (x, V) -> (f(x), J V), see `jvp_step`.
        state: (B..., dim) initial states, one trajectory each.
        num_steps: steps averaged over, after `transient` steps that align the tangents.
        num_exponents: k <= dim; k = 1 gives the maximum exponent.
        reorth_every: steps between QR re-orthonormalisations (1 = every step).
        generator: draws the random initial tangent vectors.

    Returns:
        (B..., k) exponents per step (natural log), in descending order.
    """
    tangents = initial_tangents(state, num_exponents, generator)
    log_growth = torch.zeros(state.shape[:-1] + (num_exponents,), dtype=state.dtype,
                             device=state.device)
    total = transient + num_steps
    for n in range(total):
        state, tangents = tangent_step(state, tangents)
        if (n + 1) % reorth_every == 0 or n + 1 == total:
            tangents, log_r = reorthonormalise(tangents)
            if n >= transient:
                log_growth += log_r
    # the steps before the first QR after the transient are counted approximately: negligible
    return log_growth / num_steps


def max_lyapunov_exponent(step: Callable[[torch.Tensor], torch.Tensor], state: torch.Tensor,
                          num_steps: int, transient: int = 0, **kwargs) -> torch.Tensor:
    """The largest exponent (B...) of a plain map x -> f(x), by forward-mode tangents."""
    tangent_step = jvp_step(step)
    return lyapunov_exponents(tangent_step, state, num_steps, 1, transient, **kwargs)[..., 0]
