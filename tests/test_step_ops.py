"""What one steady-state training step costs the host on the gpu backend: PyTorch operators and
host-device synchronisations, counted on the CPU with the Triton launches stubbed out (the
kernels' own work is not what is counted). A synchronisation is `aten::_local_scalar_dense`
(`.item()`, `bool(tensor)`), `nonzero`, or indexing with a boolean mask (nonzero on CUDA).

Design numbers: a fixed-rate step is 5 Triton launches (forward, objective, the backward
recurrence, the weight gradients' sums, the momentum step) and no synchronisation; the adaptive
rate adds one call per k candidate steps (2 launches: forward and objective of k·R networks) and
one synchronisation per call (the flag "did any run reject all k"), and its update is a launch of
its own. Operator ceilings are today's
counts plus a little, so that a change adding host work fails here."""

from collections import Counter

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode, _disable_current_modes

from moex.config.model import ModelConfig
from moex.config.train import ExpertPhaseConfig, GatingPhaseConfig, TrainConfig
from moex.kernels import available
from moex.model import init_experts, init_gating
from moex.tasks import make_task, task_config
from moex.train import train_experts, train_gating
from tests.helpers import generators

SYNCS = ("_local_scalar_dense", "nonzero", "boolean mask")


class _Count(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.ops = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        self.ops[name] += 1
        if name in ("index", "index_put", "index_put_") and any(
                i is not None and i.dtype == torch.bool for i in args[1]):
            self.ops["boolean mask"] += 1
        return func(*args, **(kwargs or {}))


def _train(phase: int, steps: int, adaptive: bool, backend) -> Counter:
    task = make_task(task_config("lissajous2", num_series=2, length=30), seed=0)
    series = torch.as_tensor(task.series)
    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 4, 5
    ghat = torch.softmax(torch.randn(2, 2, 29, 2, generator=torch.Generator().manual_seed(0),
                                     dtype=torch.float64), -1)
    with _Count() as count:
        if phase == 1:
            train_experts(init_experts(model, 2, 2, generators([1, 2])), series, model,
                          ExpertPhaseConfig(steps=steps, adaptive_lr=adaptive, log_every=1000),
                          TrainConfig(), backend=backend)
        else:
            train_gating(init_gating(model, 2, 2, generators([1, 2])), ghat, series[:, :-1], model,
                         GatingPhaseConfig(steps=steps, adaptive_lr=adaptive, log_every=1000),
                         rule=TrainConfig(), backend=backend)
    return count.ops


@pytest.mark.parametrize("phase, adaptive, max_ops, max_syncs, max_launches", [
    (1, False, 5, 0, 5), (1, True, 65, 1, 8), (2, False, 5, 0, 5), (2, True, 65, 1, 8)])
def test_a_steady_state_gpu_step_stays_within_its_host_budget(monkeypatch, phase, adaptive,
                                                              max_ops, max_syncs, max_launches):
    """One step = the counts of a 22-step training minus a 21-step one (the same logging and
    checkpoint steps in both: progress lines at steps 2, 4, ..., 20, the last step's line being
    the final one); with stubbed kernels every candidate step is accepted, so the adaptive
    rate's k candidates are one call (2 launches) and one flag read."""
    gpu, why = available("gpu")
    if gpu is None:
        pytest.skip(f"backend gpu cannot run here: {why}")
    from moex.kernels.gpu import lanes, phases, update

    def launch(kernel, programs, *args, STATS=None, **meta):
        """No kernel; an objective kernel's statistics are 1 (outside the count)."""
        launches[0] += 1
        if STATS is not None:
            with _disable_current_modes():
                STATS.fill_(1.0)

    for module in (lanes, phases, update):  # every training launch goes through `launch`
        monkeypatch.setattr(module, "launch", launch)
    monkeypatch.setattr(phases._Problem, "trials", 4)  # several candidates per call (default 1)
    launches = [0]
    short = _train(phase, 21, adaptive, gpu)
    before = launches[0]
    long = _train(phase, 22, adaptive, gpu)
    step = {k: long[k] - short[k] for k in long if long[k] != short[k]}
    syncs = sum(step.get(k, 0) for k in SYNCS)
    ops = sum(v for k, v in step.items() if k != "boolean mask")
    assert syncs == max_syncs, step
    assert 0 < ops <= max_ops, step
    assert launches[0] - 2 * before == max_launches
