import torch

from moex.closed_loop import generate, trained_state
from moex.config.model import ModelConfig
from moex.kernels import get_backend
from moex.model import (
    ClosedLoopState,
    closed_loop_step,
    expert_forward,
    gating_forward,
    init_experts,
    init_gating,
    random_state,
)
from tests.helpers import generators


def _model(delay=2, K=3, D=2, S=2):
    cfg = ModelConfig(num_experts=K, delay=delay)
    cfg.experts.context_size, cfg.gating.context_size = 4, 5
    experts = init_experts(cfg, S, D, generators([1, 2]))
    gating = init_gating(cfg, S, D, generators([3, 4]))
    return cfg, experts, gating


def test_tangent_map_equals_autograd_jacobian():
    """The hand-written tangent of the full closed loop (all contexts, both delay lines, real
    gates) equals forward-mode autograd of the step, column by column."""
    _, experts, gating = _model()
    state = random_state(experts, gating, 3, num_features=2, delay=2,
                         generator=torch.Generator().manual_seed(0))
    flat = state.flat()
    k = 4
    tangents = torch.randn((k,) + flat.shape, generator=torch.Generator().manual_seed(1))
    d_next = closed_loop_step(experts, gating, state, noise=None,
                              tangents=state.like(tangents)).tangents

    def step(x):
        return closed_loop_step(experts, gating, state.like(x)).state.flat()

    for i in range(k):
        _, expected = torch.func.jvp(step, (flat,), (tangents[i],))
        torch.testing.assert_close(d_next.flat(lead=3)[i], expected, rtol=1e-10, atol=1e-12)


def test_tangent_map_without_experts():
    cfg = ModelConfig(num_experts=4, delay=1)
    gating = init_gating(cfg, 1, 0, generators([0]))
    state = random_state({}, gating, 2, num_features=0, delay=1,
                         generator=torch.Generator().manual_seed(0))
    tangents = torch.randn((2,) + state.flat().shape)
    d_next = closed_loop_step({}, gating, state, noise=None, tangents=state.like(tangents)).tangents
    for i in range(2):
        _, expected = torch.func.jvp(
            lambda x: closed_loop_step({}, gating, state.like(x)).state.flat(), (state.flat(),),
            (tangents[i],))
        torch.testing.assert_close(d_next.flat(lead=3)[i], expected)


def test_closed_loop_equals_open_loop_fed_its_own_outputs(T=12, delay=2):
    _, experts, gating = _model(delay=delay)
    S = 2
    series = torch.randn(S, delay, 2).tanh()
    gates = torch.softmax(torch.randn(2, S, delay, 3), -1)
    state = trained_state(experts, gating, gates, series, delay=delay)
    out = generate(experts, gating, state, T, backend=get_backend())
    # rebuild the closed loop's input and gate sequences, then run the teacher-forced passes
    inputs = torch.cat([series[None].expand(2, -1, -1, -1), out["outputs"][:, :, : T - delay]], 2)
    g_seq = out["gates"]
    for r in range(2):
        y, _ = expert_forward({k: v[r:r + 1] for k, v in experts.items()}, inputs[r])
        mixture = (g_seq[r:r + 1, ..., None] * y).sum(-2)
        torch.testing.assert_close(mixture[0], out["outputs"][r])
        log_g, _ = gating_forward({k: v[r:r + 1] for k, v in gating.items()}, g_seq[r:r + 1],
                                  inputs[r], delay)
        torch.testing.assert_close(log_g.exp()[0], g_seq[r, :, delay:])


def test_state_flattening_round_trip():
    _, experts, gating = _model()
    state = random_state(experts, gating, 3, num_features=2, delay=2,
                         generator=torch.Generator().manual_seed(0))
    again = state.like(state.flat())
    for a, b in zip(vars(state).values(), vars(again).values(), strict=True):
        assert torch.equal(a, b)
    assert isinstance(again, ClosedLoopState)
    assert torch.allclose(state.gates.sum(-1), torch.ones(2, 3, 2))


def test_gate_estimates_temperature():
    """Temperature 1 is ĝ = softmax(β) (Eq. 9), below 1 sharper, 0 the one-hot argmax."""
    from moex.model import gate_estimates

    beta = torch.randn(2, 3, 5, 4, generator=torch.Generator().manual_seed(0))
    soft = gate_estimates(beta)
    torch.testing.assert_close(soft, torch.softmax(beta, -1))
    sharp = gate_estimates(beta, 0.5)
    assert (sharp.max(-1).values >= soft.max(-1).values).all()
    hard = gate_estimates(beta, 0.0)
    assert torch.equal(hard.argmax(-1), beta.argmax(-1)) and torch.equal(hard.sum(-1),
                                                                       torch.ones(2, 3, 5))


def test_a_runs_random_states_and_noise_do_not_depend_on_the_runs_beside_it():
    """With a generator per run (`moex.jobs.run_generators`, as `moex generate` and the evaluation
    draw), run 0's samples from a batch of two equal its samples alone, bit for bit."""
    from moex.jobs import run_generators

    _, experts, gating = _model()

    def run0(runs: int) -> dict:
        first = tuple({k: v[:runs] for k, v in net.items()} for net in (experts, gating))
        gens = run_generators(5, runs)
        state = random_state(*first, 3, num_features=2, delay=2, generator=gens)
        return generate(*first, state, 20, noise_std=0.1, generator=gens, backend=get_backend())

    alone, batch = run0(1), run0(2)
    for name in ("outputs", "gates"):
        assert torch.equal(batch[name][:1], alone[name]), name
