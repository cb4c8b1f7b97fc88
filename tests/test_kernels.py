"""The compiled backend against the PyTorch reference: objectives, every gradient group, whole
training trajectories, closed-loop samples and exponents."""

import dataclasses

import numpy as np
import pytest
import torch

from moex.closed_loop import closed_loop_lyapunov, generate, random_state
from moex.kernels import get_backend, reference
from moex.model import ModelConfig, init_experts, init_gating
from moex.tasks import TaskConfig, make_task
from moex.train import (
    ExpertPhaseConfig,
    GatingPhaseConfig,
    TrainConfig,
    train_experts,
    train_gating,
)
from tests.conftest import generators

kernels = pytest.importorskip("moex.kernels.cpu")
REFERENCE, COMPILED = get_backend("reference"), get_backend("compiled")
TOLERANCE = {torch.float64: 1e-10, torch.float32: 1e-5}


def _problems(R, S, T, K, D, M, delay, learn_tau, attraction, dtype, seed=0):
    """Phase-1 and phase-2 problems of both backends on random parameters and data."""
    model = ModelConfig(num_experts=K, delay=delay, learn_time_constants=learn_tau)
    model.experts.context_size, model.gating.context_size = M, M + 1
    g = torch.Generator().manual_seed(seed)
    series = torch.randn(S, T + delay, D, generator=g).tanh().to(dtype)
    experts = init_experts(model, S, D, generators(range(R)), dtype) if D else {}
    if D:
        experts["beta"] = torch.randn(R, S, T, K, generator=g).to(dtype)
        experts["log_sigma"] = (0.3 * torch.randn(R, K, generator=g)).to(dtype)
    gating = init_gating(model, S, D, generators(range(R, 2 * R)), dtype)
    ghat = torch.softmax(torch.randn(R, S, T, K, generator=g), -1).to(dtype)
    phase1, phase2 = ExpertPhaseConfig(attraction=attraction), GatingPhaseConfig(
        attraction=attraction)
    x = series.numpy()
    out = []
    for backend in (REFERENCE, COMPILED):
        problems = [(backend.gating_problem(ghat.numpy(), x[:, :T], model, phase2,
                                            list(range(R))), gating)]
        if D:
            problems.append((backend.expert_problem(x[:, :-delay], x[:, delay:], model, phase1,
                                                    R), experts))
        out.append(problems)
    return out


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("R, S, T, K, D, M, delay, learn_tau, attraction", [
    (2, 3, 17, 2, 2, 4, 1, False, False),  # the paper's settings, small
    (3, 2, 11, 3, 2, 5, 2, True, True),  # learned τ, attraction, τ = 2
    (1, 1, 9, 5, 3, 3, 1, True, False),  # one series: lanes of different experts
    (2, 4, 13, 7, 0, 6, 1, False, True),  # symbolic (Reber-like): phase 2 only
])
def test_objectives_and_every_gradient_group_match(R, S, T, K, D, M, delay, learn_tau,
                                                   attraction, dtype):
    tol = TOLERANCE[dtype]
    for (ref, params), (fast, _) in zip(*_problems(R, S, T, K, D, M, delay, learn_tau,
                                                   attraction, dtype), strict=True):
        arrays = {k: v.numpy() for k, v in params.items()}
        learned = [k for k in arrays if k != "tau" or learn_tau]
        results = []
        for problem in (ref, fast):
            grads = {k: np.full_like(arrays[k], np.nan) for k in learned}
            stats = problem.value_and_grad(arrays, grads, np.ones(R, bool))
            results.append((stats, grads, problem.value(arrays, np.ones(R, bool))))
        (ref_stats, ref_grads, ref_value), (stats, grads, value) = results
        for name in ref_stats:
            scale = max(1.0, np.abs(ref_stats[name]).max())
            np.testing.assert_allclose(stats[name], ref_stats[name], rtol=tol, atol=tol * scale,
                                       err_msg=name)
            np.testing.assert_allclose(value[name], stats[name], rtol=tol, atol=tol * scale)
        for name in learned:
            scale = max(1.0, np.abs(ref_grads[name]).max())
            np.testing.assert_allclose(grads[name], ref_grads[name], rtol=tol, atol=tol * scale,
                                       err_msg=name)


def test_inactive_runs_are_skipped_and_others_unchanged():
    """Runs marked inactive (failed) are not computed; the active ones give the same values."""
    (_, _), (problems, _) = _problems(3, 2, 9, 2, 2, 4, 1, False, False, torch.float64)
    problem, params = problems
    arrays = {k: v.numpy() for k, v in params.items()}
    grads = {k: np.zeros_like(v) for k, v in arrays.items() if k != "tau"}
    full = problem.value_and_grad(arrays, grads, np.ones(3, bool))
    kept = {k: v.copy() for k, v in grads.items()}
    arrays["w_rec"][1] = np.nan  # a failed run's parameters
    part = problem.value_and_grad(arrays, grads, np.array([True, False, True]))
    for name in full:
        np.testing.assert_array_equal(part[name][[0, 2]], full[name][[0, 2]])
    for name in grads:
        np.testing.assert_array_equal(grads[name][[0, 2]], kept[name][[0, 2]])


@pytest.mark.parametrize("adaptive", [False, True])
@pytest.mark.parametrize("form", ["paper", "mregn"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_training_trajectories_of_both_phases_match(adaptive, form, dtype, steps=12):
    task = make_task(TaskConfig(num_series=2, length=40), seed=0)
    series = torch.as_tensor(task.series, dtype=dtype)
    model = ModelConfig(learn_time_constants=True)
    model.experts.context_size, model.gating.context_size = 4, 5
    rule = TrainConfig(momentum_form=form)
    # (attraction stays off: at this rate its u_0 update has a gain of about 10 per step, so any
    # rounding difference grows exponentially; its gradient is checked above)
    phase1 = ExpertPhaseConfig(steps=steps, adaptive_lr=adaptive, learning_rate=0.05,
                               log_every=1)
    phase2 = GatingPhaseConfig(steps=steps, adaptive_lr=adaptive, learning_rate=1.0, log_every=1)
    out = {}
    for backend in (REFERENCE, COMPILED):
        experts, beta, rows1 = train_experts(
            init_experts(model, 2, 2, generators([0, 1]), dtype), series, model, phase1, rule,
            backend=backend)
        gating, rows2 = train_gating(init_gating(model, 2, 2, generators([0, 1]), dtype),
                                     torch.softmax(beta, -1), series[:, :-1], model, phase2, rule,
                                     backend=backend)
        out[backend.name] = (experts, beta, gating, rows1 + rows2)
    ref, fast = out["reference"], out["compiled"]
    tol = TOLERANCE[dtype] * (100 if dtype == torch.float32 else 1)  # 24 steps of float32
    torch.testing.assert_close(fast[1], ref[1], rtol=tol, atol=tol)
    for a, b in ((ref[0], fast[0]), (ref[2], fast[2])):
        for k in a:
            torch.testing.assert_close(b[k], a[k], rtol=tol, atol=tol, msg=k)
    assert [r["retries"] for r in ref[3]] == [r["retries"] for r in fast[3]]
    if adaptive:
        assert any(r["lr_scale"] != 1.0 for r in fast[3])


def test_noisy_phase2_matches_reference_and_batches_equal_runs_alone(steps=6):
    """With input noise in phase 2, both backends draw the same noise; run r sees the noise of
    its own seed whether trained in a batch or alone."""
    task = make_task(TaskConfig(num_series=2, length=30), seed=0)
    series = torch.as_tensor(task.series)
    model = ModelConfig()
    model.gating.context_size = 5
    phase2 = GatingPhaseConfig(steps=steps, input_noise_var=1e-2)
    ghat = torch.softmax(torch.randn(3, 2, 29, 2, generator=torch.Generator().manual_seed(1)), -1)
    out = {}
    for backend in (REFERENCE, COMPILED):
        out[backend.name] = train_gating(init_gating(model, 2, 2, generators([4, 5, 6])), ghat,
                                         series[:, :-1], model, phase2, TrainConfig(),
                                         backend=backend, seeds=[7, 8, 9])[0]
        alone = train_gating(init_gating(model, 2, 2, generators([5])), ghat[1:2],
                             series[:, :-1], model, phase2, TrainConfig(), backend=backend,
                             seeds=[8])[0]
        for k in alone:
            torch.testing.assert_close(alone[k][0], out[backend.name][k][1], rtol=0,
                                       atol=1e-12)
    clean = train_gating(init_gating(model, 2, 2, generators([4, 5, 6])), ghat, series[:, :-1],
                         model, dataclasses.replace(phase2, input_noise_var=0.0), TrainConfig(),
                         backend=COMPILED, seeds=[7, 8, 9])[0]
    for k in clean:
        torch.testing.assert_close(out["compiled"][k], out["reference"][k], rtol=1e-10,
                                   atol=1e-10)
    assert (clean["w_out"] - out["compiled"]["w_out"]).abs().max() > 1e-6  # noise did act


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


@pytest.mark.parametrize("K, D, delay, k, uniform", [(2, 2, 1, 1, False), (3, 2, 2, 3, False),
                                                     (4, 0, 1, 2, False), (3, 2, 1, 2, True)])
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
def test_closed_loop_kernel_matches_reference(K, D, delay, k, uniform, dtype, tol, steps=40):
    """Outputs, gates, potentials, next state, tangents (up to the sign QR leaves free) and the
    log growth of the compiled closed loop equal the reference, with noise, without experts
    (symbolic tasks) and with the C tool's uniform gates in the Jacobian."""
    experts, gating, state = _closed_loop_model(K, D, delay, dtype)
    tangents = torch.linalg.qr(torch.randn(state.flat().shape + (k,), dtype=dtype))[0]
    noise = 0.1 * torch.randn(2, 3, steps, D, dtype=dtype)
    ref = reference.closed_loop(experts, gating, state, steps, noise, tangents, True, uniform)
    fast = kernels.closed_loop(experts, gating, state, steps, noise, tangents, True, uniform)
    for a, b in zip(vars(ref.state).values(), vars(fast.state).values(), strict=True):
        torch.testing.assert_close(b, a, rtol=tol, atol=tol)
    for name in ("outputs", "gates", "gating_u", "growth"):
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), rtol=tol, atol=tol)
    signs = torch.sign((ref.tangents * fast.tangents).sum(-2, keepdim=True))
    torch.testing.assert_close(fast.tangents * signs, ref.tangents, rtol=tol, atol=tol)
    assert ref.growth.abs().max() > 0.1  # the growth is not trivially zero


def test_closed_loop_kernel_leaves_its_input_state_alone():
    experts, gating, state = _closed_loop_model(2, 2, 1, torch.float64)
    before = [x.clone() for x in vars(state).values()]
    kernels.closed_loop(experts, gating, state, 5)
    for a, b in zip(before, vars(state).values(), strict=True):
        assert torch.equal(a, b)


def test_generation_and_exponents_equal_across_backends():
    """The whole evaluation path (chunked, noise from one generator) gives the same samples and
    exponents on both backends."""
    experts, gating, state = _closed_loop_model(2, 2, 1, torch.float64)
    out = {}
    for backend in (REFERENCE, COMPILED):
        chunks = []
        lam = closed_loop_lyapunov(experts, gating, state, 30, 7, torch.Generator().manual_seed(0),
                                   num_exponents=2, noise_std=1e-2, on_chunk=chunks.append,
                                   backend=backend)
        gen = generate(experts, gating, state, 20, 0.01, torch.Generator().manual_seed(1),
                       backend)
        out[backend.name] = (lam, torch.cat([c.outputs for c in chunks], 2), gen["outputs"])
    for a, b in zip(out["reference"], out["compiled"], strict=True):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-10)


def test_nearest_symbols_match_reference():
    g = np.random.default_rng(0)
    points, prototypes = g.uniform(-1, 1, (3, 37, 2)), g.uniform(-1, 1, (11, 2))
    symbols = g.integers(0, 4, 11)
    np.testing.assert_array_equal(COMPILED.nearest_symbols(points, prototypes, symbols),
                                  REFERENCE.nearest_symbols(points, prototypes, symbols))


def test_backend_choice():
    assert get_backend("auto", "cpu").name == "compiled"
    assert get_backend("reference").name == "reference"
    assert get_backend("auto", "cuda").name == "reference"
    with pytest.raises(ValueError, match="backend=compiled runs on the CPU only"):
        get_backend("compiled", "cuda")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_reference_runs_on_cuda_and_matches_cpu():
    (problems, _), _ = _problems(2, 2, 19, 2, 2, 4, 1, False, False, torch.float64)
    for problem, params in problems:
        arrays = {k: v.numpy() for k, v in params.items()}
        on_gpu = dataclasses.replace(get_backend("reference", "cuda"))
        assert on_gpu.device == "cuda"
        cpu = problem.value(arrays, np.ones(2, bool))
        problem.device = torch.device("cuda")
        gpu = problem.value(arrays, np.ones(2, bool))
        for name in cpu:
            np.testing.assert_allclose(gpu[name], cpu[name], rtol=1e-10, atol=1e-10)
