"""A whole training step of all R runs on one thread with its arguments bound once: the gradient
at θ, the momentum step Δθ (Eqs. 17-18), the adaptive rate's trials at θ + Δθ and their
judgement (Sec. 2.1.4), and the step taken.

The training loop (`moex.train._ascend`) otherwise makes each of those a backend call that
converts its tensors, stages the parameters, checks the lanes' record of their forward pass and
wraps the statistics: 160-390 µs of Python per step at R = 1, 6-11 % of an epoch. A `Stepper`
binds every array once (the parameters' views of the flat (R, P) buffers where the kernels can
read them as they are, at R = 1 all of them) and makes a step of 2 + 3 compiled calls per trial:
the phase kernel per evaluation, the update functions between (`update.after_gradient`,
`after_trial`, `apply_runs`, and the lanes' record of their forward pass, `lanes.stale_runs`, on
whole rows of the flat buffer). Those run without fast-math flags: inside the fast-math phase
kernel (one call per step) LLVM may drop their NaN and infinity checks, which decide whether a run
failed.

A step gives the bits of the separate calls: the same compiled functions on the same numbers in
the same order (tests/test_step.py trains both ways).
"""

import numpy as np
import torch

from moex.kernels.cpu.lanes import first_use, stale_runs, to_host
from moex.kernels.cpu.update import after_gradient, after_trial, apply_runs


class Stepper:
    """A problem's whole training step on the training loop's buffers
    (`moex.kernels.Problem.stepper`); calling it returns the statistics at θ (before the step).

    Args:
        problem: the cpu problem (its staging, lanes, record of the forward pass, STATS,
            `kernel_args` and `evaluate`).
        buffers: the loop's (R, P) tensors theta, grad, velocity, delta, scratch (θ + Δθ).
        columns: {group: (first, last) column} of the flat buffer; fixed: the groups not
            learned; rate (P,), lr_scale (R,) float64, failed (R,) bool, retries (R,) int64:
            the loop's tensors, updated in place.
        settings: criterion, momentum, paper_form, adaptive, max_retries, decrease, increase,
            max_ratio (the rule), tau (τ's columns or None).
    """

    def __init__(self, problem, buffers: dict, columns: dict, fixed: dict, *, rate, lr_scale,
                 failed, retries, criterion: str, momentum: float, paper_form: bool,
                 adaptive: bool, max_retries: int, decrease: float, increase: float,
                 max_ratio: float, tau):
        self.problem, lanes = problem, problem.lanes
        theta, grad, velocity, delta, scratch = (to_host(buffers[k]) for k in (
            "theta", "grad", "velocity", "delta", "scratch"))
        R, dtype = theta.shape[0], theta.dtype
        shapes = {k: problem.staging.params[k].shape for k in columns}

        def views(flat):
            return {k: flat[:, a:b].reshape(shapes[k]) for k, (a, b) in columns.items()}

        fixed = {k: to_host(v) for k, v in fixed.items()}
        # the arrays the kernel reads (views of the buffers where it can take them as they are)
        # and the copies each evaluation needs into the others
        self.point = {}
        for name, flat in (("theta", theta), ("scratch", scratch)):
            source = {**views(flat), **fixed}
            staged = problem.staging.load(source)
            self.point[name] = (staged, [(source[k], staged[k]) for k in columns
                                         if not np.shares_memory(staged[k], flat)])
        grads = views(grad)
        written = problem.staging.outputs(grads)
        self.copy_out = [(written[k], grads[k]) for k in columns if written[k] is not grads[k]]
        self.masks = np.zeros((4, R), bool)  # active, stale, pending, frozen
        active, stale, pending, _ = self.masks
        kernel_args = problem.kernel_args
        self.args = {True: kernel_args(self.point["theta"][0], written, True, active, stale),
                     False: kernel_args(self.point["scratch"][0], written, False, pending,
                                        pending)}
        bits = np.dtype(f"u{dtype.itemsize}")
        self.bits = (theta.view(bits),), (scratch.view(bits),)
        self.then, self.current = (np.zeros(theta.shape, bits),), np.zeros(R, bool)
        self.stats = np.zeros((len(problem.STATS), R), dtype)
        self.flat = theta, grad, velocity, delta, scratch
        self.loop = (to_host(rate), to_host(lr_scale), to_host(failed), to_host(retries))
        self.rule = (dtype.type(momentum), bool(paper_form), bool(adaptive), int(max_retries),
                     *(tau or (0, 0)))
        self.trial = (float(decrease), dtype.type(decrease), float(increase),
                      dtype.type(max_ratio))
        forwarded = problem.forwarded
        self.record = (lanes.block_runs, forwarded.first_block, forwarded.last_block,
                       forwarded.enabled)
        self.criterion = problem.STATS.index(criterion)

    def _evaluate(self, point: str, want_grad: bool) -> None:
        for source, staged in self.point[point][1]:
            np.copyto(staged, source)
        self.problem.evaluate(self.args[want_grad])

    def __call__(self) -> dict[str, torch.Tensor]:
        theta, grad, velocity, delta, scratch = self.flat
        rate, lr_scale, failed, retries = self.loop
        active, stale, pending, frozen = self.masks
        block_runs, first_block, last_block, reuse = self.record
        out = self.problem.lanes.out
        np.logical_not(failed, out=active)
        if reuse:
            stale_runs(self.bits[0], self.then, self.current, active, stale)
        else:
            stale[:] = active
        with first_use(*self.problem.KERNEL):
            self._evaluate("theta", True)
        for written, grads in self.copy_out:
            np.copyto(grads, written)
        trials = after_gradient(self.stats, out, self.current, theta, grad, velocity, delta,
                                rate, lr_scale, failed, pending, retries, *self.rule)
        c = self.criterion
        for _ in range(self.rule[3] if trials else 0):
            np.add(theta, delta, out=scratch)  # (the separate calls' torch.add: the same bits)
            self._evaluate("scratch", False)
            if not after_trial(self.bits[1], self.then, self.current, block_runs, first_block,
                               last_block, reuse, delta, out[c], self.stats[c], pending,
                               lr_scale, retries, *self.trial):
                break
        _, paper_form, adaptive, _, tau_start, tau_end = self.rule
        if adaptive:  # the step taken, runs still rejected frozen
            np.logical_or(pending, failed, out=frozen)
            apply_runs(0, len(failed), theta, delta, velocity, frozen, paper_form, tau_start,
                       tau_end)
        values = torch.from_numpy(self.stats.copy())
        return {name: values[i] for i, name in enumerate(self.problem.STATS)}
