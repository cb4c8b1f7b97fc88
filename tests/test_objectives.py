import math

import torch

from moex import objectives


def test_mixture_log_likelihood_by_hand():
    outputs = torch.tensor([0.1, 0.5]).view(1, 1, 1, 2, 1)  # two experts, D = 1
    target = torch.tensor([0.2]).view(1, 1, 1)
    gates = torch.tensor([0.25, 0.75]).view(1, 1, 1, 2)
    var = torch.tensor([[0.04, 0.09]])
    dens = [math.exp(-(o - 0.2) ** 2 / (2 * v)) / math.sqrt(2 * math.pi * v)
            for o, v in ((0.1, 0.04), (0.5, 0.09))]
    expected = math.log(0.25 * dens[0] + 0.75 * dens[1])
    got = objectives.mixture_log_likelihood(outputs, target, gates.log(), var)
    assert abs(got.item() - expected) < 1e-12


def test_log_space_survives_far_outliers():
    outputs = torch.tensor([5.0, 6.0]).view(1, 1, 1, 2, 1)
    got = objectives.mixture_log_likelihood(outputs, torch.zeros(1, 1, 1),
                                            torch.log(torch.tensor([[[[0.5, 0.5]]]])),
                                            torch.tensor([[1e-4, 1e-4]]))
    assert torch.isfinite(got).all()  # every density underflows in probability space


def test_gate_prior_by_hand():
    beta = torch.tensor([0.0, 1.0, 3.0]).view(1, 1, 3, 1)
    log_norm = 0.5 * math.log(2 * math.pi * 4)
    expected = -(1 / 8) - (4 / 8) - 2 * log_norm
    assert abs(objectives.gate_prior_log_density(beta, 2.0).item() - expected) < 1e-12


def test_beta_gradient_matches_paper_formula(S=1, T=5, K=3, D=2, std=0.7):
    g = torch.Generator().manual_seed(0)
    outputs = torch.randn(1, S, T, K, D, generator=g).tanh()
    targets = torch.randn(S, T, D, generator=g).tanh()
    var = torch.rand(1, K, generator=g) + 0.1
    beta = torch.randn(1, S, T, K, generator=g).requires_grad_(True)
    log_l = (objectives.mixture_log_likelihood(outputs, targets, beta.log_softmax(-1), var)
             + objectives.gate_prior_log_density(beta, std))
    (grad,) = torch.autograd.grad(log_l.sum(), beta)
    # Eq. 19: ĝ (p_i - p) / p + G_n / ς²
    ghat = beta.detach().softmax(-1)
    sq = (outputs - targets[None, :, :, None]).square().sum(-1)
    p_i = torch.exp(-sq / (2 * var[:, None, None])) / (2 * math.pi * var[:, None, None]) ** (D / 2)
    p = (ghat * p_i).sum(-1, keepdim=True)
    b = beta.detach()
    G = torch.zeros_like(b)
    G[:, :, :-1] += b[:, :, 1:] - b[:, :, :-1]
    G[:, :, 1:] -= b[:, :, 1:] - b[:, :, :-1]
    torch.testing.assert_close(grad, ghat * (p_i - p) / p + G / std**2)


def test_kl_zero_iff_equal_and_matches_likelihood_up_to_constant():
    g = torch.Generator().manual_seed(1)
    ghat = torch.softmax(torch.randn(2, 3, 4, 5, generator=g), -1)
    assert objectives.gating_kl(ghat.log(), ghat).abs().max() < 1e-12
    other = torch.softmax(torch.randn(2, 3, 4, 5, generator=g), -1)
    kl = objectives.gating_kl(other.log(), ghat)
    assert (kl > 0).all()
    entropy = -(ghat * ghat.log()).sum((1, 2, 3))
    torch.testing.assert_close(kl, -objectives.gating_log_likelihood(other.log(), ghat) - entropy)
    one_hot = torch.eye(5)[torch.randint(5, (2, 3, 4), generator=g)]
    assert torch.isfinite(objectives.gating_kl(other.log(), one_hot)).all()


def test_mixture_mse_by_hand():
    outputs = torch.tensor([[0.0, 1.0], [1.0, 1.0]]).view(1, 1, 1, 2, 2)  # K = 2, D = 2
    gates = torch.tensor([0.5, 0.5]).view(1, 1, 1, 2)
    targets = torch.tensor([0.5, 0.0]).view(1, 1, 2)
    # mixture = (0.5, 1.0); error² = 0 + 1; E = ½ · 1 / (1 · 2)
    assert abs(objectives.mixture_mse(outputs, targets, gates).item() - 0.25) < 1e-15


def test_attraction_gradient_pulls_toward_trajectory_mean():
    u0 = torch.tensor([[[0.0, 2.0]]]).requires_grad_(True)  # (R, S, M)
    traj = torch.tensor([[[[1.0, 2.0], [1.0, 2.0], [1.0, 2.0]]]])  # (R, S, T, M)
    (grad,) = torch.autograd.grad(objectives.initial_state_attraction(u0, traj, 1e-3).sum(), u0)
    mean = torch.tensor([0.75, 2.0])
    var = torch.tensor([0.1875, 1e-3])
    torch.testing.assert_close(grad[0, 0], (mean - u0.detach()[0, 0]) / var)
