import math

import torch

from moex.metrics.lyapunov import jvp_step, lyapunov_exponents, max_lyapunov_exponent


def test_logistic_map_r4_gives_ln2(samples=64, steps=2500):
    x0 = torch.rand(samples, 1, generator=torch.Generator().manual_seed(0)) * 0.8 + 0.1
    lam = max_lyapunov_exponent(lambda x: 4 * x * (1 - x), x0, steps, transient=100)
    assert abs(lam.mean().item() - math.log(2)) < 0.01


def test_linear_map_gives_log_abs_a():
    for a in (0.5, -1.7, 3.0):
        lam = max_lyapunov_exponent(lambda x, a=a: a * x, torch.ones(3, 1), 200)
        torch.testing.assert_close(lam, torch.full((3,), math.log(abs(a))))


def test_spectrum_of_a_diagonal_linear_map():
    A = torch.diag(torch.tensor([2.0, 0.5, -0.25]))
    lam = lyapunov_exponents(jvp_step(lambda x: x @ A.T), torch.ones(2, 3), 100,
                             num_exponents=3, transient=30, reorth_every=5)
    torch.testing.assert_close(lam, torch.log(torch.tensor([2.0, 0.5, 0.25])).expand(2, 3))


def test_contracting_rnn_is_negative(M=6):
    g = torch.Generator().manual_seed(1)
    W = torch.randn(M, M, generator=g) * 0.3 / math.sqrt(M)
    lam = max_lyapunov_exponent(lambda u: 0.8 * u + 0.2 * torch.tanh(u) @ W.T,
                                torch.randn(4, M, generator=g), 500, transient=100)
    assert (lam < 0).all()
