"""Parameters to lanes and back, and the work arrays of a phase (layout: `moex.kernels.cpu`).

Lane l is entry l % LB of block l // LB (LB = `simd.width` of the run's dtype). A run's lanes are
contiguous, series by series: lane (r·S + s)·K' + k is series s of run r for network k of the K'
the run has (its K experts in phase 1, its gating RNN in phase 2: lane r·S + s), so that a
series' K' lanes sit side by side and whole blocks hold whole series. Lanes past the last run are
padding: zero weights, no data.
"""

import contextlib
import logging
import os
import time

import numpy as np
import torch
from numba import njit

from moex.errors import check
from moex.kernels.cpu.simd import JIT, padded, width, zeros


@njit(inline="always", **JIT)
def spread(lane, S, params, u0, net):  # pragma: no cover
    """Copy the weights of the network that owns `lane` into it (zeros for padding lanes).
    Network parameters are (R, K', ...) with K' experts per run (1 for the gating RNN); u0 is
    (R, S, K', H)."""
    w_in, w_rec, w_out, b_c, b_o, tau = params
    lane_w_in, lane_w_rec, lane_w_out, lane_b_c, lane_b_o, eps, u0_lane = net
    R, KK, LB = w_in.shape[0], w_in.shape[1], width(lane_b_c)
    b, v = lane // LB, lane % LB
    q, k = lane // KK, lane % KK  # q = r·S + s
    r, s = min(q // S, R - 1), q % S
    real = q < R * S
    H, NI, NO = w_rec.shape[2], w_in.shape[3], w_out.shape[2]
    for i in range(H):
        lane_b_c[b, i, v] = b_c[r, k, i] if real else 0.0
        eps[b, i, v] = 1.0 / tau[r, k, i] if real else 1.0
        u0_lane[b, i, v] = u0[r, s, k, i] if real else 0.0
        for d in range(NI):
            lane_w_in[b, i, d, v] = w_in[r, k, i, d] if real else 0.0
        for j in range(H):
            lane_w_rec[b, i, j, v] = w_rec[r, k, i, j] if real else 0.0
    for o in range(NO):
        lane_b_o[b, o, v] = b_o[r, k, o] if real else 0.0
        for i in range(H):
            lane_w_out[b, o, i, v] = w_out[r, k, o, i] if real else 0.0


@njit(inline="always", **JIT)
def lane_sum(x, lo, hi, step=1):  # pragma: no cover
    """Σ over lanes lo, lo + step, .. below hi of x (NB, LB), in that order."""
    total, LB = 0.0, width(x)
    for lane in range(lo, hi, step):
        total += x[lane // LB, lane % LB]
    return total


@njit(inline="always", **JIT)
def gather(g, S, tau, lane_grads, grads, learn_eps):  # pragma: no cover
    """Sum the per-lane gradients of network g's S lanes (series 0..S-1 in turn) into its
    parameter gradients (∂/∂τ = -ε² ∂/∂ε); layouts as in `spread`."""
    l_w_in, l_w_rec, l_w_out, l_b_c, l_b_o, l_eps = lane_grads
    g_w_in, g_w_rec, g_w_out, g_b_c, g_b_o, g_tau = grads
    KK = g_w_in.shape[1]
    r, k = g // KK, g % KK
    H, NI, NO = g_w_rec.shape[2], g_w_in.shape[3], g_w_out.shape[2]
    lo, hi = r * S * KK + k, (r + 1) * S * KK  # its lanes, every KK-th
    for i in range(H):
        g_b_c[r, k, i] = lane_sum(l_b_c[:, i], lo, hi, KK)
        if learn_eps:
            g_tau[r, k, i] = -lane_sum(l_eps[:, i], lo, hi, KK) / (tau[r, k, i] * tau[r, k, i])
        for d in range(NI):
            g_w_in[r, k, i, d] = lane_sum(l_w_in[:, i, d], lo, hi, KK)
        for j in range(H):
            g_w_rec[r, k, i, j] = lane_sum(l_w_rec[:, i, j], lo, hi, KK)
    for o in range(NO):
        g_b_o[r, k, o] = lane_sum(l_b_o[:, o], lo, hi, KK)
        for i in range(H):
            g_w_out[r, k, o, i] = lane_sum(l_w_out[:, o, i], lo, hi, KK)


@njit(inline="always", **JIT)
def run_lanes(r, S, T, u0_lane, S1, S2, floor, attraction, want_grad, l_u0,
              g_u0):  # pragma: no cover
    """After the backward pass, for the lanes of run r: the C code's attraction of u_0 to the
    mean μ of its own trajectory {u_0..u_T} (not in the paper; value returned, gradient
    (μ - u_0)/max(var, floor) added) and the u_0 gradients copied out to g_u0 (R, S, K', H)."""
    value, LB = 0.0, width(u0_lane)
    KK = g_u0.shape[2]
    for n in range(KK * S):  # network by network, series by series
        k, s = n // S, n % S
        lane = (r * S + s) * KK + k
        b, v = lane // LB, lane % LB
        for i in range(u0_lane.shape[1]):
            if attraction:
                mean = S1[b, i, v] / (T + 1)
                var = max(S2[b, i, v] / (T + 1) - mean * mean, floor)
                diff = u0_lane[b, i, v] - mean
                value -= diff * diff / (2.0 * var)
                l_u0[b, i, v] -= diff / var
            if want_grad:
                g_u0[r, s, k, i] = l_u0[b, i, v]
    return value


def runs_of_blocks(num_blocks, lanes_per_run, num_runs, LB):
    """(NB, 2): the first and last run each block of LB lanes touches."""
    starts = np.arange(num_blocks) * LB
    first = np.minimum(starts // lanes_per_run, num_runs - 1)
    last = np.minimum((starts + LB - 1) // lanes_per_run, num_runs - 1)
    return np.stack([first, last], 1)


@njit(inline="always", **JIT)
def block_active(b, block_runs, active):  # pragma: no cover
    """Whether a run of block b is `active` (a loop: `.any()` of a slice compiled slower)."""
    for r in range(block_runs[b, 0], block_runs[b, 1] + 1):
        if active[r]:
            return True
    return False


class Forwarded:
    """Which runs' lanes hold the forward pass of the parameters a call now hands: the gradient
    step after an accepted adaptive trial (Sec. 2.1.4) is at the trial's point, so it finds the
    trial's forward pass in the lanes and runs only what follows it. The forward pass is a
    function of the parameters, the inputs and nothing else, computed per lane, so the step gives
    bit for bit what a fresh pass would.

    A block of lanes is recomputed when any run it holds is stale, with every lane's current
    parameters; a run is then current if all of its blocks were recomputed, unchanged if none
    was, and unknown (stale from then on) if some were and its parameters had changed.
    The stepper (`moex.kernels.cpu.step`) keeps a record of its own on the same rules, over the
    objective's parameters too (phase 1's β and log σ), and reuses the trial's objective and
    ∂/∂o as well (the kernels' `reuse`); this class serves the separate calls.

    Args:
        block_runs: (NB, 2) the first and last run of each block (`runs_of_blocks`).
        lanes_per_run: lanes of one run; names: the parameters the forward pass reads;
        LB: lanes per block.
    """

    enabled = True  # False: every call runs its forward pass (the tests compare the two)

    def __init__(self, block_runs, lanes_per_run: int, names: tuple[str, ...], LB: int):
        R = int(block_runs[-1, 1]) + 1
        first, last = np.arange(R) * lanes_per_run, (np.arange(R) + 1) * lanes_per_run - 1
        self.first_block, self.last_block = first // LB, last // LB
        self.block_runs, self.names = block_runs, names
        self.params: tuple = ()  # the bits (`_bits`) of the parameters the lanes were run with
        self.current = np.zeros(R, bool)

    def _bits(self, params: dict) -> tuple:
        return tuple(_bits(np.ascontiguousarray(params[name])) for name in self.names)

    def stale(self, params: dict, active: np.ndarray) -> np.ndarray:
        """(R,) the active runs whose lanes need a forward pass for `params`."""
        if not (self.enabled and self.current.any()):
            return active
        out = np.empty_like(active)
        stale_runs(0, len(out), self._bits(params), self.params, self.current, active, out)
        return out

    def record(self, params: dict, stale: np.ndarray) -> None:
        """After a call that recomputed the blocks holding a `stale` run, with `params`."""
        now = self._bits(params)
        if not self.params:
            self.params = tuple(np.array(x) for x in now)
        record_runs(0, len(stale), now, self.params, stale, self.block_runs, self.first_block,
                    self.last_block, self.current)

    def forget(self) -> None:
        """The inputs changed (fresh input noise): no lane holds a current forward pass."""
        self.current[:] = False


def _bits(x: np.ndarray) -> np.ndarray:
    """(R, -1) unsigned integers of the same bits: an exact comparison (-0.0 is not 0.0)."""
    return x.reshape(len(x), -1).view(f"u{x.dtype.itemsize}")


@njit(inline="always", **JIT)
def _equal(now, then, r):  # pragma: no cover
    """Whether run r's row of every array in `now` equals that in `then` (unsigned integers: the
    parameters' bits): the XOR of every pair ORed, which LLVM vectorises (a loop that leaves at
    the first difference stays scalar: 3-6x slower over a row of phase 1's β)."""
    for k in range(len(now)):
        a, b = now[k], then[k]
        differ = a.dtype.type(0)
        for q in range(a.shape[1]):
            differ |= a[r, q] ^ b[r, q]
        if differ:
            return False
    return True


@njit(nogil=True, inline="always", **JIT)
def stale_runs(lo, hi, now, then, current, active, out):  # pragma: no cover
    """out[r] for runs r = lo..hi-1: whether r is active and not current with exactly the
    parameter bits `now`."""
    for r in range(lo, hi):
        out[r] = active[r] and not (current[r] and _equal(now, then, r))


@njit(nogil=True, inline="always", **JIT)
def record_runs(lo, hi, now, then, stale, block_runs, first_block, last_block,
                current):  # pragma: no cover
    """Runs lo..hi-1 after a call that recomputed every block holding a `stale` run, with
    parameters of the bits `now`: a run all of whose blocks were recomputed is current (its row
    of `then` := `now`), one none of whose blocks was keeps its state, and one in between stays
    current only if its parameters did not change. `then` None: the record is `now` itself, whose
    row the caller never changes while its run is current (the stepper's θ + Δθ: nothing to copy
    or compare)."""
    for r in range(lo, hi):  # (loops written out: array expressions here took
        count = 0  # seconds of a first run to compile)
        for b in range(first_block[r], last_block[r] + 1):
            count += block_active(b, block_runs, stale)
        if count == last_block[r] - first_block[r] + 1:
            if then is not None:
                for k in range(len(now)):
                    new, old = now[k], then[k]
                    for q in range(new.shape[1]):
                        old[r, q] = new[r, q]
            current[r] = True
        elif count > 0 and then is not None:
            current[r] = current[r] and _equal(now, then, r)


# ---------------------------------------------------------------------------------------------
# the backend interface (the same classes as moex.kernels.reference)

logger = logging.getLogger("moex.kernels.cpu")
_ready: set = set()


def first_use(kernel, what: str, after: float = 2.0):
    """Log lines around the first call of a kernel in this process where it takes a while: numba
    compiles it then (tens of seconds) or waits for the helper that compiles it beside the run
    (`warm`); a kernel loaded from the cache on disk (about a second) says nothing, so a cached
    run's log has no line about kernels. The first line comes `after` seconds, while it waits.
    A context manager; once the kernel is ready, one that does nothing (the training loop's
    every step: a generator's would cost it several µs)."""
    return _READY if kernel in _ready else _first_use(kernel, what, after)


_READY = contextlib.nullcontext()


@contextlib.contextmanager
def _first_use(kernel, what: str, after: float):
    import threading

    from moex.kernels.cpu import warm

    told = threading.Event()

    def tell():
        told.set()
        logger.info("compiling the %s (on first use, then cached on disk) ...", what)

    timer = threading.Timer(after, tell)
    timer.daemon = True
    timer.start()
    start = time.perf_counter()
    try:
        if warm.wait_for(kernel) and told.is_set():
            logger.info("the helper process compiled the %s in the meantime", what)
        yield
    finally:
        timer.cancel()
    _ready.add(kernel)
    if told.is_set():
        logger.info("compiled %s ready in %.1f s", what, time.perf_counter() - start)


NET = ("w_in", "w_rec", "w_out", "b_c", "b_o", "tau")


def per_network(params: dict, experts: bool) -> tuple:
    """The network parameters as (R, K', ...) views (K' = 1 for the gating RNN), never copies:
    the kernels write gradients into them."""
    return tuple(params[n] if experts else params[n][:, None] for n in NET)


def in_lanes(per_lane: np.ndarray) -> np.ndarray:
    """(..., NL) -> (NB, ..., LB), lanes padded with zeros to whole blocks."""
    NL, LB, NP = per_lane.shape[-1], width(per_lane), padded(per_lane.shape[-1], per_lane.dtype)
    padded_lanes = np.zeros(per_lane.shape[:-1] + (NP,), per_lane.dtype)
    padded_lanes[..., :NL] = per_lane
    blocks = np.moveaxis(padded_lanes.reshape(per_lane.shape[:-1] + (NP // LB, LB)), -2, 0)
    out = zeros(blocks.shape, per_lane.dtype)
    out[...] = blocks
    return out


SIZES = ("compiled", "runtime")  # the values of MOEX_CPU_SIZES, the default first


def size_choice() -> str:
    """MOEX_CPU_SIZES (default compiled), a `ConfigError` naming the choices for another value."""
    choice = os.environ.get("MOEX_CPU_SIZES", SIZES[0])
    check(choice in SIZES, f"MOEX_CPU_SIZES={choice}; choose compiled or runtime")
    return choice


def sizes(H: int, NI: int, NO: int) -> tuple:
    """The RNN passes' `sizes` argument (`moex.kernels.cpu.rnn`): tuples of H, NI and NO zeros,
    whose lengths numba compiles in as constants (a kernel for each network size, its loops
    unrolled: 1.3-1.6x as fast), or with MOEX_CPU_SIZES=runtime three empty tuples (one kernel for
    every size, for code that meets many sizes: the test suite). The same bits either way."""
    return ((0,) * H, (0,) * NI, (0,) * NO) if size_choice() == SIZES[0] else ((), (), ())


class Lanes:
    """Work arrays of one phase, block-major (NB, ..., LB) so that a block's history is one
    contiguous piece of memory: per-lane weights, histories and per-lane gradients; the RNN's
    `sizes` (H units, NI inputs, NO outputs)."""

    def __init__(self, T, H, NI, NO, *, num_lanes, lanes_per_run, num_runs, learn_tau,
                 attraction, dtype):
        self.width = LB = width(dtype)
        self.sizes = sizes(H, NI, NO)
        NB = padded(num_lanes, dtype) // LB

        def blocks(*shape):
            return zeros((NB,) + shape + (LB,), dtype)

        self.net = (blocks(H, NI), blocks(H, H), blocks(NO, H), blocks(H), blocks(NO), blocks(H),
                    blocks(H))
        sums = (NB, H if attraction else 0, LB)
        self.work = [blocks(H), blocks(T, H), blocks(T, NO),
                     blocks(*((T, H) if learn_tau else (0, 0))), zeros(sums), zeros(sums),
                     blocks(T, NO)]
        self.lane_grads = tuple(zeros(x.shape, dtype) for x in self.net)
        self.block_runs = runs_of_blocks(NB, lanes_per_run, num_runs, LB)
        self.num_lanes = NB * LB
        self.out = np.zeros((4, num_runs), dtype)

    def stats(self, names) -> dict[str, np.ndarray]:
        return {n: torch.from_numpy(self.out[i].copy()) for i, n in enumerate(names)}


class Staging:
    """The arrays the kernels read parameters from and write gradients to. numba types a strided
    view differently from a C-contiguous array, and the training loop's views of its (R, P)
    buffers are strided for R > 1: those are copied into C-contiguous arrays of this class (a few
    percent of a step), so that every kernel compiles once per dtype. A view that is already
    C-contiguous (every group at R = 1) is handed to the kernels as it is: no copy in or out."""

    def __init__(self, shapes: dict, dtype):
        self.params = {n: np.zeros(shape, dtype) for n, shape in shapes.items()}
        self.grads = {n: np.zeros(shape, dtype) for n, shape in shapes.items()}
        # (tensor, its numpy view, whether the kernels take it as it is), the last few per
        # (group, copy_in): the training loop hands the same views every step (the parameters'
        # and, in turn, the adaptive rate's candidates'), not to be converted and checked again
        self.seen: dict[tuple[str, bool], list[tuple]] = {}

    def load(self, params: dict) -> dict:
        """The arrays holding `params` for the kernels to read."""
        return {name: self._direct(name, value, self.params[name], True)
                for name, value in params.items()}

    def outputs(self, grads: dict | None) -> dict:
        """The arrays the kernels write the gradients into: the `grads` views themselves where
        they can, else this class's (`store` copies those out); scratch for groups not given."""
        return {name: self._direct(name, grads[name], own, False) if grads and name in grads
                else own for name, own in self.grads.items()}

    def _direct(self, name: str, value, own: np.ndarray, copy_in: bool) -> np.ndarray:
        """The numpy view of `value` where the kernels can take it as it is (`_usable`), else
        `own`, with the value copied in if `copy_in`; the view and its check are remembered for
        the group's last `SEEN` tensors."""
        recent = self.seen.setdefault((name, copy_in), [])
        seen = next((entry for entry in recent if entry[0] is value), None)
        if seen is None:
            x = to_host(value)
            seen = (value, x, _usable(x, own))
            recent[:] = [seen, *recent[:SEEN - 1]]
        _, x, usable = seen
        if usable:
            return x
        if copy_in:
            np.copyto(own, x)
        return own

    def store(self, grads: dict | None, written: dict) -> None:
        """Copy the gradients the kernels wrote into `written` out to `grads` where they differ."""
        for name, value in (grads or {}).items():
            if written[name] is self.grads[name]:
                np.copyto(to_host(value), self.grads[name])


SEEN = 4  # tensors remembered per group: the parameters, the candidates, and spares


def _usable(x: np.ndarray, own: np.ndarray) -> bool:
    """Whether the kernels can take `x` as it is, instead of `own` (C-contiguous, writeable,
    aligned, of the staged shape and dtype)."""
    return (x.flags.c_contiguous and x.flags.writeable and x.flags.aligned
            and x.shape == own.shape and x.dtype == own.dtype)


def to_host(x) -> np.ndarray:
    """The numpy view of a CPU tensor (the training loop's buffers; a tensor elsewhere is
    copied to the host), or the array itself."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
