"""The compiled kernels against the PyTorch reference: values and every gradient group."""

import pytest
import torch

from moex.evaluate import EvalConfig, closed_loop_lyapunov, generate, random_state
from moex.model import (
    ModelConfig,
    closed_loop_run,
    init_experts,
    init_gating,
    leaky_scan,
    set_backend,
)
from moex.tasks import TaskConfig, make_task
from moex.train import (
    ExpertPhaseConfig,
    GatingPhaseConfig,
    TrainConfig,
    expert_objective,
    gating_objective,
    train_experts,
    train_gating,
)
from tests.conftest import generators

kernels = pytest.importorskip("moex.kernels")


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 1e-5)])
def test_scan_values_and_gradients_match_reference(dtype, tol, B=(2, 3), T=9, N=4, M=5):
    g = torch.Generator().manual_seed(0)
    args = [torch.randn(*B, T, N, M, generator=g), 0.5 * torch.randn(*B, M, M, generator=g),
            torch.rand(*B, 1, M, generator=g), torch.randn(*B, 1, M, generator=g),
            torch.randn(*B, N, M, generator=g)]
    args = [a.to(dtype).requires_grad_(True) for a in args]
    weights = torch.randn(2, *B, T, N, M, generator=g).to(dtype)
    results = []
    for scan in (leaky_scan, kernels.leaky_scan_compiled):
        u, c = scan(*args)
        loss = (u * weights[0] + c * weights[1]).sum()
        results.append((u, c, *torch.autograd.grad(loss, args)))
    for ref, fast in zip(*results, strict=True):
        torch.testing.assert_close(fast, ref, rtol=tol, atol=tol)


def test_compiled_scan_passes_gradcheck():
    g = torch.Generator().manual_seed(1)
    args = [torch.randn(2, 5, 3, 4, generator=g), 0.5 * torch.randn(2, 4, 4, generator=g),
            torch.rand(2, 1, 4, generator=g), torch.randn(2, 1, 4, generator=g),
            torch.randn(2, 3, 4, generator=g)]
    assert torch.autograd.gradcheck(kernels.leaky_scan_compiled,
                                    [a.requires_grad_(True) for a in args])


def _objective_gradients(backend, objective, params):
    set_backend(backend)
    leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    value, stats = objective(leaves)
    return value, stats, torch.autograd.grad(value.sum(), list(leaves.values()))


def test_phase_objectives_and_every_gradient_group_match():
    model = ModelConfig(learn_time_constants=True, num_experts=3)
    model.experts.context_size, model.gating.context_size = 4, 5
    series = torch.randn(2, 12, 2, generator=torch.Generator().manual_seed(2)).tanh()
    experts = init_experts(model, 2, 2, generators([1, 2]))
    experts["beta"] = torch.randn(2, 2, 11, 3, generator=torch.Generator().manual_seed(3))
    gating = init_gating(model, 2, 2, generators([3, 4]))
    ghat = torch.softmax(experts["beta"], -1)
    for objective, params in (
        (expert_objective(series[:, :-1], series[:, 1:], {}, model,
                          ExpertPhaseConfig(attraction=True)), experts),
        (gating_objective(ghat, series[:, :-1], {}, model, GatingPhaseConfig(attraction=True)),
         gating),
    ):
        ref = _objective_gradients("reference", objective, params)
        fast = _objective_gradients("compiled", objective, params)
        torch.testing.assert_close(fast[0], ref[0], rtol=0, atol=1e-10)
        for name, a, b in zip(params, ref[2], fast[2], strict=True):
            torch.testing.assert_close(b, a, rtol=0, atol=1e-10, msg=name)


def test_training_both_phases_matches_reference():
    task = make_task(TaskConfig(num_series=2, length=40), seed=0)
    series = torch.as_tensor(task.series)
    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 4, 5
    out = {}
    for backend in ("reference", "compiled"):
        set_backend(backend)
        experts, beta, _ = train_experts(init_experts(model, 2, 2, generators([0, 1])), series,
                                         model, ExpertPhaseConfig(steps=10, adaptive_lr=True),
                                         TrainConfig())
        gating, _ = train_gating(init_gating(model, 2, 2, generators([0, 1])),
                                 torch.softmax(beta, -1), series[:, :-1], model,
                                 GatingPhaseConfig(steps=10), TrainConfig())
        out[backend] = (experts, beta, gating)
    ref, fast = out["reference"], out["compiled"]
    torch.testing.assert_close(fast[1], ref[1], rtol=0, atol=1e-10)
    for a, b in ((ref[0], fast[0]), (ref[2], fast[2])):
        for k in a:
            torch.testing.assert_close(b[k], a[k], rtol=0, atol=1e-10, msg=k)


def _closed_loop_model(K, D, delay, dtype):
    model = ModelConfig(num_experts=K, delay=delay)
    model.experts.context_size, model.gating.context_size = 4, 5
    experts = init_experts(model, 2, D, generators([1, 2]), dtype) if D else {}
    gating = init_gating(model, 2, D, generators([3, 4]), dtype)
    for params in (experts, gating):  # weights large enough for non-trivial dynamics
        for name in ("w_rec", "w_in"):
            if name in params:
                params[name] = params[name] * 8
    state = random_state(experts, gating, 3, D, delay, torch.Generator().manual_seed(5))
    return experts, gating, state


@pytest.mark.parametrize("K, D, delay, k", [(2, 2, 1, 1), (3, 2, 2, 3), (4, 0, 1, 2)])
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
def test_closed_loop_kernel_matches_reference(K, D, delay, k, dtype, tol, steps=40):
    """Outputs, gates, potentials, next state, tangents (up to the sign QR leaves free) and the
    log growth of the compiled closed loop equal `closed_loop_run`, with noise and without
    experts (symbolic tasks)."""
    experts, gating, state = _closed_loop_model(K, D, delay, dtype)
    tangents = torch.linalg.qr(torch.randn(state.flat().shape + (k,), dtype=dtype))[0]
    noise = 0.1 * torch.randn(2, 3, steps, D, dtype=dtype)
    ref = closed_loop_run(experts, gating, state, steps, noise, tangents, True)
    fast = kernels.closed_loop_compiled(experts, gating, state, steps, noise, tangents, True)
    for a, b in zip(vars(ref[0]).values(), vars(fast[0]).values(), strict=True):
        torch.testing.assert_close(b, a, rtol=tol, atol=tol)
    for a, b in zip(ref[1], fast[1], strict=True):
        torch.testing.assert_close(b, a, rtol=tol, atol=tol)
    torch.testing.assert_close(fast[3], ref[3], rtol=tol, atol=tol)
    signs = torch.sign((ref[2] * fast[2]).sum(-2, keepdim=True))
    torch.testing.assert_close(fast[2] * signs, ref[2], rtol=tol, atol=tol)
    assert ref[3].abs().max() > 0.1  # the growth is not trivially zero


def test_closed_loop_kernel_leaves_its_input_state_alone():
    experts, gating, state = _closed_loop_model(2, 2, 1, torch.float64)
    before = [x.clone() for x in vars(state).values()]
    kernels.closed_loop_compiled(experts, gating, state, 5)
    for a, b in zip(before, vars(state).values(), strict=True):
        assert torch.equal(a, b)


def test_generation_and_exponents_equal_across_backends():
    """The whole evaluation path (chunked, noise from one generator) gives the same samples and
    exponents on both backends."""
    experts, gating, state = _closed_loop_model(2, 2, 1, torch.float64)
    cfg = EvalConfig(lyapunov_steps=30, transient=7, num_exponents=2, noise_var=1e-4)
    out = {}
    for backend in ("reference", "compiled"):
        set_backend(backend)
        chunks = []
        lam = closed_loop_lyapunov(experts, gating, state, cfg, torch.Generator().manual_seed(0),
                                   chunks.append)
        gen = generate(experts, gating, state, 20, 0.01, torch.Generator().manual_seed(1))
        out[backend] = (lam, torch.cat([c[0] for c in chunks], 2), gen["outputs"])
    for a, b in zip(out["reference"], out["compiled"], strict=True):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-10)


def test_backend_choice():
    assert set_backend("auto", "cpu") == "compiled"
    assert set_backend("reference") == "reference"
    with pytest.raises(ValueError, match="backend=compiled runs on the CPU only"):
        set_backend("compiled", "cuda")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_reference_runs_on_cuda_and_matches_cpu():
    model = ModelConfig()
    series = torch.randn(2, 20, 2).tanh()
    experts = init_experts(model, 2, 2, generators([0]))
    objective = expert_objective(series[:, :-1], series[:, 1:], {}, model, ExpertPhaseConfig())
    experts["beta"] = torch.zeros(1, 2, 19, 2)
    cpu = objective(experts)[0]
    gpu = expert_objective(series[:, :-1].cuda(), series[:, 1:].cuda(), {}, model,
                           ExpertPhaseConfig())({k: v.cuda() for k, v in experts.items()})[0]
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-10, atol=1e-10)
