"""A whole training step in one compiled call (`moex.kernels.cpu.step`) gives the bits of the
training loop's separate calls (gradient, momentum step, adaptive trials, update), in both
phases, both precisions, both momentum forms, at a fixed and the adaptive rate, with τ learned
and fixed, a run that fails, phase-2 input noise (fresh inputs every step: no forward pass
reused across it), and the lanes' record of their forward pass on and off; and it is one call
per step."""

import numba
import pytest
import torch

from moex.config.model import ModelConfig
from moex.config.train import ExpertPhaseConfig, GatingPhaseConfig, TrainConfig
from moex.kernels import get_backend
from moex.kernels.cpu import phases, step
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


def _train(dtype, adaptive, form, learn_tau, steps=6):
    """Both phases of R runs (run 1's experts give NaN: it fails and is frozen)."""
    model = ModelConfig(num_experts=2, learn_time_constants=learn_tau)
    model.experts.context_size, model.gating.context_size = 3, 4
    g = torch.Generator().manual_seed(0)
    series = torch.randn(S, T + 1, D, generator=g).tanh().to(dtype)
    experts = init_experts(model, S, D, generators([1, 2, 3]), dtype)
    experts["w_out"][1] = float("nan")
    rule = TrainConfig(momentum_form=form)
    backend = get_backend("cpu")
    phase1 = ExpertPhaseConfig(steps=steps, adaptive_lr=adaptive, learning_rate=0.05)
    experts, beta, rows1 = train_experts(experts, series, model, phase1, rule, backend=backend)
    gating = init_gating(model, S, D, generators([1, 2, 3]), dtype)
    phase2 = GatingPhaseConfig(steps=steps, adaptive_lr=adaptive, learning_rate=1.0,
                               input_noise_var=0.01)
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


def test_a_whole_step_without_the_record_of_forward_passes_gives_the_same_bits(one_thread,
                                                                               monkeypatch):
    kept = _train(torch.float64, True, "paper", True)
    monkeypatch.setattr(Forwarded, "enabled", False)
    _same(kept, _train(torch.float64, True, "paper", True))


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


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_whole_step_on_two_threads_gives_the_bits_of_one(monkeypatch, dtype):
    """On two threads the stepper shares out each stage (phase 1's chunks of runs, the update's
    runs: here however small the buffers) and gives one thread's bits; the separate calls on two
    threads give them too."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread here")
    monkeypatch.setattr(step, "SPLIT", 0)
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
        monkeypatch.setattr(phases._Problem, "stepper", lambda self, *a, **k: None)
        _same(one, _train(dtype, True, "paper", True))
    finally:
        numba.set_num_threads(before)
