"""The fast backends (cpu: numba; gpu: Triton, in its interpreter without CUDA) against the PyTorch
reference: objectives, every gradient group, whole training trajectories, closed-loop samples and
exponents. Each law test runs on every backend through the `backend` fixture."""

import ast
import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
import torch

from moex.closed_loop import closed_loop_lyapunov, generate
from moex.config.model import ModelConfig
from moex.config.train import AdaptiveLRConfig, ExpertPhaseConfig, GatingPhaseConfig, TrainConfig
from moex.kernels import REGISTRY, available, get_backend, reference
from moex.metrics.lyapunov import initial_tangents, reorthonormalise
from moex.model import closed_loop_step, init_experts, init_gating, random_state
from moex.tasks import make_task, task_config
from moex.train import train_experts, train_gating
from tests.helpers import INTERPRETED, backend_params, generators

REFERENCE, COMPILED = get_backend("reference"), get_backend("cpu")
TOLERANCE = {torch.float64: 1e-10, torch.float32: 1e-5}


def _on(params: dict, device) -> dict:
    return {k: v.to(device) for k, v in params.items()}


def _problems(R, S, T, K, D, M, delay, learn_tau, attraction, dtype, seed=0, fast=COMPILED):
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
    x = series
    out = []
    for backend in (REFERENCE, fast):
        problems = [(backend.gating_problem(ghat, x[:, :T], model, phase2,
                                            list(range(R))), _on(gating, backend.device))]
        if D:
            problems.append((backend.expert_problem(x[:, :-delay], x[:, delay:], model, phase1,
                                                    R), _on(experts, backend.device)))
        out.append(problems)
    return out


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("R, S, T, K, D, M, delay, learn_tau, attraction", [
    (2, 3, 17, 2, 2, 4, 1, False, False),  # the paper's settings, small
    (3, 2, 11, 3, 2, 5, 2, True, True),  # learned τ, attraction, τ = 2
    (1, 1, 9, 5, 3, 3, 1, True, False),  # one series: lanes of different experts
    (2, 4, 13, 7, 0, 6, 1, False, True),  # symbolic (Reber-like): phase 2 only
    (1, 2, 2, 2, 2, 3, 1, True, False),  # one time step: BPTT's pairs of steps, a lone one
])
def test_objectives_and_every_gradient_group_match(R, S, T, K, D, M, delay, learn_tau,
                                                   attraction, dtype, backend):
    _assert_backends_agree(_problems(R, S, T, K, D, M, delay, learn_tau, attraction, dtype,
                                     fast=backend), R, learn_tau, TOLERANCE[dtype])


@pytest.mark.parametrize("backend", backend_params(reference=False), indirect=True)
def test_float32_attraction_of_a_state_far_from_zero_matches(backend):
    """The u_0 attraction's variance is taken by difference, Σu²/n - μ²: in float32 sums the
    difference loses the digits the variance is made of when the mean is far from zero (a GPU's
    ∂u_0 was 35x further from float64 than the reference's at first contact). Here u_0 ≈ 40 and
    τ = 1000, so the trajectory's mean² is ~10⁴ times its variance. Measured (× the largest
    |∂u_0|): float64 sums, as both backends keep, 5-7e-5 from the reference — the float32
    trajectory's own rounding, which no float32 method escapes; float32 sums 4.4e-3."""
    if not backend.caps.float32:
        pytest.skip(f"{backend.name} runs float64 only")

    def far_from_zero(params):
        g = torch.Generator().manual_seed(5)
        params["u0"] = (40.0 + torch.randn(params["u0"].shape, generator=g)).to(params["u0"])
        params["tau"] = torch.full_like(params["tau"], 1000.0)

    _assert_backends_agree(_problems(2, 2, 30, 2, 2, 4, 1, True, True, torch.float32,
                                     fast=backend), 2, True, 2e-4, edit=far_from_zero)


def _assert_backends_agree(pairs, R, learn_tau, tol, edit=lambda params: None):
    """Objectives and every gradient group of the reference's problems (pairs[0]) equal the fast
    backend's (pairs[1]) within tol × max(1, the largest |value|); `edit` sets the parameters."""
    results = []
    for problems in pairs:
        results.append([])
        for problem, params in problems:
            edit(params)
            learned = [k for k in params if k != "tau" or learn_tau]
            grads = {k: torch.full_like(params[k], torch.nan) for k in learned}
            active = torch.ones(R, dtype=torch.bool, device=params["w_in"].device)
            stats = problem.value_and_grad(params, grads, active)
            results[-1].append(tuple(_host(x) for x in (stats, grads,
                                                         problem.value(params, active))))
    for ((ref_stats, ref_grads, _), (stats, grads, value)) in zip(*results,
                                                                         strict=True):
        for name in ref_stats:
            scale = max(1.0, np.abs(ref_stats[name]).max())
            np.testing.assert_allclose(stats[name], ref_stats[name], rtol=tol, atol=tol * scale,
                                       err_msg=name)
            np.testing.assert_allclose(value[name], stats[name], rtol=tol, atol=tol * scale)
        for name in ref_grads:
            scale = max(1.0, np.abs(ref_grads[name]).max())
            np.testing.assert_allclose(grads[name], ref_grads[name], rtol=tol, atol=tol * scale,
                                       err_msg=name)


def _host(values: dict) -> dict:
    return {k: torch.as_tensor(v).detach().cpu().numpy() for k, v in values.items()}


def test_inactive_runs_are_skipped_and_others_unchanged(backend):
    """A run marked inactive (failed) keeps its gradients; the active ones give the same values
    and gradients as with every run active."""
    _, (problems, _) = _problems(3, 2, 9, 2, 2, 4, 1, False, False, torch.float64, fast=backend)
    problem, params = problems
    grads = {k: torch.zeros_like(v) for k, v in params.items() if k != "tau"}
    full = _host(problem.value_and_grad(params, grads, torch.ones(3, dtype=torch.bool)))
    kept = _host(grads)
    params["w_rec"][1] = torch.nan  # a failed run's parameters
    part = _host(problem.value_and_grad(params, grads, torch.tensor([True, False, True])))
    for name in full:
        np.testing.assert_array_equal(part[name][[0, 2]], full[name][[0, 2]])
    for name, value in _host(grads).items():
        np.testing.assert_array_equal(value[[0, 2]], kept[name][[0, 2]])
        np.testing.assert_array_equal(value[1], kept[name][1])


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs 2 numba threads")
@pytest.mark.parametrize("R", [3, 9, 17])
def test_cpu_kernels_give_the_same_bits_on_any_number_of_threads(R):
    """Both phases (value and every gradient) and the closed loop with a tangent give the same
    bits on 1 and 2 threads. With K = 3 experts a phase-1 chunk is 8 series (three blocks of 8
    lanes) of whichever runs: R = 3 (9 series of 3) makes 2 chunks, the second a single series,
    R = 9 makes 4 and R = 17 makes 7, most of them holding series of two runs; on 2 threads the
    threads claim them in an order that varies from call to call."""
    _, fast = _problems(R, 3, 11, 3, 2, 4, 1, True, True, torch.float64)
    model = ModelConfig(num_experts=3)
    gens = generators(range(R))
    experts, gating = init_experts(model, 3, 2, gens), init_gating(model, 3, 2, gens)
    state = random_state(experts, gating, 5, num_features=2, delay=1, generator=gens[0])
    tangents = initial_tangents(state.flat(), 1, torch.Generator().manual_seed(0))
    results = []
    before = numba.get_num_threads()
    try:
        for threads in (1, 2):
            numba.set_num_threads(threads)
            out = []
            for problem, params in fast:
                grads = {k: torch.zeros_like(v) for k, v in params.items()}
                out += [*_host(problem.value_and_grad(params, grads, torch.ones(R, dtype=bool)))
                        .values(), *_host(grads).values(),
                        *_host(problem.value(params, torch.ones(R, dtype=bool))).values()]
            run = COMPILED.closed_loop(experts, gating, state, 20, tangents=tangents, count=True)
            out += [run.outputs.numpy(), run.gates.numpy(), run.growth.numpy()]
            results.append(out)
    finally:
        numba.set_num_threads(before)
    assert len(results[0]) == len(results[1]) > 20
    for one, two in zip(*results, strict=True):
        np.testing.assert_array_equal(one, two)


def _trajectory_cases():
    """Every combination on each backend compared with the reference; on a backend interpreted
    here (gpu in Triton's interpreter, ~20-40 s a case) two in the default suite, covering both
    forms, both rates and both precisions, the other six marked slow."""
    cases = []
    for param in backend_params(reference=False):
        name = param.values[0]
        for dtype in (torch.float64, torch.float32):
            for form in ("paper", "mregn"):
                for adaptive in (False, True):
                    quick = name not in INTERPRETED or (dtype, form, adaptive) in (
                        (torch.float64, "paper", True), (torch.float32, "mregn", False))
                    cases.append(pytest.param(name, dtype, form, adaptive,
                                              id=f"{name}-{dtype}-{form}-{adaptive}",
                                              marks=() if quick else pytest.mark.slow))
    return cases


@pytest.mark.parametrize("backend, dtype, form, adaptive", _trajectory_cases(),
                         indirect=["backend"])
def test_training_trajectories_of_both_phases_match(backend, dtype, form, adaptive):
    steps, length = (4, 16) if backend.caps.interpreted else (12, 40)
    task = make_task(task_config("lissajous2", num_series=2, length=length), seed=0)
    series = torch.as_tensor(task.series, dtype=dtype)
    model = ModelConfig(learn_time_constants=True)
    model.experts.context_size, model.gating.context_size = 4, 5
    rule = TrainConfig(momentum_form=form)
    # (attraction stays off: at this rate its u_0 update has a gain of about 10 per step, so any
    # rounding difference grows exponentially; its gradient is checked above)
    phase1 = ExpertPhaseConfig(steps=steps, adaptive_lr=adaptive, learning_rate=0.05,
                               log_every=1)
    phase2 = GatingPhaseConfig(steps=steps, adaptive_lr=adaptive, learning_rate=1.0, log_every=1)
    out = []
    for each in (REFERENCE, backend):
        experts, beta, rows1 = train_experts(init_experts(model, 2, 2, generators([0, 1]), dtype),
                                             series, model, phase1, rule, backend=each)
        gating, rows2 = train_gating(init_gating(model, 2, 2, generators([0, 1]), dtype),
                                     torch.softmax(beta, -1), series[:, :-1], model, phase2,
                                     rule=rule, backend=each)
        out.append((experts, beta, gating, rows1 + rows2))
    ref, fast = out
    tol = TOLERANCE[dtype] * (100 if dtype == torch.float32 else 1)  # 24 steps of float32
    torch.testing.assert_close(fast[1], ref[1], rtol=tol, atol=tol)
    for a, b in ((ref[0], fast[0]), (ref[2], fast[2])):
        for k in a:
            torch.testing.assert_close(b[k], a[k], rtol=tol, atol=tol, msg=k)
    assert [r["retries"] for r in ref[3]] == [r["retries"] for r in fast[3]]
    if adaptive:
        assert any(r["lr_scale"] != 1.0 for r in fast[3])


def test_gpu_candidate_steps_in_one_call_train_as_one_by_one(monkeypatch):
    """The gpu backend evaluates k adaptive-rate candidates per call and each run takes its first
    accepted one: both phases give the same bits and history as k = 1 (one trial per call), with
    retries accepted after 1-4 shrinks and steps given up after max_retries = 5 (not a multiple
    of k = 3, so the last call is cut short)."""
    gpu, why = available("gpu")
    if gpu is None:
        pytest.skip(f"backend gpu cannot run here: {why}")
    from moex.kernels.gpu import phases

    task = task_config("lissajous2", num_series=2, length=5)
    series = torch.as_tensor(make_task(task, seed=0).series)
    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 4, 5
    rule = TrainConfig(adaptive=AdaptiveLRConfig(max_retries=5))
    phase1 = ExpertPhaseConfig(steps=3, adaptive_lr=True, learning_rate=2.0, log_every=1)
    phase2 = GatingPhaseConfig(steps=3, adaptive_lr=True, learning_rate=20.0, log_every=1)
    out = []
    for k in (1, 3):
        monkeypatch.setattr(phases._Problem, "trials", k)
        experts, beta, rows1 = train_experts(init_experts(model, 3, 2, generators([0, 1, 2])),
                                             series, model, phase1, rule, backend=gpu)
        gating, rows2 = train_gating(init_gating(model, 3, 2, generators([3, 4, 5])),
                                     torch.softmax(beta, -1), series[:, :-1], model, phase2,
                                     rule=rule, backend=gpu)
        out.append(({**experts, "beta": beta}, gating, rows1, rows2))
    for one, batched in zip(*out, strict=True):
        if isinstance(one, dict):
            for name in one:
                assert torch.equal(one[name], batched[name]), name
        else:
            assert one == batched
    for rows in out[0][2:]:
        retries = {r["retries"] for r in rows}
        assert 5 in retries and retries & {1, 2, 3, 4}, retries


def test_noisy_phase2_matches_reference_and_batches_equal_runs_alone(backend):
    """With input noise in phase 2, both backends draw the same noise; run r sees the noise of
    its own seed whether trained in a batch or alone."""
    steps, length = (3, 8) if backend.caps.interpreted else (6, 15)
    task = make_task(task_config("lissajous2", num_series=2, length=length), seed=0)
    series = torch.as_tensor(task.series)
    model = ModelConfig()
    model.gating.context_size = 5
    phase2 = GatingPhaseConfig(steps=steps, input_noise_var=1e-2)
    ghat = torch.softmax(torch.randn(3, 2, length - 1, 2,
                                     generator=torch.Generator().manual_seed(1)), -1)
    out = []
    for each in (REFERENCE, backend):
        out.append(train_gating(init_gating(model, 2, 2, generators([4, 5, 6])), ghat,
                                series[:, :-1], model, phase2, rule=TrainConfig(), backend=each,
                                seeds=[7, 8, 9])[0])
        alone = train_gating(init_gating(model, 2, 2, generators([5])), ghat[1:2], series[:, :-1],
                             model, phase2, rule=TrainConfig(), backend=each, seeds=[8])[0]
        for k in alone:
            torch.testing.assert_close(alone[k][0], out[-1][k][1], rtol=0, atol=1e-12)
    clean = train_gating(init_gating(model, 2, 2, generators([4, 5, 6])), ghat, series[:, :-1],
                         model, dataclasses.replace(phase2, input_noise_var=0.0),
                         rule=TrainConfig(), backend=backend, seeds=[7, 8, 9])[0]
    for k in clean:
        torch.testing.assert_close(out[1][k], out[0][k], rtol=1e-10, atol=1e-10)
    assert (clean["w_out"] - out[1]["w_out"]).abs().max() > 1e-6  # noise did act


def test_input_noise_comes_in_the_dtype_asked_drawn_and_scaled_in_float64():
    """float32 noise is the float64 noise rounded once (it was float64 before: NumPy 2 promotes
    float32 · a float64 scalar, which laid float32 lanes out as float64's on AVX-512)."""
    from moex.kernels.noise import input_noise

    wide = input_noise([3, 4], 5, (2, 7, 1), 0.01, np.float64)
    narrow = input_noise([3, 4], 5, (2, 7, 1), 0.01, torch.float32)
    assert wide.dtype == np.float64 and narrow.dtype == np.float32
    assert np.array_equal(narrow, wide.astype(np.float32)) and wide.std() > 0.05


def _closed_loop_model(K, D, delay, dtype):
    model = ModelConfig(num_experts=K, delay=delay)
    model.experts.context_size, model.gating.context_size = 4, 5
    experts = init_experts(model, 2, D, generators([1, 2]), dtype) if D else {}
    gating = init_gating(model, 2, D, generators([3, 4]), dtype)
    for params in (experts, gating):  # weights large enough for non-trivial dynamics
        for name in ("w_rec", "w_in"):
            if name in params:
                params[name] = params[name] * 8
    state = random_state(experts, gating, 3, num_features=D, delay=delay,
                         generator=torch.Generator().manual_seed(5))
    return experts, gating, state


def _closed_loop_cases():
    """(K, D, delay, k tangents, uniform gates): on each backend compared with the reference,
    every case in both precisions, and without tangents; on a backend interpreted here (slow)
    each feature once in float64 and one case in float32."""
    one = [(2, 2, 1, 1, False), (3, 2, 2, 1, False), (4, 0, 1, 1, False), (3, 2, 1, 1, True)]
    several = [(3, 2, 2, 3, False), (4, 0, 1, 2, False), (3, 2, 1, 2, True)]
    no_tangent = [(2, 2, 1, 0, False)]
    precisions = [(torch.float64, 1e-10), (torch.float32, 1e-4)]
    cases = []
    for param in backend_params(reference=False):
        name = param.values[0]
        if name in INTERPRETED:
            chosen = [(c, precisions[0]) for c in one + several + no_tangent] + [
                (several[0], precisions[1])]
        else:
            chosen = [(c, p) for c in one + several + no_tangent for p in precisions]
        cases += [pytest.param(name, *c, *p, id=f"{name}-{'-'.join(map(str, c))}-{p[0]}")
                  for c, p in chosen]
    return cases


@pytest.mark.parametrize("backend, K, D, delay, k, uniform, dtype, tol", _closed_loop_cases(),
                         indirect=["backend"])
def test_closed_loop_kernel_matches_reference(backend, K, D, delay, k, uniform, dtype, tol):
    """Outputs, gates, potentials, next state, tangents (up to the sign QR leaves free) and the
    log growth of the compiled closed loop equal the reference, with noise, without experts
    (symbolic tasks), with the C tool's uniform gates in the Jacobian, and without tangents."""
    steps = 20 if backend.caps.interpreted else 40
    experts, gating, state = _closed_loop_model(K, D, delay, dtype)
    tangents = torch.linalg.qr(torch.randn(state.flat().shape + (k,), dtype=dtype))[0] if k \
        else None
    noise = 0.1 * torch.randn(2, 3, steps, D, dtype=dtype)
    ref = reference.closed_loop(experts, gating, state, steps, noise=noise, tangents=tangents,
                                count=True, uniform_gates=uniform)
    fast = backend.closed_loop(experts, gating, state, steps, noise=noise, tangents=tangents,
                               count=True, uniform_gates=uniform)
    for a, b in zip(vars(ref.state).values(), vars(fast.state).values(), strict=True):
        torch.testing.assert_close(b, a, rtol=tol, atol=tol)
    for name in ("outputs", "gates", "gating_u", "growth"):
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), rtol=tol, atol=tol)
    if k:
        signs = torch.sign((ref.tangents * fast.tangents).sum(-2, keepdim=True))
        torch.testing.assert_close(fast.tangents * signs, ref.tangents, rtol=tol, atol=tol)
        assert ref.growth.abs().max() > 0.1  # the growth is not trivially zero


def test_closed_loop_kernel_leaves_its_input_state_alone(backend):
    experts, gating, state = _closed_loop_model(2, 2, 1, torch.float64)
    before = [x.clone() for x in vars(state).values()]
    backend.closed_loop(experts, gating, state, 5,
                        tangents=torch.linalg.qr(torch.randn(state.flat().shape + (1,)))[0])
    for a, b in zip(before, vars(state).values(), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("exponents", [1, 2])
def test_generation_and_exponents_equal_across_backends(backend, exponents):
    """The whole evaluation path (chunked, noise from one generator) gives the same samples and
    exponents on every backend."""
    experts, gating, state = _closed_loop_model(2, 2, 1, torch.float64)
    out = []
    for each in (REFERENCE, backend):
        chunks = []
        lam = closed_loop_lyapunov(experts, gating, state, 30, 7,
                                   generator=torch.Generator().manual_seed(0),
                                   num_exponents=exponents, noise_std=1e-2, on_chunk=chunks.append,
                                   backend=each)
        gen = generate(experts, gating, state, 20, noise_std=0.01,
                       generator=torch.Generator().manual_seed(1), backend=each)
        out.append((lam, torch.cat([c.outputs for c in chunks], 2), gen["outputs"]))
    for a, b in zip(*out, strict=True):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-10)


@pytest.fixture(scope="module")
def fixed_point():
    """A mixture (K = 2, D = 2, τ = 1) at a stable fixed point of its closed loop, found by
    running it 3000 steps, and the Jacobian of one step there (autograd), per run (2, dim, dim)."""
    model = ModelConfig(num_experts=2, delay=1)
    model.experts.context_size, model.gating.context_size = 4, 5
    experts = init_experts(model, 2, 2, generators([1, 2]))
    gating = init_gating(model, 2, 2, generators([3, 4]))
    start = random_state(experts, gating, 1, num_features=2, delay=1,
                         generator=torch.Generator().manual_seed(5))
    fixed = COMPILED.closed_loop(experts, gating, start, 3000).state
    jacobians = []
    for r in range(2):
        def step(x, r=r):
            one = [{k: v[r:r + 1] for k, v in net.items()} for net in (experts, gating)]
            return closed_loop_step(*one, fixed.like(x)).state.flat()

        jacobians.append(torch.func.jacrev(step)(fixed.flat()[r:r + 1])[0, 0, :, 0, 0, :])
    return experts, gating, fixed, torch.stack(jacobians)


def test_exponents_at_a_fixed_point_are_benettins_qr_of_its_jacobian(backend, fixed_point, k=2,
                                                                     transient=3, steps=12):
    """Lyapunov law on every backend: at a fixed point the tangent map is the constant Jacobian
    J, so the estimated spectrum is exactly (1/n) Σ ln |R_ii| of the QR iteration Q ← qr(J Q)
    from the same initial tangents (the transient's steps not counted)."""
    experts, gating, fixed, J = fixed_point
    lam = closed_loop_lyapunov(experts, gating, fixed, steps, transient,
                               generator=torch.Generator().manual_seed(0), num_exponents=k,
                               backend=backend)
    q = initial_tangents(fixed.flat(), k, torch.Generator().manual_seed(0))[:, 0]  # (2, dim, k)
    total = 0
    for t in range(transient + steps):
        q, log_r = reorthonormalise(J @ q)
        total = total + (log_r if t >= transient else 0)
    torch.testing.assert_close(lam[:, 0], total / steps, rtol=1e-10, atol=1e-12)


def test_exponents_at_a_fixed_point_converge_to_log_eigenvalue_moduli(fixed_point):
    """...and that iteration converges to ln |μ_i|, the log moduli of J's leading eigenvalues
    (here within 1e-3 after 300 + 300 steps: the leading moduli lie within 0.5 % of each other)."""
    experts, gating, fixed, J = fixed_point
    lam = closed_loop_lyapunov(experts, gating, fixed, 300, 300,
                               generator=torch.Generator().manual_seed(0), num_exponents=2,
                               backend=COMPILED)
    moduli = torch.linalg.eigvals(J).abs().sort(descending=True).values[:, :2]
    torch.testing.assert_close(lam[:, 0], moduli.log(), rtol=0, atol=1e-3)


def test_nearest_symbols_match_reference(backend):
    """Tensors in, int64 tensors out on the backend's device, the reference's symbols; with more
    prototypes than one of the gpu kernel's tiles, a tie between two tiles going to the first."""
    g = torch.Generator().manual_seed(0)
    points, prototypes = torch.rand(3, 37, 2, generator=g) * 2 - 1, torch.rand(40, 2, generator=g)
    symbols = torch.randint(0, 4, (40,), generator=g)
    prototypes[33], symbols[33] = prototypes[2], (symbols[2] + 1) % 4  # the same point, tiles 1, 3
    points[0, 0] = prototypes[2]
    got = backend.nearest_symbols(points, prototypes, symbols)
    assert got.dtype == torch.int64 and got.shape == (3, 37)
    assert got.device.type == torch.device(backend.device).type
    torch.testing.assert_close(got.cpu(), REFERENCE.nearest_symbols(points, prototypes, symbols))


def test_backend_choice(monkeypatch):
    assert get_backend("auto", "cpu").name == "cpu"
    assert get_backend("compiled").name == "cpu"  # the old name
    assert get_backend("reference").name == "reference"
    assert get_backend("auto", "cuda").name == "gpu"  # Triton is a dev dependency
    with pytest.raises(ValueError, match="backend=cpu runs on the CPU only"):
        get_backend("cpu", "cuda")
    with pytest.raises(ValueError, match="backend='numba'; choose one of auto, reference, cpu"):
        get_backend("numba")
    from moex.kernels import gpu

    monkeypatch.setattr(gpu, "INTERPRET", False)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="backend=gpu needs device=cuda and a CUDA device"):
            get_backend("gpu", "cpu")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("name", [n for n in REGISTRY if n != "cpu"])  # those that run on CUDA
def test_cuda_backends_match_cpu(name):
    """On a real GPU: the reference and the Triton kernels (compiled, not interpreted) give the
    cpu backend's statistics and gradients on both phases."""
    cuda = get_backend(name, "cuda")
    for ref_side, gpu_side in zip(*_problems(2, 3, 37, 2, 2, 10, 1, True, True, torch.float64,
                                             fast=cuda), strict=True):
        results = []
        for problem, params in (ref_side, gpu_side):
            grads = {k: torch.zeros_like(v) for k, v in params.items()}
            active = torch.ones(2, dtype=torch.bool)
            results.append((_host(problem.value_and_grad(params, grads, active)),
                            _host(grads)))
        for a, b in zip(*results, strict=True):
            for k in a:
                np.testing.assert_allclose(b[k], a[k], rtol=1e-10, atol=1e-10, err_msg=k)


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_cpu_step_after_an_accepted_trial_reuses_its_forward_pass_bit_for_bit(monkeypatch, noise):
    """The cpu backend's gradient step after an accepted adaptive trial takes the trial's forward
    pass from the lanes (`lanes.Forwarded`): both phases trained so (with retries, steps given up
    after 2 retries, learned τ and 3 runs whose lanes share blocks) equal the same training with
    every forward pass run afresh, bit for bit; with phase-2 input noise (fresh inputs every
    step) nothing is reused. (The training loop's separate calls; the stepper's record of its
    lanes: tests/test_step.py.)"""
    from moex.kernels.cpu import lanes, phases

    monkeypatch.setattr(phases._Problem, "stepper", lambda self, *a, **k: None)

    task = make_task(task_config("lissajous2", num_series=3, length=40), seed=1)
    series = torch.as_tensor(task.series)
    model = ModelConfig(learn_time_constants=True)
    model.experts.context_size, model.gating.context_size = 4, 5
    rule = TrainConfig(adaptive=AdaptiveLRConfig(max_retries=2))  # some steps are given up
    phase1 = ExpertPhaseConfig(steps=12, adaptive_lr=True, learning_rate=0.3, log_every=1)
    phase2 = GatingPhaseConfig(steps=12, adaptive_lr=True, learning_rate=20.0, log_every=1,
                               input_noise_var=noise)
    calls = []
    original = lanes.Forwarded.stale

    def spy(self, params, active):  # (active runs, runs given a forward pass) per gradient step
        result = original(self, params, active)
        calls.append((int(active.sum()), int(result.sum())))
        return result

    monkeypatch.setattr(lanes.Forwarded, "stale", spy)
    out = []
    for reuse in (True, False):
        monkeypatch.setattr(lanes.Forwarded, "enabled", reuse)
        calls.clear()
        experts, beta, rows1 = train_experts(init_experts(model, 3, 2, generators([0, 1, 2])),
                                             series, model, phase1, rule, backend=COMPILED)
        gating, rows2 = train_gating(init_gating(model, 3, 2, generators([0, 1, 2])),
                                     torch.softmax(beta, -1), series[:, :-1], model, phase2,
                                     rule=rule, backend=COMPILED)
        out.append(({**experts, "beta": beta, **{f"g_{k}": v for k, v in gating.items()}},
                    rows1 + rows2, list(calls)))
    (reused, rows, calls_on), (fresh, fresh_rows, calls_off) = out
    for k in reused:
        assert torch.equal(reused[k], fresh[k]), k
    assert rows == fresh_rows
    for phase in ("experts", "gating"):  # retried, and given up (2 retries: still rejected)
        assert {1, 2} <= {r["retries"] for r in rows if r["phase"] == phase}, phase
    assert all(active == stale for active, stale in calls_off)
    phase1_calls, phase2_calls = calls_on[:12], calls_on[12:]
    assert sum(active - stale for active, stale in phase1_calls) >= 12  # most runs reused
    saved = sum(active - stale for active, stale in phase2_calls)
    assert saved == 0 if noise else saved >= 12


@pytest.mark.parametrize("shape, dtype", [((3, 10, 8), np.float64), ((1,), np.float32),
                                          ((2, 0, 8), np.float64), ((5, 3, 2, 8), np.float64)])
def test_lane_arrays_start_on_a_cache_line(shape, dtype):
    """`simd.zeros` (the cpu kernels' lane arrays): zeros of the shape and dtype asked for, C
    contiguous, starting on a 64-byte line (numpy starts small arrays on 16), so that every block
    row of LB float64 is one cache line."""
    from moex.kernels.cpu.simd import ALIGN, zeros

    for _ in range(20):  # numpy's allocator lands on other offsets from call to call
        x = zeros(shape, dtype)
        assert x.shape == shape and x.dtype == dtype and x.flags.c_contiguous
        assert x.ctypes.data % ALIGN == 0 or x.size == 0  # (an empty one is never read)
        assert not x.any()


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("rows, length", [(18, 1000), (3, 1), (5, 17)])
def test_line_rows_start_every_row_on_a_cache_line(rows, length, dtype):
    """`simd.line_rows` (the phase-1 mixture's rows of time steps, allocated in a kernel): rows of
    at least `length` entries, each starting on a 64-byte line, padded by less than a line."""
    from numba import njit

    from moex.kernels.cpu.simd import ALIGN, line_rows

    @njit
    def allocate(rows, length, like):
        return line_rows(rows, length, like)

    like = np.zeros(1, dtype)
    for _ in range(20):  # the allocator lands on other offsets from call to call
        x = allocate(rows, length, like)
        assert x.shape[0] == rows and length <= x.shape[1] < length + ALIGN // x.itemsize
        assert x.dtype == dtype and x.flags.c_contiguous
        assert all(x[r].ctypes.data % ALIGN == 0 for r in range(rows))


def _float32_ulps(out: np.ndarray, exact: np.ndarray) -> np.ndarray:
    """|out - exact| in units of the last place of exact rounded to float32."""
    return np.abs(out - exact) / np.spacing(np.abs(exact).astype(np.float32)).astype(np.float64)


def test_vectorised_tanh_is_within_2_ulp_in_float32_and_1e_14_in_float64():
    """`simd.tanh` (the cpu kernels' own, so that lane loops vectorise): for float32 within 2 ulp
    of the exact tanh (float64's, rounded) at every 999th float32 of |x| < 50 (both signs: 2.2
    million values; float32 arithmetic, tanh x / 2 doubled: at most 1.877 ulp over every float32,
    the slow test below), and exactly odd; in float64 within 1e-14 of numpy's. Blocks of 16
    float32 lanes rely on the float32 one."""
    from moex.kernels.cpu.simd import tanh

    @numba.njit(error_model="numpy")
    def apply(x, out):
        for i in range(x.size):
            out[i] = tanh(x[i])

    x = np.arange(0, 0x7F800000, 37 * 27, dtype=np.int64).astype(np.uint32).view(np.float32)
    x = x[np.abs(x) < 50]
    x = np.concatenate([x, -x])
    out = np.empty_like(x)
    apply(x, out)
    assert _float32_ulps(out, np.tanh(x.astype(np.float64))).max() <= 2.0
    np.testing.assert_array_equal(out[: len(x) // 2], -out[len(x) // 2:])
    assert out.dtype == np.float32 and out[x == 0].size and not out[x == 0].any()
    x64 = np.random.default_rng(0).uniform(-30, 30, 100_000)
    out64 = np.empty_like(x64)
    apply(x64, out64)
    assert np.abs(out64 - np.tanh(x64)).max() < 1e-14


@pytest.mark.slow
def test_the_float32_tanh_is_within_2_ulp_at_every_float32():
    """Every non-negative float32 below infinity (2.1 billion, in chunks of 2^24; ~1-2 min):
    `simd.tanh` within 2 ulp of float64's tanh rounded (1.877 ulp at most, near x = 1.02), and
    odd."""
    from moex.kernels.cpu.simd import tanh

    @numba.njit(error_model="numpy")
    def apply(x, out):
        for i in range(x.size):
            out[i] = tanh(x[i])

    largest, chunk = 0.0, 1 << 24
    for start in range(0, 0x7F800000, chunk):
        x = np.arange(start, min(start + chunk, 0x7F800000), dtype=np.uint32).view(np.float32)
        out, mirrored = np.empty_like(x), np.empty_like(x)
        apply(x, out)
        apply(-x, mirrored)
        np.testing.assert_array_equal(mirrored, -out)
        largest = max(largest, _float32_ulps(out, np.tanh(x.astype(np.float64))).max())
    assert largest <= 2.0


def test_vectorised_exp_and_log_match_numpy_over_the_range_the_kernels_use():
    """`simd.exp` within 1e-14 relative of numpy's on |x| <= 700 and clamped beyond (its
    clamp: llvm.maxnum/minnum, vectorisable); `simd.log` within 1e-15 relative on normal doubles
    from e^-700 to e^700."""
    from moex.kernels.cpu.simd import exp, log

    @numba.njit(error_model="numpy")
    def apply(x, out_exp, out_log):
        for i in range(x.size):
            out_exp[i] = exp(x[i])
            out_log[i] = log(out_exp[i])

    x = np.random.default_rng(0).uniform(-700, 700, 200_000)
    out_exp, out_log = np.empty_like(x), np.empty_like(x)
    apply(x, out_exp, out_log)
    assert np.abs(out_exp / np.exp(x) - 1).max() < 1e-14
    assert np.abs(out_log / np.log(out_exp) - 1).max() < 1e-15
    far = np.array([-1e4, -701.0, 701.0, 1e4])
    out_exp, out_log = np.empty_like(far), np.empty_like(far)
    apply(far, out_exp, out_log)
    np.testing.assert_allclose(out_exp, np.exp([-700.0, -700.0, 700.0, 700.0]), rtol=1e-14)


def test_the_float32_tanh_rational_is_what_its_fitting_script_gives():
    """`python tools/fit_tanh_rational.py` (the fit of `simd._TANH_P` / `_TANH_Q`; one BLAS
    thread, ~1 s) prints the kernels' coefficients (rounded to float32, to one float32 ulp:
    another BLAS may round its least squares otherwise) and a largest relative error left in
    tanh x below 2e-8 at its points."""
    from moex.kernels.cpu.simd import _TANH_P, _TANH_Q

    script = Path(__file__).parent.parent / "tools" / "fit_tanh_rational.py"
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert float(out[0].split()[-1]) < 2e-8
    for line, kernels in zip(out[1:], (_TANH_P, _TANH_Q), strict=True):
        fitted = np.float32(ast.literal_eval(line.split(" = ")[1]))
        np.testing.assert_allclose(fitted, np.float32(kernels), rtol=1.2e-7)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_a_blocks_history_by_lane_is_its_transpose_and_comes_back_bit_for_bit(dtype):
    """Phase 1's outputs and ∂L/∂o between a block's (T, D, LB) and rows by lane (D, LB, T'):
    `transpose_tile`'s shuffles over whole tiles, element by element after them (T = 2 LB + 5:
    both), every bit moved (NaN payloads, -0.0, infinities, subnormals), nothing written beyond
    T."""
    from moex.kernels.cpu.phases import _by_lane, _by_step
    from moex.kernels.cpu.simd import width

    LB, D = width(np.dtype(dtype)), 2
    T = 2 * LB + 5
    bits = np.dtype(f"u{np.dtype(dtype).itemsize}")
    block = np.random.default_rng(0).integers(0, np.iinfo(bits).max, (T, D, LB), bits,
                                              endpoint=True).view(dtype)
    tiny = np.finfo(dtype).smallest_subnormal
    block[0, 0, :5] = -0.0, np.inf, -np.inf, tiny, np.nan  # and random NaN payloads besides
    block[-1, -1, -2:] = np.nan, -tiny  # in the part moved element by element too
    rows = np.zeros((D, LB, 3 * LB), dtype)
    _by_lane(block, rows)
    np.testing.assert_array_equal(rows[:, :, :T].view(bits), block.transpose(1, 2, 0).view(bits))
    assert not rows[:, :, T:].view(bits).any()
    back = np.zeros_like(block)
    _by_step(rows, back)
    np.testing.assert_array_equal(back.view(bits), block.view(bits))


def test_a_tile_is_moved_only_between_c_contiguous_arrays_of_one_dtype():
    """`transpose_tile` reads its arrays as flat data of one element type: a strided view or a
    second dtype would be read or written wrongly, so such a call does not compile."""
    from moex.kernels.cpu.simd import transpose_tile

    @numba.njit
    def move(src, dst):
        transpose_tile(src, 0, 8, dst, 0, 8)

    good = np.zeros((8, 8))
    move(good, np.zeros((8, 8)))
    for src, dst in ((good, np.zeros((8, 16), np.float32)), (np.zeros((8, 16))[:, ::2], good),
                     (good, np.zeros((8, 16))[:, ::2])):
        with pytest.raises(numba.core.errors.TypingError):
            move(src, dst)


def test_vectorised_exp_and_log_are_within_2_ulp_in_float32():
    """`simd.exp` and `simd.log` of float32 arguments, in float32 arithmetic (the phase-1 mixture
    and the phase-2 softmax of float32 runs): within 2 ulp of the exact value (float64's) at every
    997th float32 in exp's range [-87, 88] and of log's normal positive floats (exhaustively, in
    a scratch run: at most 1.06 and 0.83 ulp); exp clamped beyond, and returning float32."""
    from moex.kernels.cpu.simd import exp, log

    @numba.njit(error_model="numpy")
    def apply(x, out_exp, out_log):
        for i in range(x.size):
            out_exp[i] = exp(x[i])
            out_log[i] = log(x[i])

    every = np.arange(0, 0x7F800000, 997, dtype=np.int64).astype(np.uint32).view(np.float32)
    for x, f, which in ((np.concatenate([every[every <= 88], -every[every <= 87]]), np.exp, 0),
                       (every[every >= np.finfo(np.float32).tiny], np.log, 1)):
        out = (np.empty_like(x), np.empty_like(x))
        apply(x, *out)
        assert out[which].dtype == np.float32
        assert _float32_ulps(out[which], f(x.astype(np.float64))).max() <= 2.0
    far = np.array([-1e4, -88.0, 89.0, 1e4], np.float32)
    out = (np.empty_like(far), np.empty_like(far))
    apply(far, *out)
    np.testing.assert_allclose(out[0], np.exp([-87.0, -87.0, 88.0, 88.0]), rtol=2e-7)


_WIDTH_PROBE = """
import sys
import numpy as np
from moex.kernels.cpu import simd
simd.WIDTHS[np.dtype(np.float32)] = int(sys.argv[1])  # before anything compiles
from moex.kernels.cpu import rnn
from tests.test_kernels import rnn_blocks
np.save(sys.argv[2], rnn_blocks(rnn, simd.width(np.float32)))
"""


def rnn_blocks(rnn, LB, lanes=16, T=7, NI=3, H=5, NO=2, compiled=False, dtype=np.float32):
    """The forward pass and BPTT (learned τ) of `lanes` random lanes, run in blocks of LB lanes,
    with the sizes compiled in (`lanes.sizes`) or not; every output of every lane, flattened in
    lane order."""
    g = np.random.default_rng(3)
    sizes = ((0,) * H, (0,) * NI, (0,) * NO) if compiled else ((), (), ())

    def draw(*shape, scale=1.0):
        return (scale * g.standard_normal(shape + (lanes,))).astype(dtype)

    X, w_in, w_rec, w_out = draw(T, NI), draw(H, NI), draw(H, H, scale=0.5), draw(NO, H)
    b_c, b_o, u0, DY = draw(H), draw(NO), draw(H), draw(T, NO)
    eps = g.uniform(0.1, 1.0, (H, lanes)).astype(dtype)
    out = []
    for lo in range(0, lanes, LB):
        def part(x, lo=lo):
            return np.ascontiguousarray(x[..., lo:lo + LB])

        def new(*shape, dtype=dtype):
            return np.zeros(shape + (LB,), dtype)

        C0, C, Y, U = new(H), new(T, H), new(T, NO), new(T, H)
        S1, S2 = new(H, dtype=np.float64), new(H, dtype=np.float64)
        rnn.forward_pass(part(X), part(w_in), part(w_rec), part(w_out), part(b_c), part(b_o),
                         part(eps), part(u0), True, C0, C, Y, U, S1, S2, sizes)
        grads = (new(H, NI), new(H, H), new(NO, H), new(H), new(NO), new(H), new(H))
        rnn.backward_pass(part(DY), part(X), C0, C, U, part(u0), part(w_rec), part(w_out),
                          part(eps), *grads, sizes)
        out.append(np.concatenate([np.moveaxis(a, -1, 0).reshape(LB, -1).astype(np.float64)
                                   for a in (C0, C, Y, U, S1, S2) + grads], 1))
    return np.concatenate(out)


def test_float32_blocks_of_8_and_16_lanes_give_the_same_bits(tmp_path):
    """The block width is a compile-time constant (`simd.width`: 16 float32 lanes on a CPU with
    AVX-512, 8 without) and no lane reads another: the forward pass and BPTT of 16 float32 lanes
    give the same bits in blocks of 16 as in blocks of 8 (the other width compiled in a process of
    its own, with a cache of its own), so float32 results do not depend on the CPU's width."""
    import subprocess
    import sys

    from moex.kernels.cpu import rnn, simd

    here = simd.width(np.float32)
    other = 24 - here
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    done = subprocess.run([sys.executable, "-c", _WIDTH_PROBE, str(other), str(tmp_path / "o")],
                          capture_output=True, text=True, env=env, timeout=600,
                          cwd=Path(__file__).parents[1])
    assert done.returncode == 0, done.stderr
    theirs, ours = np.load(tmp_path / "o.npy"), rnn_blocks(rnn, here)
    assert ours.shape == theirs.shape and np.isfinite(ours).all() and ours[:, :5].any()
    np.testing.assert_array_equal(ours, theirs)


@pytest.mark.parametrize("dtype, NI, H, NO", [(np.float64, 1, 3, 1), (np.float32, 3, 5, 2)])
def test_the_rnn_passes_compiled_for_their_sizes_give_the_bits_of_the_passes_for_any_size(
        dtype, NI, H, NO):
    """`lanes.sizes`: with H, NI and NO compiled in as constants LLVM unrolls the loops over them,
    but no operation changes or moves (no reassociation is allowed): every output of the
    forward pass and of BPTT (learned τ) equals the one-for-every-size kernel's, bit for bit."""
    from moex.kernels.cpu import rnn, simd

    LB = simd.width(dtype)
    sized, any_size = (rnn_blocks(rnn, LB, lanes=2 * LB, T=9, NI=NI, H=H, NO=NO, compiled=c,
                                  dtype=dtype) for c in (True, False))
    assert np.isfinite(sized).all() and sized.any()
    assert sized.tobytes() == any_size.tobytes()


def test_the_kernels_size_choice_is_checked(monkeypatch):
    from moex.errors import ConfigError
    from moex.kernels.cpu.lanes import sizes

    monkeypatch.setenv("MOEX_CPU_SIZES", "compiled")
    assert sizes(3, 2, 1) == ((0, 0, 0), (0, 0), (0,))
    monkeypatch.setenv("MOEX_CPU_SIZES", "runtime")
    assert sizes(3, 2, 1) == ((), (), ())
    monkeypatch.setenv("MOEX_CPU_SIZES", "fixed")
    with pytest.raises(ConfigError, match="MOEX_CPU_SIZES=fixed; choose compiled or runtime"):
        sizes(3, 2, 1)


def test_forward_pass_record_of_runs_whose_lanes_share_blocks():
    """`Forwarded` with 8 lanes a block and 6 lanes a run: run 0 in block 0, run 1 in blocks 0
    and 1, run 2 in blocks 1 and 2. Recomputing block 0 alone (run 0 stale) after run 1's
    parameters changed leaves run 1 half old, half new: stale; run 0 current; run 2 untouched."""
    from moex.kernels.cpu.lanes import Forwarded, runs_of_blocks

    record = Forwarded(runs_of_blocks(3, 6, 3, 8), 6, ("w",), 8)
    params = {"w": np.zeros((3, 2))}
    everyone = np.ones(3, bool)
    np.testing.assert_array_equal(record.stale(params, everyone), everyone)  # nothing recorded
    record.record(params, everyone)
    np.testing.assert_array_equal(record.stale(params, everyone), [False, False, False])
    changed = {"w": np.array([[0.0, 0.0], [1.0, 0.0], [0.0, -0.0]])}  # -0.0 differs from 0.0
    np.testing.assert_array_equal(record.stale(changed, everyone), [False, True, True])
    record.record(changed, np.array([True, False, False]))
    np.testing.assert_array_equal(record.stale(changed, everyone), [False, True, True])
    np.testing.assert_array_equal(record.stale(params, everyone), [False, True, False])
    record.forget()
    np.testing.assert_array_equal(record.stale(params, everyone), everyone)


@pytest.mark.parametrize("R", [1, 2])
def test_staging_hands_contiguous_views_to_the_kernels_as_they_are(monkeypatch, R):
    """`lanes.Staging` with the training loop's (R, P) buffers: at R = 1 every group's view is
    C-contiguous, and the kernels read and write the buffers themselves (no copy); at R = 2 the
    views are strided and go through copies, gradients copied back. Either way a step of both
    phases gives the same bits as a step with every group copied (the copying staging)."""
    from moex.kernels.cpu import lanes
    from moex.train import _Flat

    problems = _problems(R, 3, 9, 2, 2, 4, 1, False, False, torch.float64)[1]
    for problem, params in problems:
        fixed = {"tau": params.pop("tau")}  # τ not learned: passed, no gradient
        layout = _Flat(params, torch.device("cpu"))
        theta, grad = layout.zeros(), layout.zeros()
        views, grads = layout.views(theta), layout.views(grad)
        for k, v in params.items():
            views[k].copy_(v)
        net = {**views, **fixed}
        staged, written = problem.staging.load(net), problem.staging.outputs(grads)
        for k in views:
            shared = np.shares_memory(staged[k], theta.numpy())
            assert shared == (R == 1) and np.shares_memory(written[k], grad.numpy()) == (R == 1)
            np.testing.assert_array_equal(staged[k], params[k].numpy())
        assert written["tau"] is problem.staging.grads["tau"]  # not learned: scratch
        active = torch.ones(R, dtype=torch.bool)
        results = []
        for direct in (True, False):
            if not direct:  # the staging before: every group copied
                monkeypatch.setattr(lanes, "_usable", lambda x, own: False)
                problem.staging.seen.clear()
            grad.fill_(float("nan"))  # every gradient must be written
            stats = problem.value_and_grad(net, grads, active)
            results.append((grad.clone(), stats))
            problem.forwarded.forget()
        (g1, s1), (g2, s2) = results
        assert torch.isfinite(g1).all() and torch.equal(g1, g2)
        assert all(torch.equal(s1[k], s2[k]) for k in s1)
        monkeypatch.undo()


def test_every_entry_point_to_the_time_loops_asks_for_its_backend():
    """No silent `auto`: training, evaluation and the closed loop take the backend as a required
    keyword, so a caller who forgets it gets a TypeError instead of the CPU."""
    import inspect

    from moex.closed_loop import closed_loop_lyapunov, generate
    from moex.evaluation import evaluate, track_metrics
    from moex.train import train_experts, train_gating

    for function in (train_experts, train_gating, generate, closed_loop_lyapunov, evaluate,
                     track_metrics):
        backend = inspect.signature(function).parameters["backend"]
        assert backend.kind is inspect.Parameter.KEYWORD_ONLY, function.__name__
        assert backend.default is inspect.Parameter.empty, function.__name__


def test_a_backend_is_one_registry_entry_and_its_interface_is_checked(monkeypatch):
    """A backend is a module of `BackendModule`'s names and one entry in `LOADERS`: a copy of the
    reference registered under a new name trains; a module lacking names is refused, by name,
    when it is chosen."""
    import types

    from moex import kernels
    from moex.kernels import reference

    monkeypatch.setitem(kernels.LOADERS, "mine", lambda device: kernels.Backend(
        "mine", device, kernels._checked(reference)))
    mine = kernels.get_backend("mine")
    task = make_task(task_config("lissajous2", num_series=2, length=30), seed=0)
    model = ModelConfig()
    model.experts.context_size = 3
    experts = init_experts(model, 2, 2, generators([0]))
    _, beta, rows = train_experts(experts, torch.as_tensor(task.series), model,
                                  ExpertPhaseConfig(steps=3, log_every=1), TrainConfig(),
                                  backend=mine)
    assert len(rows) == 4 and torch.isfinite(beta).all()
    half = types.ModuleType("half")
    half.ExpertProblem, half.GatingProblem = reference.ExpertProblem, reference.GatingProblem
    monkeypatch.setitem(kernels.LOADERS, "half", lambda device: kernels.Backend(
        "half", device, kernels._checked(half)))
    with pytest.raises(TypeError, match="half lacks closed_loop, nearest_symbols, warm_up, "
                                        "momentum_step, apply_step"):
        kernels.get_backend("half")
