import torch

from moex.config.model import ModelConfig
from moex.model import expert_forward, gating_forward, init_experts, init_gating, leaky_scan
from tests.helpers import generators


def _scan_by_hand(drive, w_rec, eps, bias, u0):
    """Eqs. 1-2 written out one network and one step at a time."""
    u, c, out = u0.clone(), torch.tanh(u0 + bias), []
    for d in drive:
        u = (1 - eps) * u + eps * (d + w_rec @ c)
        c = torch.tanh(u + bias)
        out.append(u)
    return torch.stack(out)


def test_leaky_scan_matches_equations(B=3, T=6, N=2, M=4):
    g = torch.Generator().manual_seed(0)
    drive, w = torch.randn(B, T, N, M, generator=g), torch.randn(B, M, M, generator=g)
    eps, bias = torch.rand(B, 1, M, generator=g), torch.randn(B, 1, M, generator=g)
    u0 = torch.randn(B, N, M, generator=g)
    u, c = leaky_scan(drive, w, eps, bias, u0)
    torch.testing.assert_close(c, torch.tanh(u + bias[:, None]))
    for b in range(B):
        for n in range(N):
            ref = _scan_by_hand(drive[b, :, n], w[b], eps[b, 0], bias[b, 0], u0[b, n])
            torch.testing.assert_close(u[b, :, n], ref, rtol=0, atol=1e-13)


def test_runs_in_a_batch_equal_runs_alone(R=3, S=2, T=7, D=2, K=2):
    cfg = ModelConfig(num_experts=K)
    seeds = [11, 12, 13]
    x = torch.randn(S, T, D, generator=torch.Generator().manual_seed(5)).tanh()
    together = init_experts(cfg, S, D, generators(seeds))
    y, _ = expert_forward(together, x)
    gates = torch.softmax(torch.randn(R, S, T, K), -1)
    gating = init_gating(cfg, S, D, generators(seeds))
    log_g, _ = gating_forward(gating, gates, x, cfg.delay)
    for r, seed in enumerate(seeds):
        alone = init_experts(cfg, S, D, generators([seed]))
        for name in alone:
            assert torch.equal(alone[name][0], together[name][r])
        torch.testing.assert_close(expert_forward(alone, x)[0][0], y[r], rtol=0, atol=1e-14)
        alone_g = init_gating(cfg, S, D, generators([seed]))
        torch.testing.assert_close(gating_forward(alone_g, gates[r:r + 1], x, cfg.delay)[0][0],
                                   log_g[r], rtol=0, atol=1e-14)


def test_initialisation_schemes(S=3, D=2):
    paper = init_experts(ModelConfig(init="paper"), S, D, generators([0]))
    mregn = init_experts(ModelConfig(init="mregn"), S, D, generators([0]))
    M = paper["w_rec"].shape[-1]
    for name in ("w_in", "w_rec", "w_out", "b_c", "b_o"):
        assert paper[name].abs().max() <= 1 / M
    assert paper["u0"].abs().max() <= 1 and paper["u0"].abs().max() > 1 / M
    assert (mregn["u0"] == 0).all()
    assert mregn["b_c"].abs().max() > 1 / M  # U[-1, 1] biases
    assert torch.allclose(paper["tau"], torch.tensor(1 / 0.2))


def test_gates_are_probabilities_and_shifted_by_delay(S=2, T=9, D=2, K=3):
    cfg = ModelConfig(num_experts=K, delay=3)
    gating = init_gating(cfg, S, D, generators([0, 1]))
    gates = torch.softmax(torch.randn(2, S, T, K), -1)
    x = torch.randn(S, T, D)
    log_g, _ = gating_forward(gating, gates, x, cfg.delay)
    assert log_g.shape == (2, S, T - 3, K)
    torch.testing.assert_close(log_g.exp().sum(-1), torch.ones(2, S, T - 3))
    # the output at time n only depends on inputs up to n - τ: changing the last τ inputs is moot
    gates2, x2 = gates.clone(), x.clone()
    gates2[:, :, -3:], x2[:, -3:] = 1 / K, 0.0
    torch.testing.assert_close(gating_forward(gating, gates2, x2, cfg.delay)[0], log_g)
