"""A whole training step of all R runs with its arguments bound once: the gradient at θ, the
momentum step Δθ (Eqs. 17-18), the adaptive rate's trials at θ + Δθ and their judgement
(Sec. 2.1.4), and the step taken.

The training loop (`moex.train._ascend`) otherwise makes each of those a backend call that converts
its tensors, stages the parameters, checks the lanes' record of their forward pass and wraps the
statistics: 160-390 µs of Python per step at R = 1, 6-11 % of an epoch. A `Stepper` binds every
array once (the parameters' views of the flat (R, P) buffers where the kernels can read them as they
are, at R = 1 all of them, and the buffers themselves for the groups the kernel takes as rows: phase
1's β, read and written in place at any R) and makes a step of a few compiled calls with nothing
between them but the calls: the phase kernel per evaluation (`evaluate`) and the update functions
around it (`update.before_gradient`: the runs to compute; `after_gradient`: Δθ and the first trial's
point θ + Δθ; `after_trial`: the trial judged and the next trial's point; `after_trials`: the step
taken, and whose lanes still hold θ's forward pass), on whole rows of the flat buffer. Those run
without fast-math flags (said outright: a function called from the fast-math phase kernel would
inherit its flags), which would let LLVM drop their NaN and infinity checks, which decide whether
a run failed. The statistics stay in an array until the loop reads them
(`statistics`, where it logs). Each NumPy or PyTorch operation between the calls had cost 5-60 µs
there (line_profiler), 10-50 times its time in a loop of its own (timeit): after a kernel that has
filled the caches with its lanes, the interpreter's code and data come back from memory (the likely
cause; not measured with counters on this VM). Host time per step at R = 1 is now 30-70 µs
(`benchmarks/bench_host.py`: 2.5-3.2 % of an epoch).

A gradient step right after an accepted adaptive trial is at the trial's point: it takes the
trial's forward pass, objective and ∂/∂o from the lanes (the trial computes ∂/∂o for it; phase
1's mixture is a quarter of a step) and runs only BPTT and the sums.

The phase kernels make each run's sums in every call, and `after_gradient` in the gradient's
call, run by run: the thread that finishes a run's last chunk of series (phase 1) or block of
lanes (phase 2) makes them (the kernels' `left`), so that no pass over the (R, P) buffers and no
run sums on the calling thread follow the call, and a run is finished while the other thread still
computes. On two threads at R = 30 a phase-1 step had spent 0.9-1.4 ms in the sums and in
`after_gradient`'s passes over the buffers, which are bound by memory bandwidth and gained little
from a second thread (BENCHMARKS.md).

On more than one thread the evaluation's chunks of series or blocks are shared out as in the
separate calls (`threads.share`), and so are the update's other stages' runs, with the staging
copies of their rows, where the (R, P) buffers (or the copies) hold at least `threads.SPLIT` entries
(phase 1's buffers at R = 30: nothing of their size is left to one thread); smaller ones are one
call, cheaper than a handoff, and so is each trial's judgement (`after_trial`: flags per run, and
the next point of the runs still pending). Those calls go to the stepper's crew (`threads.Crew`:
the other threads wait between them in compiled code, without the GIL) where its loop is compiled
or cached, and a phase of `LONG` seconds or more compiles it at its second step; otherwise through
the threads' pool.

The record of the lanes' forward pass (with `reuse`) is θ + Δθ's own buffer: a run is current
while its lanes hold the forward pass of its row of `scratch`, which nothing rewrites while it is
(`after_gradient` clears every run before it writes the trial points, `after_trial` each run
whose next point it writes, a separate call or fresh input noise all of them). `after_trials`
then keeps a run current only where its step was taken and τ's clamp moved nothing: θ is then
that row bit for bit (θ + Δθ, the same addition), so nothing is copied after a trial and nothing
compared before the next gradient (the comparison was a pass over two (R, P) buffers, 0.3 ms a
step at 30 networks).

A step gives the bits of the separate calls, on any number of threads: the same compiled
functions on the same numbers in the same order (tests/test_step.py trains both ways).
"""

import logging
import time
from functools import partial

import numpy as np
import torch

from moex.kernels.cpu import threads
from moex.kernels.cpu.lanes import first_use, to_host
from moex.kernels.cpu.update import (
    after_trial,
    after_trials,
    before_gradient,
    momentum_buffer,
)

logger = logging.getLogger("moex.kernels.cpu")
LONG = 300.0  # seconds of a phase's steps from which its stepper compiles the crew's loop: it
# saves 1-2.7 % of a step at 30 networks on two threads and costs 3-4 s of compile once


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
            max_ratio (the rule), tau (τ's columns or None), steps (the steps the training
            loop will take: whether to compile the crew's loop).
    """

    def __init__(self, problem, buffers: dict, columns: dict, fixed: dict, *, rate, lr_scale,
                 failed, retries, criterion: str, momentum: float, paper_form: bool,
                 adaptive: bool, max_retries: int, decrease: float, increase: float,
                 max_ratio: float, tau, steps: int = 0):
        self.problem, lanes = problem, problem.lanes
        theta, grad, velocity, delta, scratch = (to_host(buffers[k]) for k in (
            "theta", "grad", "velocity", "delta", "scratch"))
        R, dtype = theta.shape[0], theta.dtype
        shapes = {k: problem.staging.params[k].shape for k in columns}

        def views(flat):
            return {k: flat[:, a:b].reshape(shapes[k]) for k, (a, b) in columns.items()}

        fixed = {k: to_host(v) for k, v in fixed.items()}
        # the arrays the kernel reads (views of the buffers where it can take them as they are,
        # the buffers themselves for the groups it takes as rows) and the copies each
        # evaluation needs into the others
        rows = [k for k in problem.ROWS if k in columns]
        staged, copies = [], []  # at θ (the gradient), at θ + Δθ (a trial)
        for flat in (theta, scratch):
            source = {k: v for k, v in {**views(flat), **fixed}.items() if k not in rows}
            staged.append({**problem.staging.load(source),
                           **{k: (flat, columns[k][0]) for k in rows}})
            copies.append([(source[k], staged[-1][k]) for k in columns
                           if k not in rows and not np.shares_memory(staged[-1][k], flat)])
        grads = {k: v for k, v in views(grad).items() if k not in rows}
        written = {**problem.staging.outputs(grads), **{k: (grad, columns[k][0]) for k in rows}}
        # the gradients the kernel writes into staging arrays (groups whose views of `grad` are
        # strided, R > 1), which `after_gradient` copies into `grad`
        sources = [(written[k].reshape(R, -1), columns[k][0]) for k in grads
                   if written[k] is not grads[k]]
        active, stale, pending = np.zeros((3, R), bool)
        forwarded = problem.forwarded
        # with the record, a gradient step after an accepted trial reuses the trial's forward
        # pass, objective and ∂/∂o (the trial computes them); the record compares the columns
        # that all of those read (phase 1's β among them: most of a row)
        reuse = forwarded.enabled
        read = [columns[k] for k in (*forwarded.names, *problem.AFTER_FORWARD) if k in columns]
        a, b = min(a for a, _ in read), max(b for _, b in read)
        bits = np.dtype(f"u{dtype.itemsize}")
        # the record: a current run's lanes hold the forward pass of its row of θ + Δθ's bits,
        # `scratch` itself (`after_trial` clears `current` where it writes a row; `after_gradient`
        # for every run), which θ equals after `after_trials` where it keeps the run current
        trial_bits, current = (scratch[:, a:b].view(bits),), np.zeros(R, bool)
        self.current, self.pending = current, pending
        self.stats = np.zeros((len(problem.STATS), R), dtype)
        rate, lr_scale, failed, retries = (to_host(x) for x in (rate, lr_scale, failed, retries))
        rule = (dtype.type(momentum), bool(paper_form), bool(adaptive), int(max_retries),
                *(tau or (0, 0)))
        velocity = momentum_buffer(velocity, delta, paper_form)
        c = problem.STATS.index(criterion)
        # each stage's compiled function and its arguments after (lo, hi), bound once
        self.before = (before_gradient, R, current, failed, active, stale)
        update = _update(problem, sources, stats=self.stats, current=current, theta=theta,
                         grad=grad, velocity=velocity, delta=delta, scratch=scratch, rate=rate,
                         lr_scale=lr_scale, failed=failed, pending=pending, retries=retries,
                         rule=rule)
        self.trial = (after_trial, R, trial_bits, current,
                      lanes.block_runs, forwarded.first_block, forwarded.last_block,
                      reuse, theta, delta, scratch, lanes.out[c], self.stats[c], pending,
                      lr_scale, retries, float(decrease), dtype.type(decrease), float(increase),
                      dtype.type(max_ratio))
        self.finish = (after_trials, R, theta, delta, velocity, pending, failed, current,
                       rule[1], *rule[4:])
        # each evaluation's staging copies and the phase kernel's arguments: the gradient at θ
        # (the runs `stale` run forward), a trial at θ + Δθ (the `pending` runs). The kernels
        # make each run's sums, and in the gradient's call `after_gradient`, inside the call, in
        # the thread that finishes the run's last chunk or block (`left`: each run's still to go)
        finishing = partial(problem.kernel_args, reuse=reuse,
                            finish=(np.zeros(R, np.int64), update))
        # the calls without a stepper (the separate calls) take arguments of the same types, so
        # that one compiled kernel serves all (`left` empty: nothing of the update is read)
        problem.idle = (np.zeros(0, np.int64), update)
        evaluations = (finishing(staged[0], written, True, active, stale),
                       finishing(staged[1], written, False, pending, pending))
        # the calls over the threads, bound to the step's crew (`threads.Crew`): the phase
        # kernel's at θ and at θ + Δθ, and the step taken
        calls = [(kernel, rest) for kernel, _, _, *rest in map(problem.shared, evaluations)]
        self.crew = threads.Crew(calls + [(after_trials, self.finish[2:])] * bool(adaptive))
        self.evaluations = {
            want_grad: (copies[i], threads.by_size(_entries(copies[i])), evaluations[i],
                        partial(self.crew.share, i))
            for i, want_grad in enumerate((True, False))}
        self.steps, self.made = steps, 0  # the steps the training loop takes, and made
        self.trials = max_retries if adaptive else 0
        self.adaptive = adaptive
        # the update's stages shared out only where a pass over the buffers outlasts a handoff
        self.over = threads.by_size(theta.size) is threads.over
        self.runs = R

    def _evaluate(self, want_grad: bool) -> None:
        copies, over, args, share = self.evaluations[want_grad]
        if copies:  # (the point itself written by the update before: θ, or θ + Δθ)
            over(_rows, self.runs, copies)
        self.problem.evaluate(args, share)

    def __call__(self) -> None:
        """One training step of every run; its statistics at θ in `statistics()` until the
        next. The second step (the first with the kernels compiled) is timed: where the steps
        left would take `LONG` seconds or more on more than one thread, the crew's loop is
        compiled then (`threads.Crew`: 3-4 s once, then loaded from the cache)."""
        self.made += 1
        if self.made != 2:
            self._step()
            return
        start = time.perf_counter()
        self._step()
        left = (time.perf_counter() - start) * (self.steps - self.made)
        if left >= LONG and threads.count() > 1 and not self.crew.ready:
            logger.info("compiling the loop of the kernels' threads for the %.0f s left of this "
                        "phase (a few seconds, once: then loaded from the cache)", left)
            self.crew.compile()

    def _step(self) -> None:
        threads.one(*self.before)  # (two flags per run: less than a handoff)
        with first_use(*self.problem.KERNEL):
            self._evaluate(True)
        for _ in range(self.trials):
            self._evaluate(False)
            # (the trial judged, flags per run, and the next point of the runs still pending:
            # rarely more than a few rows, less than a handoff)
            threads.one(*self.trial)
            if not np.count_nonzero(self.pending):
                break
        if self.adaptive:  # the step taken, runs still rejected frozen
            if self.over:
                self.crew.over(2, self.runs)
            else:
                threads.one(*self.finish)

    def statistics(self) -> dict[str, torch.Tensor]:
        """The last step's statistics at θ (before its update), (R,) each: read only where the
        loop logs them, as converting them every step took 20-50 µs at R = 1 (a cold path after
        the kernel, 2-3 % of an epoch)."""
        values = torch.from_numpy(self.stats.copy())
        return {name: values[i] for i, name in enumerate(self.problem.STATS)}


def _entries(copies: list) -> int:
    return sum(source.size for source, _ in copies)


def _rows(lo: int, hi: int, copies: list) -> None:
    """Rows lo..hi-1 (runs) of each (source, destination) of `copies` (numpy lets go of the GIL
    while it copies)."""
    for source, destination in copies:
        np.copyto(destination[lo:hi], source[lo:hi])


def _update(problem, sources: list, *, stats, current, theta, grad, velocity, delta, scratch,
            rate, lr_scale, failed, pending, retries, rule: tuple) -> tuple:
    """`update.after_gradient`'s arguments after (lo, hi), `sources` ((R, n) array, first
    column of `grad`) padded with empty ones to one per staged group of `problem`: the same
    types whichever groups are learned, so that the phase kernel that calls it compiles once."""
    R, dtype = theta.shape[0], theta.dtype
    sources = sources + [(np.zeros((R, 0), dtype), 0)] * (len(problem.staging.grads)
                                                          - len(sources))
    return (tuple(a for a, _ in sources), np.array([c for _, c in sources], np.int64), stats,
            problem.lanes.out, current, theta, grad, velocity, delta, scratch, rate, lr_scale,
            failed, pending, retries, *rule)


def idle(problem) -> tuple:
    """A phase kernel's `finish` for its calls before any stepper: no run's update (`left`
    empty: nothing of it is read), in arguments of the types a paper-form stepper binds
    (`_update`'s, velocity None), so that one compiled kernel serves both."""
    out = problem.lanes.out
    R, dtype = out.shape[1], out.dtype
    rows, flags = np.zeros((R, 0), dtype), np.zeros(R, bool)
    return np.zeros(0, np.int64), _update(
        problem, [], stats=np.zeros_like(out), current=flags, theta=rows, grad=rows,
        velocity=None, delta=rows, scratch=rows, rate=np.zeros(0, dtype), lr_scale=np.zeros(R),
        failed=flags, pending=flags, retries=np.zeros(R, np.int64),
        rule=(dtype.type(0), True, True, 0, 0, 0))

