"""Compiled CPU backend (numba): the functions of `moex.kernels.reference`; a training step of all
R runs is one compiled call per thread, the sums per run after it (in the training step: in the
call, by the thread that finishes the run's last item, with the run's momentum step).

Layout. Every independent recurrence is a *lane*: an (expert, series) pair of one run in phase 1
(lane (r·S + s)·K + k: a series' K lanes side by side), a series of one run in phase 2 (lane
r·S + s), a (run, sample) trajectory of the closed loop. Lanes are the last axis of every work
array, padded to whole blocks of `simd.width` lanes (8 in float64, 16 in float32 on a CPU with
AVX-512); each lane carries its own copy of its network's weights, so a block of lanes is one
SIMD vector whichever networks its lanes belong to. A block runs its whole time loop with the
lane loop innermost; blocks are shared out among threads (`threads`). The per-lane weight gradients
are summed over the lanes of each network at the end. Phase 1 takes chunks of whole series that
fill whole blocks (one block of four series at K = 2 in float64) through the forward pass, the
mixture and BPTT in one thread, its histories in that core's cache; its mixture, which runs along
time one (run, series) at a time, reads the experts' outputs and writes ∂L/∂o as rows by lane, into
which the forward and backward stages move each block's tiles across (`simd.transpose_tile`).
The RNN passes are compiled for the sizes of the networks (`lanes.sizes`: units, inputs and
outputs as constants, the loops over them unrolled), a kernel per size unless
MOEX_CPU_SIZES=runtime.

Modules: `cache` (numba's cache keyed on every source here), `simd` (lanes, exp/log/tanh, fma),
`threads` (the kernels' thread pool), `rnn` (the leaky RNN's forward pass and BPTT over a block
of lanes, with the derivation), `lanes` (parameters to lanes and back, work arrays), `phases`
(phase 1 and phase 2: the objectives, the problem classes), `closed_loop` (the autonomous mixture
with Lyapunov tangents), `symbols` (nearest-point readout), `update` (the training loop's
momentum step), `step` (a whole training step with its arguments bound once, on the kernels'
threads), `warm` and `helper` (a first run's helper process that compiles the later kernels while
the run trains: the run's side and the process). The GPU backend (`moex.kernels.gpu`)
mirrors it module for module.
"""

from moex.kernels.cpu.cache import install

install()  # numba's cache keyed on all of this package's sources, before any kernel is decorated

from moex.kernels.cpu.closed_loop import closed_blocks, closed_loop  # noqa: E402
from moex.kernels.cpu.phases import ExpertProblem, GatingProblem, gating_items  # noqa: E402
from moex.kernels.cpu.symbols import nearest_symbols  # noqa: E402
from moex.kernels.cpu.update import adaptive_trial, apply_step, momentum_step  # noqa: E402

__all__ = ["ExpertProblem", "GatingProblem", "adaptive_trial", "apply_step", "closed_loop",
           "momentum_step", "nearest_symbols", "warm_up"]
LATER = (closed_blocks, gating_items)  # the helper's two large kernels (`warm.cached`)


def warm_up(precision: str, gating: tuple[int, int, int]) -> None:
    """A first run (an empty cache) compiles phase 2 (for the gating RNN's sizes `gating`: units,
    inputs, outputs) and the closed loop in a helper process while it trains phase 1 (`warm`)."""
    from numba import typeof

    from moex.kernels.cpu import warm
    from moex.kernels.cpu.lanes import sizes

    warm.start(precision, LATER, gating, typeof(sizes(*gating)))
