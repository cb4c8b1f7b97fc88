"""A whole training step in one compiled call (`moex.kernels.cpu.step`) gives the bits of the
training loop's separate calls (gradient, momentum step, adaptive trials, update), in both
phases, both precisions, both momentum forms, at a fixed and the adaptive rate, with τ learned
and fixed, a run that fails, phase-2 input noise (fresh inputs every step: no forward pass
reused across it), and the lanes' record of their forward pass on and off; and it is one call
per step."""

import numba
import numpy as np
import pytest
import torch

from moex.config.model import ModelConfig
from moex.config.train import (
    AdaptiveLRConfig,
    ExpertPhaseConfig,
    GatingPhaseConfig,
    TrainConfig,
)
from moex.kernels import get_backend
from moex.kernels.cpu import phases, step, threads
from moex.kernels.cpu.lanes import Forwarded
from moex.model import init_experts, init_gating
from moex.train import train_experts, train_gating
from tests.helpers import generators

R, S, T, D = 3, 2, 9, 2


@pytest.fixture
def one_thread():
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(before)


def _train(dtype, adaptive, form, learn_tau, steps=6, rate=0.05, retries=1000, noise=0.01,
           S=S):
    """Both phases of R runs of S series (run 1's experts give NaN: it fails and is frozen);
    phase 1 at `rate`, trials given up after `retries`; phase 2 with input noise of variance
    `noise`."""
    model = ModelConfig(num_experts=2, learn_time_constants=learn_tau)
    model.experts.context_size, model.gating.context_size = 3, 4
    g = torch.Generator().manual_seed(0)
    series = torch.randn(S, T + 1, D, generator=g).tanh().to(dtype)
    experts = init_experts(model, S, D, generators([1, 2, 3]), dtype)
    experts["w_out"][1] = float("nan")
    rule = TrainConfig(momentum_form=form, adaptive=AdaptiveLRConfig(max_retries=retries))
    backend = get_backend("cpu")
    phase1 = ExpertPhaseConfig(steps=steps, adaptive_lr=adaptive, learning_rate=rate,
                               log_every=1)
    experts, beta, rows1 = train_experts(experts, series, model, phase1, rule, backend=backend)
    gating = init_gating(model, S, D, generators([1, 2, 3]), dtype)
    phase2 = GatingPhaseConfig(steps=steps, adaptive_lr=adaptive, learning_rate=1.0,
                               input_noise_var=noise)
    ghat = torch.softmax(torch.randn(R, S, T, 2, generator=g), -1).to(dtype)
    gating, rows2 = train_gating(gating, ghat, series[:, :-1], model, phase2, rule=rule,
                                 backend=backend)
    return experts, beta, gating, rows1 + rows2


def _bits(x: torch.Tensor) -> torch.Tensor:
    return x.contiguous().view(torch.int64 if x.dtype == torch.float64 else torch.int32)


def _same(a, b) -> None:
    for part_a, part_b in zip(a[:3], b[:3], strict=True):
        for k in part_a if isinstance(part_a, dict) else [None]:
            x, y = (part_a[k], part_b[k]) if k else (part_a, part_b)
            assert torch.equal(_bits(x), _bits(y)), k
    rows_a, rows_b = a[3], b[3]
    assert len(rows_a) == len(rows_b)
    for row_a, row_b in zip(rows_a, rows_b, strict=True):
        assert row_a.keys() == row_b.keys()
        for k, v in row_a.items():
            assert v == row_b[k] or (v != v and row_b[k] != row_b[k]), (row_a, row_b)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("adaptive", [True, False])
@pytest.mark.parametrize("form,learn_tau", [("paper", True), ("mregn", False)])
def test_a_whole_step_in_one_call_gives_the_separate_calls_bits(one_thread, monkeypatch,
                                                                 dtype, adaptive, form,
                                                                 learn_tau):
    made = []
    stepper = phases._Problem.stepper

    def counted(self, *args, **kwargs):
        made.append(stepper(self, *args, **kwargs))
        return made[-1]

    monkeypatch.setattr(phases._Problem, "stepper", counted)
    whole = _train(dtype, adaptive, form, learn_tau)
    assert len(made) == 2 and all(s is not None for s in made)  # both phases took it
    last = {(row["phase"], row["run"]): row["failed"] for row in whole[3]}  # the final rows
    assert last == {(phase, r): phase == "experts" and r == 1 for phase in ("experts", "gating")
                    for r in range(R)}
    monkeypatch.setattr(phases._Problem, "stepper", lambda self, *a, **k: None)
    _same(whole, _train(dtype, adaptive, form, learn_tau))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_whole_step_without_the_record_of_forward_passes_gives_the_same_bits(one_thread,
                                                                               monkeypatch,
                                                                               dtype):
    """With the record, a gradient step reuses an accepted trial's forward pass and objective
    (with ∂/∂o); without it, it computes them: the same bits, with phase-1 trials rejected (1
    retry) and given up (2), and phase 2 without input noise (with it nothing is reused)."""
    kept = _train(dtype, True, "paper", True, steps=12, rate=2.0, retries=2, noise=0.0)
    assert {1, 2} <= {row["retries"] for row in kept[3] if row["phase"] == "experts"}
    monkeypatch.setattr(Forwarded, "enabled", False)
    _same(kept, _train(dtype, True, "paper", True, steps=12, rate=2.0, retries=2, noise=0.0))



def test_a_run_that_accepted_its_trial_is_current_and_skips_the_next_forward_pass(one_thread,
                                                                                 monkeypatch):
    """The stepper's record is θ + Δθ's own buffer: after a step, a run that accepted a trial is
    current (its lanes hold the forward pass at that point, which θ now equals bit for bit) and
    the next gradient leaves it out of the forward pass; a run still pending after its last
    trial (its row of the record rewritten) is not current."""
    seen, gradients = [], []
    call, before = step.Stepper.__call__, step.before_gradient

    def watched(self):
        call(self)
        seen.append((self.current.copy(), self.pending.copy()))

    def recorded(lo, hi, current, failed, active, stale):
        was = current.copy()
        before(lo, hi, current, failed, active, stale)
        gradients.append((was[lo:hi], active[lo:hi].copy(), stale[lo:hi].copy()))

    monkeypatch.setattr(step.Stepper, "__call__", watched)
    monkeypatch.setattr(step, "before_gradient", recorded)
    _train(torch.float64, True, "paper", True, steps=12, rate=2.0, retries=2, noise=0.0)
    assert any(current.any() for current, _ in seen)
    assert not any((current & pending).any() for current, pending in seen)
    reused = [(was & active & ~stale).sum() for was, active, stale in gradients]
    assert sum(reused) > 0  # forward passes left out
    assert all((~stale[active] <= was[active]).all() for was, active, stale in gradients)
    assert sum((was & active & stale).sum() for was, active, stale in gradients) < sum(reused)


def test_a_separate_call_between_whole_steps_leaves_their_bits(one_thread, monkeypatch):
    """A separate call (`value`) between the stepper's steps runs its own forward passes in the
    lanes (here at parameters scaled by 0.9): the stepper's record of its passes is dropped, so
    its next gradient step computes them afresh instead of reusing the lanes, and the training
    gives the bits it gives without the call. The separate calls leave no record of their own
    while a stepper keeps one."""
    args = (torch.float64, True, "paper", True)
    kw = dict(steps=8, rate=2.0, retries=2, noise=0.0)  # trials accepted, rejected, given up
    plain = _train(*args, **kw)
    call, recorded = step.Stepper.__call__, []

    def interrupted(self):
        call(self)
        problem = self.problem
        other = {n: torch.from_numpy(a * (1.1 if n == "tau" else 0.9))
                 for n, a in problem.staging.params.items()}
        problem.value(other, np.ones(R, bool))
        recorded.append(problem.forwarded.current.any())

    monkeypatch.setattr(step.Stepper, "__call__", interrupted)
    _same(plain, _train(*args, **kw))
    assert len(recorded) == 16 and not any(recorded)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("phase", ["experts", "gating"])
def test_a_gradient_call_reuses_the_objective_of_the_trial_before_it(one_thread, dtype, phase):
    """The stepper's `reuse`: a call without gradients (an adaptive trial) computes the
    objective's ∂/∂o too (phase 1's mixture also ∂/∂β), and a gradient call at the same
    parameters skips the objective where it skips the forward pass. Shown by changing the targets
    between the two calls (the objective reads them, the forward pass does not): the gradient
    call still gives the statistics and every gradient of a fresh call at the old targets;
    without `reuse`, the new targets' statistics."""
    model = ModelConfig(num_experts=2)
    model.experts.context_size, model.gating.context_size = 3, 4
    g = torch.Generator().manual_seed(0)
    series = torch.randn(S, T + 1, D, generator=g).tanh().to(dtype)
    backend = get_backend("cpu")
    if phase == "experts":
        params = init_experts(model, S, D, generators([1, 2, 3]), dtype)
        params["beta"] = torch.randn(R, S, T, 2, generator=g).to(dtype)
        params["log_sigma"] = (0.3 * torch.randn(R, 2, generator=g)).to(dtype)
        problem = backend.expert_problem(series[:, :-1], series[:, 1:], model,
                                         ExpertPhaseConfig(), R)
    else:
        params = init_gating(model, S, D, generators([1, 2, 3]), dtype)
        ghat = torch.softmax(torch.randn(R, S, T, 2, generator=g), -1).to(dtype)
        problem = backend.gating_problem(ghat, series[:, :-1], model, GatingPhaseConfig(),
                                         [1, 2, 3])
    grads = {k: torch.zeros_like(v) for k, v in params.items() if k != "tau"}  # τ not learned
    p, written = problem.staging.load(params), problem.staging.outputs(grads)
    active, none = np.ones(R, bool), np.zeros(R, bool)

    def call(want_grad, stale, reuse, kept=()):
        for k, v in grads.items():  # every gradient must be written (∂/∂β: by the trial)
            if k not in kept:
                v.fill_(float("nan"))
        problem.evaluate(problem.kernel_args(p, written, want_grad, active, stale, reuse=reuse))
        problem.staging.store(grads, written)
        return problem.lanes.out.copy(), {k: v.clone() for k, v in grads.items()}

    out, fresh = call(True, active, False)
    assert all(torch.isfinite(v).all() for v in fresh.values())
    # ∂L/∂o in the lanes (phase 1's also by lane, `DY_lane`): the trial must write it
    for k in (6, 10) if phase == "experts" else (6,):
        problem.lanes.work[k].fill(float("nan"))
    call(False, active, True)  # the trial: its forward pass, its objective with ∂/∂o
    targets = problem.targets.copy()
    problem.targets[:] = 0.5 * problem.targets + 0.25
    reused_out, reused = call(True, none, True, kept=("beta",))
    np.testing.assert_array_equal(reused_out, out)
    for k in fresh:
        assert torch.equal(_bits(reused[k]), _bits(fresh[k])), k
    changed_out, _ = call(True, none, False)  # the forward pass reused, the objective not
    assert (changed_out[1] != out[1]).all()  # ln p (Σ ĝ ln g) at the new targets
    problem.targets[:] = targets


def test_a_whole_step_is_one_call_however_many_trials(one_thread, monkeypatch):
    """No training step goes through the problem's separate calls (`value_and_grad`, `value`):
    only the last evaluation after the loop does, the same count for 2 steps as for 8."""
    calls = []
    call = phases._Problem._call

    def counted(self, *args):
        calls.append(args[-1])
        return call(self, *args)

    monkeypatch.setattr(phases._Problem, "_call", counted)
    counts = []
    for steps in (2, 8):
        calls.clear()
        _train(torch.float64, True, "paper", True, steps=steps)
        counts.append(len(calls))
    assert counts[0] == counts[1] > 0


@pytest.mark.parametrize("crew", [False, True])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_whole_step_on_two_threads_gives_the_bits_of_one(monkeypatch, dtype, crew):
    """On two threads the stepper shares out each stage (phase 1's chunks of runs, the update's
    runs: here however small the buffers) and gives one thread's bits; the separate calls on two
    threads give them too. With `crew` every phase counts as long (`step.LONG` 0): from its
    second step on the stepper's calls go to its crew's worker (`threads.Crew`), which the
    staging copies' calls through the pool release every step; without, the crew's loop is
    neither compiled nor loaded, and every call goes through the pool."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread here")
    monkeypatch.setattr(threads, "SPLIT", 0)
    monkeypatch.setattr(step, "LONG", 0.0 if crew else float("inf"))
    if not crew:  # (nor loaded: compiled in this process or cached by another test)
        monkeypatch.setattr(threads, "_loaded", lambda *args: False)
    before = numba.get_num_threads()
    made, stepper = [], phases._Problem.stepper

    def counted(self, *args, **kwargs):
        made.append(stepper(self, *args, **kwargs))
        return made[-1]

    try:
        numba.set_num_threads(1)
        one = _train(dtype, True, "paper", True)
        numba.set_num_threads(2)
        monkeypatch.setattr(phases._Problem, "stepper", counted)
        _same(one, _train(dtype, True, "paper", True))
        assert len(made) == 2 and all(s is not None for s in made)
        # the worker ended calls of every kind (its count of calls ended), or none at all
        assert all(s.crew.ready == crew for s in made)
        assert all((s.crew.control[0, 4] >= 3 * 4) == crew for s in made)
        monkeypatch.setattr(phases._Problem, "stepper", lambda self, *a, **k: None)
        _same(one, _train(dtype, True, "paper", True))
    finally:
        numba.set_num_threads(before)


@pytest.mark.parametrize("adaptive", [True, False])
def test_each_run_finished_in_the_kernel_call_gives_the_separate_calls_bits(monkeypatch,
                                                                           adaptive):
    """Both phase kernels make each run's sums in the stepper's calls, and its update
    (`update.after_gradient`) in the gradient's call, in the thread that finishes the run's last
    chunk of series (phase 1) or block of lanes (phase 2) (the kernels' `left`). With 3 series a
    phase-1 chunk of 4 holds series of two runs and a run's series lie in two chunks, and a
    phase-2 block of 8 lanes holds three runs' lanes, the third's in two blocks; on two threads
    (chunks and blocks claimed in any order) every run is finished once per call, after all its
    chunks or blocks, and the training gives the bits of the separate calls on one thread, with
    phase-1 trials accepted, rejected and given up (adaptive: 2 retries)."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread here")
    before, calls, made = numba.get_num_threads(), {}, []
    stepper = phases._Problem.stepper

    def watch(problem):
        evaluate = problem.evaluate

        def watched(self, args, *share):
            evaluate(self, args, *share)
            calls.setdefault(problem, []).append(args[-2].copy())  # each run's items left

        monkeypatch.setattr(problem, "evaluate", watched)

    def counted(self, *args, **kwargs):
        made.append(stepper(self, *args, **kwargs))
        return made[-1]

    try:
        numba.set_num_threads(1)
        monkeypatch.setattr(phases._Problem, "stepper", lambda self, *a, **k: None)
        kw = dict(S=3, rate=2.0, retries=2) if adaptive else dict(S=3)
        separate = _train(torch.float64, adaptive, "paper", True, **kw)
        numba.set_num_threads(2)
        monkeypatch.setattr(phases._Problem, "stepper", counted)
        watch(phases.ExpertProblem)
        watch(phases.GatingProblem)
        _same(separate, _train(torch.float64, adaptive, "paper", True, **kw))
    finally:
        numba.set_num_threads(before)
    # the calls without a stepper take arguments of the same types: one compiled kernel
    for made_ in made:
        left, update = made_.evaluations[True][2][-2:]
        assert numba.typeof((left, update)) == numba.typeof(step.idle(made_.problem))
    if adaptive:
        assert {0, 1, 2} <= {row["retries"] for row in separate[3] if row["phase"] == "experts"}
    assert list(made[0].problem.items_of_run) == [1, 2, 2]
    assert list(made[1].problem.items_of_run) == [1, 1, 2]
    # 6 steps of each phase, a gradient call each and (adaptive) trial calls; every run
    # finished once in each
    for problem in (phases.ExpertProblem, phases.GatingProblem):
        finished = [left for left in calls[problem] if left.size]
        assert len(finished) >= 6 * (1 + adaptive), problem
        assert all((left == 0).all() for left in finished), problem


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_kernels_compiled_for_the_network_sizes_train_to_the_same_bits(monkeypatch, dtype):
    """Both phases, adaptive, τ learned, with the kernels compiled for the networks' sizes
    (`lanes.sizes`, the default outside the suite) and with the kernels for any size: the same
    parameters, β and training rows, bit for bit (about 40 s of compiles per precision)."""
    results = []
    for choice in ("compiled", "runtime"):
        monkeypatch.setenv("MOEX_CPU_SIZES", choice)
        results.append(_train(dtype, True, "paper", True))
    _same(*results)
