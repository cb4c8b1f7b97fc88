"""The training loop's momentum step on every backend (`momentum_step`, `apply_step`) and the
adaptive rate's trial (`adaptive_trial`): the reference's PyTorch operators give the bits, and
the compiled call (cpu) and the launch (gpu) must give the same bits, with failed runs,
non-finite gradients and objectives, a step that overflows, τ's clamp, a ratio at its threshold,
both momentum forms and both precisions. The cpu stepper's own update functions (the same
operations bound into a training step, `moex.kernels.cpu.step`) are held to the same bits."""

import numpy as np
import pytest
import torch

from moex.kernels import get_backend
from moex.kernels.cpu import update
from tests.helpers import backend_params

R, P, TAU = 6, 1500, (10, 20)  # P spans two of the gpu kernel's 1024-entry tiles


def _buffers(dtype) -> dict:
    gen = torch.Generator().manual_seed(3)
    big = torch.finfo(dtype).max

    def randn(*shape):
        return torch.randn(*shape, generator=gen, dtype=torch.float64).to(dtype)

    theta, grad, velocity = randn(R, P), randn(R, P), randn(R, P)
    theta[:, TAU[0]:TAU[1]] = 0.5 + randn(R, TAU[1] - TAU[0]).abs()  # some below 1
    theta[:, 5] = -0.0  # -0 + 0 = +0, as PyTorch adds
    grad[1, 1400] = float("nan")  # run 1: a NaN gradient
    objective = randn(R)
    objective[2] = float("inf")  # run 2: an infinite objective
    failed = torch.zeros(R, dtype=torch.bool)
    failed[3] = True  # run 3: failed before
    theta[4, 7], grad[4, 7] = big, big  # run 4: θ + Δθ overflows (at a fixed rate: rolled back)
    return dict(theta=theta, grad=grad, velocity=velocity, delta=torch.zeros(R, P, dtype=dtype),
                rate=(0.01 + torch.rand(P, generator=gen, dtype=torch.float64)).to(dtype),
                lr_scale=0.7 ** torch.arange(R, dtype=torch.float64),
                objective=objective, failed=failed)


def _same(a: dict, b: dict) -> None:
    for name in a:
        torch.testing.assert_close(b[name].cpu(), a[name], rtol=0, atol=0, equal_nan=True,
                                   msg=lambda m, name=name: f"{name}: {m}")


@pytest.mark.parametrize("backend", backend_params(reference=False), indirect=True)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("paper_form", [True, False])
@pytest.mark.parametrize("apply", [True, False])
def test_a_momentum_step_gives_the_references_bits(backend, dtype, paper_form, apply):
    want, got = _buffers(dtype), _buffers(dtype)
    got = {k: v.to(backend.device) for k, v in got.items()}
    for chosen, b in ((get_backend("reference"), want), (backend, got)):
        chosen.momentum_step(b["theta"], b["grad"], b["velocity"], b["delta"], rate=b["rate"],
                             lr_scale=b["lr_scale"], objective=b["objective"],
                             failed=b["failed"], momentum=0.9, paper_form=paper_form,
                             apply=apply, tau=TAU)
    _same(want, got)
    assert want["failed"].tolist() == [False, True, True, True, apply, False]
    assert (want["grad"][1:4] == 0).all() and want["grad"][0].ne(0).any()
    if apply:  # the step was taken: τ kept >= 1 (in every run), failed runs' θ unchanged
        assert (want["theta"][:, TAU[0]:TAU[1]] >= 1).all()
        assert torch.equal(want["theta"][4, TAU[1]:], _buffers(dtype)["theta"][4, TAU[1]:])


@pytest.mark.parametrize("backend", backend_params(reference=False), indirect=True)
@pytest.mark.parametrize("paper_form", [True, False])
def test_an_adaptive_steps_update_gives_the_references_bits(backend, paper_form):
    want, got = _buffers(torch.float64), _buffers(torch.float64)
    got = {k: v.to(backend.device) for k, v in got.items()}
    frozen = torch.tensor([False, True, False, True, False, False])
    for chosen, b in ((get_backend("reference"), want), (backend, got)):
        chosen.apply_step(b["theta"], b["grad"], b["velocity"], frozen.to(b["theta"].device),
                          paper_form=paper_form, tau=TAU)
    _same(want, got)
    assert (want["grad"][frozen] == 0).all()
    assert torch.equal(want["theta"][1, 30:], _buffers(torch.float64)["theta"][1, 30:])



@pytest.mark.parametrize("backend", backend_params(), indirect=True)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("apply", [True, False])
def test_the_paper_forms_one_buffer_gives_the_bits_of_two(backend, dtype, apply):
    """The training loop keeps the paper form's Δθ_prev in Δθ's own buffer (`moex.train`): a step
    and the adaptive rate's update with `velocity` and `delta` one tensor give what two give (Δθ
    in the one, and in both where the step was taken), on every backend."""
    two, one = _buffers(dtype), _buffers(dtype)
    one = {k: v.to(backend.device) for k, v in one.items()}
    two = {k: v.to(backend.device) for k, v in two.items()}
    one["delta"] = one.pop("velocity")  # Δθ_prev where the step reads it
    one["velocity"] = one["delta"]
    frozen = torch.tensor([False, True, False, False, True, False], device=backend.device)
    for b in (two, one):
        backend.momentum_step(b["theta"], b["grad"], b["velocity"], b["delta"], rate=b["rate"],
                              lr_scale=b["lr_scale"], objective=b["objective"],
                              failed=b["failed"], momentum=0.9, paper_form=True, apply=apply,
                              tau=TAU)
        if not apply:
            backend.apply_step(b["theta"], b["delta"], b["velocity"], frozen | b["failed"],
                               paper_form=True, tau=TAU)
    assert one["velocity"] is one["delta"]
    _same({k: two[k] for k in ("theta", "grad", "delta", "velocity", "failed")},
          {k: one[k] for k in ("theta", "grad", "delta", "velocity", "failed")})


def _trial(dtype) -> dict:
    """Runs: 0 accepts (r < 1: its rate grows), 1 accepts at r = r_th exactly (in the values'
    type), 2 rejects, 3 a NaN candidate (rejects), 4 not pending, 5 rejects with r = inf."""
    gen = torch.Generator().manual_seed(5)
    base = torch.tensor([2.0, 1.0, 1.0, 1.0, 1.0, 1.0], dtype=torch.float64).to(dtype)
    values = torch.tensor([1.0, 1.1, 1.3, float("nan"), 9.0, float("inf")],
                          dtype=torch.float64).to(dtype)
    delta = torch.randn(R, P, generator=gen, dtype=torch.float64).to(dtype)
    delta[2, 3] = -0.0
    return dict(delta=delta, values=values, base=base,
                pending=torch.tensor([True, True, True, True, False, True]),
                lr_scale=0.9 ** torch.arange(R, dtype=torch.float64),
                retries=torch.arange(R, dtype=torch.int64))


@pytest.mark.parametrize("backend", backend_params(reference=False), indirect=True)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_an_adaptive_trial_gives_the_references_bits(backend, dtype):
    want, got = _trial(dtype), _trial(dtype)
    got = {k: v.to(backend.device) for k, v in got.items()}
    left = [chosen.adaptive_trial(b["delta"], b["values"], b["base"], b["pending"],
                                  b["lr_scale"], retries=b["retries"], decrease=0.7,
                                  increase=1.05, max_ratio=1.1)
            for chosen, b in ((get_backend("reference"), want), (backend, got))]
    _same(want, got)
    assert left == [True, True]
    assert want["pending"].tolist() == [False, False, True, True, False, True]
    assert want["retries"].tolist() == [0, 1, 3, 4, 4, 6]
    start = 0.9 ** torch.arange(R, dtype=torch.float64)
    assert want["lr_scale"].tolist() == [start[0] * 1.05, start[1], start[2] * 0.7,
                                         start[3] * 0.7, start[4], start[5] * 0.7]
    assert torch.equal(want["delta"][:2], _trial(dtype)["delta"][:2])  # accepted: unchanged
    assert want["delta"][2, 3].item() == 0.0 and torch.signbit(want["delta"][2, 3])
    every = _trial(dtype)
    every["pending"][:] = False
    assert not get_backend("reference").adaptive_trial(
        every["delta"], every["values"], every["base"], every["pending"], every["lr_scale"],
        retries=every["retries"], decrease=0.7, increase=1.05, max_ratio=1.1)


def _as(dtype) -> dict:
    """numpy scalar type and unsigned integer type (the bits) of a torch dtype."""
    kind = torch.empty(0, dtype=dtype).numpy().dtype
    return {"float": kind.type, "bits": np.dtype(f"u{kind.itemsize}")}


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_steppers_trial_judges_as_the_separate_call_and_writes_the_next_point(dtype):
    """cpu stepper (`update.after_trial`): a trial judged as `adaptive_trial` judges it, each run
    still pending with its next trial's point θ + Δθ in scratch (PyTorch's sum, bit for bit),
    every other row of scratch untouched."""
    want, got = _trial(dtype), _trial(dtype)
    get_backend("reference").adaptive_trial(want["delta"], want["values"], want["base"],
                                            want["pending"], want["lr_scale"],
                                            retries=want["retries"], decrease=0.7,
                                            increase=1.05, max_ratio=1.1)
    theta = _buffers(dtype)["theta"]
    scratch = torch.full_like(theta, 7.0)
    kind = _as(dtype)
    now = (np.zeros((R, 1), kind["bits"]),)
    update.after_trial(0, R, now, np.zeros(R, bool), np.zeros((1, 2), np.int64),
                       np.zeros(R, np.int64), np.zeros(R, np.int64), False, theta.numpy(),
                       got["delta"].numpy(), scratch.numpy(), got["values"].numpy(),
                       got["base"].numpy(), got["pending"].numpy(), got["lr_scale"].numpy(),
                       got["retries"].numpy(), 0.7, kind["float"](0.7), 1.05, kind["float"](1.1))
    _same(want, got)
    pending = want["pending"]
    assert pending.tolist() == [False, False, True, True, False, True]
    _same({"next": torch.add(theta, want["delta"])[pending]}, {"next": scratch[pending]})
    assert (scratch[~pending] == 7).all()


@pytest.mark.parametrize("paper_form", [True, False])
def test_the_steppers_last_update_freezes_the_runs_pending_or_failed(paper_form):
    """cpu stepper (`update.after_trials`): the step `apply_step` takes with frozen = pending |
    failed, bit for bit."""
    want, got = _buffers(torch.float64), _buffers(torch.float64)
    pending = torch.tensor([False, True, False, False, False, True])
    get_backend("reference").apply_step(want["theta"], want["grad"], want["velocity"],
                                        pending | want["failed"], paper_form=paper_form, tau=TAU)
    update.after_trials(0, R, got["theta"].numpy(), got["grad"].numpy(), got["velocity"].numpy(),
                        pending.numpy(), got["failed"].numpy(), np.zeros(R, bool), paper_form,
                        *TAU)
    _same(want, got)
    assert (want["grad"][[1, 3, 5]] == 0).all() and want["grad"][0].ne(0).any()


def test_the_steppers_first_update_runs_forward_only_the_runs_without_a_current_pass():
    """cpu stepper (`update.before_gradient`): active = not failed; stale (run forward) = the
    active runs whose lanes do not hold the pass at θ (not `current`)."""
    failed = np.array([False, True, False, False])
    current = np.array([True, True, False, False])  # run 1 failed, runs 2 and 3 hold nothing
    active, stale = np.ones(4, bool), np.ones(4, bool)
    update.before_gradient(0, 4, current, failed, active, stale)
    assert active.tolist() == [True, False, True, True]
    assert stale.tolist() == [False, False, True, True]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_after_the_trials_a_run_stays_current_only_where_theta_is_its_trial_point(dtype):
    """`update.after_trials`: a run that took its step is at its accepted trial's point θ + Δθ
    (the record, `scratch`) bit for bit and stays current; one that τ's clamp moved, one still
    rejected or failed (frozen), or one not current before, is not current after."""
    rng = np.random.default_rng(0)
    R, P, tau = 6, 40, (30, 34)
    theta, delta = (rng.normal(size=(R, P)).astype(dtype) for _ in range(2))
    theta[:, tau[0]:tau[1]] = 3.0
    delta[:, tau[0]:tau[1]] = 0.5
    delta[2, tau[0] + 1] = -2.5  # run 2's τ falls below 1: clamped
    scratch = theta + delta  # the trials' point (`_trial_point`'s addition)
    pending = np.array([False, False, False, True, False, False])
    failed = np.array([False, False, False, False, True, False])
    current = np.array([True, True, True, True, True, False])
    update.after_trials(0, R, theta, delta, None, pending, failed, current, True, *tau)
    assert current.tolist() == [True, True, False, False, False, False]
    same = (theta.view(f"u{theta.itemsize}") == scratch.view(f"u{theta.itemsize}")).all(1)
    assert same[:2].all() and not same[2:5].any()
    assert (theta[:, tau[0]:tau[1]] >= 1).all()


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_vectorised_checks_agree_with_numpy_wherever_the_odd_entry_sits(dtype):
    """`update._finite` (every entry checked, ANDed) and `lanes._equal` (every XOR ORed) find a
    non-finite entry, or one bit changed, at the first, a middle and the last place of a row."""
    from moex.kernels.cpu.lanes import _equal

    rng = np.random.default_rng(0)
    row = rng.standard_normal(1037).astype(dtype)
    assert update._finite(row)
    for place in (0, 517, 1036):
        for odd in (np.inf, -np.inf, np.nan):
            bad = row.copy()
            bad[place] = odd
            assert not update._finite(bad)
    bits = np.dtype(f"u{np.dtype(dtype).itemsize}")
    then = np.stack([row, -row]).view(bits)
    assert _equal((then.copy(),), (then,), 0) and _equal((then.copy(),), (then,), 1)
    for place in (0, 517, 1036):
        for flip in (1, 1 << (8 * bits.itemsize - 1)):  # the lowest bit; the sign (-0.0 vs 0.0)
            now = then.copy()
            now[1, place] ^= bits.type(flip)
            assert _equal((now,), (then,), 0) and not _equal((now,), (then,), 1)
