"""Pure objective functions of the two training phases (paper Sec. 2.1.2, Eqs. 9-14).

Phase 1 maximises the mixture-of-Gaussians likelihood with a Brownian-motion prior on the gate
logits β; phase 2 maximises the Dirichlet likelihood of the gating RNN, which equals minus the KL
divergence from the estimates ĝ up to a constant. Everything is in log space.
"""

import math

import torch


def mixture_log_likelihood(outputs: torch.Tensor, targets: torch.Tensor,
                           log_gate_estimates: torch.Tensor,
                           variances: torch.Tensor) -> torch.Tensor:
    """ln p(Y | X, β, γ) = Σ_{s,n} ln Σ_k ĝ^k_n N(y_n; y^k_n, σ_k² I) (Eqs. 10-12), per run.

    Args:
        outputs: (R, S, T, K, D) expert outputs y^k_n.
        targets: (S, T, D) training outputs y_n, or (R, S, T, D) per run.
        log_gate_estimates: (R, S, T, K) ln ĝ_n = log_softmax(β_n).
        variances: (R, K) σ_k².

    Returns:
        (R,) log-likelihood summed over series and steps.
    """
    log_p = expert_log_densities(outputs, targets, variances)
    return torch.logsumexp(log_gate_estimates + log_p, dim=-1).sum((1, 2))


def expert_log_densities(outputs: torch.Tensor, targets: torch.Tensor,
                         variances: torch.Tensor) -> torch.Tensor:
    """ln N(y_n; y^k_n, σ_k² I) of every expert (Eq. 11), (R, S, T, K); arguments as for
    `mixture_log_likelihood`."""
    D = outputs.shape[-1]
    sq_err = (outputs - targets[..., None, :]).square().sum(-1)  # (R, S, T, K)
    var = variances[:, None, None]
    return -0.5 * D * torch.log(2 * math.pi * var) - sq_err / (2 * var)


def gate_prior_log_density(beta: torch.Tensor, prior_std: float) -> torch.Tensor:
    """ln φ(β) of the Brownian-motion prior on gate logits (Eq. 13), per run.

    Args:
        beta: (R, S, T, K) gate logits; the prior couples neighbouring steps within a series.
        prior_std: ς.

    Returns:
        (R,) Σ_{s, n<T, k} [-(β_{n+1} - β_n)² / (2ς²) - ln(√(2π) ς)].
    """
    diff = beta[:, :, 1:] - beta[:, :, :-1]
    log_norm = 0.5 * math.log(2 * math.pi * prior_std**2)
    return (-diff.square() / (2 * prior_std**2) - log_norm).sum((1, 2, 3))


def mixture_mse(outputs: torch.Tensor, targets: torch.Tensor,
                gates: torch.Tensor) -> torch.Tensor:
    """E = Σ ½‖y_n - Σ_k g^k_n y^k_n‖² / (T D) per run, T summed over series (paper Sec. 3).

    Args:
        outputs: (R, S, T, K, D); targets: (S, T, D) or (R, S, T, D); gates: (R, S, T, K).

    Returns:
        (R,) mean squared error of the mixture output.
    """
    _, S, T, _, D = outputs.shape
    mixture = (gates[..., None] * outputs).sum(-2)  # (R, S, T, D)
    return 0.5 * (mixture - targets).square().sum((1, 2, 3)) / (S * T * D)


def gating_log_likelihood(log_gates: torch.Tensor, gate_targets: torch.Tensor) -> torch.Tensor:
    """Σ_{s,n,k} ĝ^k_n ln g^k_n, the Dirichlet log-likelihood without ln Z(ĝ) (Eqs. 14-15).

    Args:
        log_gates: (R, S, T, K) ln g_n; gate_targets: (R, S, T, K) ĝ_n, aligned.

    Returns:
        (R,) soft-target cross-entropy, negated.
    """
    return (gate_targets * log_gates).sum((1, 2, 3))


def gating_kl(log_gates: torch.Tensor, gate_targets: torch.Tensor) -> torch.Tensor:
    """D_KL((ĝ_n) ‖ (g_n)) = Σ ĝ ln(ĝ/g) summed over series and steps (Eq. 16), per run (R,).

    Entries with ĝ = 0 contribute 0.
    """
    return (torch.xlogy(gate_targets, gate_targets) - gate_targets * log_gates).sum((1, 2, 3))


def initial_state_attraction(u0: torch.Tensor, potentials: torch.Tensor,
                             var_floor: float) -> torch.Tensor:
    """The C code's attraction of u_0 to its own trajectory (not in the paper), per run.

    A Gaussian log-prior Σ -(u_0 - μ)² / (2 max(var, floor)) whose mean μ and variance var are the
    statistics of {u_0, u_1..u_T} of the same series, held constant (detached).

    Args:
        u0: (R, S, ..., M) initial potentials; potentials: (R, S, ..., T, M) the trajectory.

    Returns:
        (R,) the attraction term; its gradient is (μ - u_0) / var.
    """
    trajectory = torch.cat([u0.unsqueeze(-2), potentials], dim=-2).detach()
    mean = trajectory.mean(-2)
    var = trajectory.var(-2, unbiased=False).clamp_min(var_floor)
    return (-(u0 - mean).square() / (2 * var)).flatten(1).sum(1)
