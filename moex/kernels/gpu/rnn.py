"""The leaky RNN of Eqs. 1-3 / 5-8, teacher forced, as three Triton kernels: the forward pass, the
backward recurrence (BPTT) and the weight gradients' sums. A training step of either phase
(`moex.kernels.gpu.phases`) is the forward kernel, the phase's objective kernel and the two
backward kernels: four launches.

Layout (the same lanes as the CPU backend, `moex.kernels.cpu`): every independent recurrence is a
*lane* — an (expert, series) pair of a run in phase 1, a series of a run in phase 2. Network n
(expert k = n mod NPR of run r = n div NPR; NPR networks per run) owns the LPN lanes n·LPN + j.
A program runs one network, its lanes in chunks of BL through the whole time loop; its products
with the weight matrices go by columns (`rnn_forward`), the columns read from memory (L1) at each
step. Lane l reads row XROW[l] of X (NX, T, NI) and row U0J[l] of its run's u_0.
Parameters are read where the training loop keeps them: the (R, ...) groups of its flat buffer,
run r at r·stride (each group's stride an argument), the rest contiguous. Sizes are padded to
powers of two inside (masked).

Forward (per lane, Eqs. 1-2 with the output layer), ε = 1/τ:
    c_{-1} = tanh(u_0 + b),  u_t = u_{t-1} + ε (W_in x_t + W_rec c_{t-1} - u_{t-1}),
    c_t = tanh(u_t + b),     o_t = W_out c_t + b_o                       (t = 0..T-1)
The kernel writes o_t (the objective applies tanh or softmax), c_t for the backward pass, u_t when
ε is learned, and Σu, Σu² over {u_0..u_T} (the C code's u_0 attraction).

Backward, given δo_t = ∂L/∂o_t; with a_t = ∂L/∂u_t and q_t = u_t + b:
    a_t = (1 - c_t²) (W_outᵀ δo_t + W_recᵀ ε a_{t+1}) + (1 - ε) a_{t+1}        (a_T = 0)
    ∂W_out += δo_t c_tᵀ,  ∂b_o += δo_t,  ∂b += (1 - c_t²)(W_outᵀ δo_t + W_recᵀ ε a_{t+1}),
    ∂W_in += (ε a_t) x_tᵀ,  ∂W_rec += (ε a_t) c_{t-1}ᵀ,  ∂ε += a_t (u_t - u_{t-1}) / ε,
and at the start, where c_{-1} = tanh(u_0 + b) feeds step 0 with r = W_recᵀ ε a_0:
    ∂u_0 = (1 - ε) a_0 + (1 - c_{-1}²) r,  ∂b += (1 - c_{-1}²) r.
With the attraction, ∂u_0 += (μ - u_0) / v (μ, v: the lane's mean and floored variance of
{u_0..u_T}, held constant). The backward recurrence (`rnn_backward`) runs a_t back through time
and writes ε a_t for every step; the sums of the weight matrices' gradients over lanes and steps
are a second kernel (`rnn_weight_gradients`), so that the recurrence's time loop holds no
(lanes, H, H) product and sums nothing across threads. Both sum in a fixed order (reruns are
exact) and write into the training loop's gradient buffer, ∂τ = -ε² ∂ε included; a run that is
not active keeps what its gradients held.

Real-valued constants are never kernel arguments: a Python float reaches a GPU kernel as a
float32 scalar (ε = 0.2 became 0.2000000030 in float64 runs), so they are read from memory.
Loop bounds are `tl.constexpr` (a training's sizes are fixed, so each compiles once; Triton's
interpreter also runs runtime bounds, as the closed loop's chunk length is).
"""

import os

import triton
import triton.language as tl
from triton.language.extra import libdevice

INTERPRET = os.environ.get("TRITON_INTERPRET") == "1"  # read when Triton is (set it before)
# float32 on a GPU: Triton lowers exp, σ and `/` to ex2.approx / div.full (≤ 2 ulp each);
# libdevice's expf, logf, tanhf and div.rn are accurate, at no cost measured on an H200 (they
# were not what put a float32 gradient off there: see `lane_moments`). The interpreter computes
# with NumPy and has no libdevice.
ACCURATE_F32 = tl.constexpr(not INTERPRET)
# the forward and backward kernels' loops over columns, unrolled by this much: at Table 2's
# H = 10 the same machine code as unrolling them whole; H = 50 whole took 50 s to compile (2 s)
UNROLL = tl.constexpr(10)


def device(fn):
    """`triton.jit` for a function the kernels call. In Triton's interpreter (`TRITON_INTERPRET=1`)
    it is the interpreter's rewrite of `fn`, called directly: Triton 3.x's interpreter patches all
    of `triton.language` again on every call of a jitted device function (a third of the time of
    the interpreted tests went there); the launch's own patching covers the call."""
    jitted = triton.jit(fn)
    return jitted.rewrite() if INTERPRET else jitted


@device
def stable_tanh(x):
    """tanh(x) = 2σ(2x) - 1: finite for every x, ≤ 3e-16 from tanh in float64, and the same
    formula on a GPU and in the interpreter; in float32 on a GPU, libdevice's tanhf."""
    out = 2.0 * tl.sigmoid(2.0 * x) - 1.0
    if x.dtype == tl.float32:
        if ACCURATE_F32:
            out = libdevice.tanh(x)
    return out


@device
def exp(x):
    """e^x, accurate in both precisions (libdevice's expf in float32 on a GPU)."""
    out = tl.exp(x)
    if x.dtype == tl.float32:
        if ACCURATE_F32:
            out = libdevice.exp(x)
    return out


@device
def log(x):
    """ln x, accurate in both precisions (libdevice's logf in float32 on a GPU)."""
    out = tl.log(x)
    if x.dtype == tl.float32:
        if ACCURATE_F32:
            out = libdevice.log(x)
    return out


@device
def divide(a, b):
    """a / b (broadcast) rounded correctly in both precisions (a float32 `/` is approximate on
    a GPU)."""
    a, b = tl.broadcast(a, b)
    if a.dtype == tl.float32:
        out = tl.math.div_rn(a, b)
    else:
        out = a / b
    return out


@device
def reciprocal(x):
    """1/x rounded correctly in both precisions."""
    return divide(tl.full(x.shape, 1.0, x.dtype), x)


@device
def _put_tile(ptr, rows, cols, value, on, NR: tl.constexpr, NC: tl.constexpr):
    """Store an (RP, CP) tile where `on` ((RP,) bools: the run is active)."""
    mask = on[:, None] & (rows < NR)[:, None] & (cols < NC)[None, :]
    tl.store(ptr + rows[:, None] * NC + cols[None, :], value, mask=mask)


@device
def _vector(ptr, cols, NC: tl.constexpr, other):
    return tl.load(ptr + cols, mask=cols < NC, other=other)


@device
def load_rows(ptr, index, lane_ok, cols, NC: tl.constexpr):
    """(BL, CP): row index[l] of (·, NC) memory for each lane."""
    mask = lane_ok[:, None] & (cols < NC)[None, :]
    return tl.load(ptr + index[:, None] * NC + cols[None, :], mask=mask, other=0.0)


@device
def lane_moments(SUMS, lane, ok, h, floor, T: tl.constexpr, H: tl.constexpr):
    """(BL, HP) mean μ and floored variance v of each lane's {u_0..u_T} from the forward kernel's
    float64 Σu, Σu² (the C code's u_0 attraction), computed in float64 (in float32 the difference
    Σu²/n - μ² loses the digits that the variance is made of), returned in floor's precision."""
    count = tl.full((1, 1), T + 1, tl.float64)
    mean = load_rows(SUMS, lane * 2, ok, h, H) / count
    var = load_rows(SUMS, lane * 2 + 1, ok, h, H) / count - mean * mean
    return mean.to(floor.dtype), tl.maximum(var.to(floor.dtype), floor)


@device
def _put(ptr, index, lane_ok, cols, value, NC: tl.constexpr):
    mask = lane_ok[:, None] & (cols < NC)[None, :]
    tl.store(ptr + index[:, None] * NC + cols[None, :], value, mask=mask)


@device
def _network(NPR: tl.constexpr):
    """This program's network n, its run r and its index k within the run (int64)."""
    n = tl.program_id(0).to(tl.int64)
    return n, n // NPR, n % NPR


@device
def _chunk(XROW, U0J, n, chunk, LPN: tl.constexpr, BL: tl.constexpr):
    """Lanes of network n in chunk `chunk`, which exist, their input rows and u_0 rows."""
    j = chunk * BL + tl.arange(0, BL)
    ok = j < LPN
    lane = n * LPN + j
    return (lane, ok, tl.load(XROW + lane, mask=ok, other=0),
            tl.load(U0J + lane, mask=ok, other=0))


@device
def _add_by_columns(acc, V, row, ok, W, cols, cols_ok, N: tl.constexpr, SJ: tl.constexpr,
                    SC: tl.constexpr):
    """acc + Σ_{j<N} v_j w_j as outer-product updates, no sum across threads: v_j the lanes'
    entry j of row `row` of V (·, N) in memory, w_j the (CP,) weights W[j·SJ + cols·SC] (a
    column of W_rec with SJ = 1, SC = H; a row with SJ = H, SC = 1)."""
    for j in tl.range(0, N, loop_unroll_factor=UNROLL):
        v_j = tl.load(V + row * N + j, mask=ok, other=0.0)[:, None]
        acc += v_j * tl.load(W + j * SJ + cols * SC, mask=cols_ok, other=0.0)[None, :]
    return acc


@device
def _state_row(lane, t, T: tl.constexpr, KEEP_C: tl.constexpr):
    """The row of C where lane `lane` leaves c_t: its history row, or one of its two scratch
    rows (t mod 2: a row is rewritten only after the barrier of the step between)."""
    if KEEP_C:
        row = lane * T + t
    else:
        row = lane * 2 + t % 2
    return row


@triton.jit
def rnn_forward(X, XROW, U0J, W_IN, W_REC, W_OUT, B_C, B_O, TAU, U0, OUT, C, U, SUMS,
                sW_IN, sW_REC, sW_OUT, sB_C, sB_O, sTAU, sU0,
                T: tl.constexpr, NI: tl.constexpr, H: tl.constexpr, NO: tl.constexpr,
                HP: tl.constexpr, NOP: tl.constexpr, BL: tl.constexpr,
                LPN: tl.constexpr, NPR: tl.constexpr, CHUNKS: tl.constexpr,
                KEEP_C: tl.constexpr, KEEP_U: tl.constexpr, KEEP_SUMS: tl.constexpr):
    """Forward pass of one network's lanes: OUT (L, T, NO) always; U (L, T, H) and SUMS
    (L, 2, H) when KEEP_U, KEEP_SUMS; C the history (L, T, H) when KEEP_C, else (L, 2, H) rows
    that pass each step's state on.

    The matrix-vector products go by columns: c_t is written to C, and after one barrier every
    thread reads it back a column c_{t,j} at a time, W_rec c_t + W_in x_{t+1} = Σ_j c_{t,j} w_j +
    Σ_i x_i w^in_i and W_out c_t likewise, as outer-product updates of the lanes' (BL, H)
    accumulators, the weight columns read from memory (L1) at every step: no sum runs across
    threads (on an H200, 0 warp shuffles per step instead of 296 and 0.59x the time at 90
    networks; BENCHMARKS.md "Compiled for an H200 without one")."""
    n, r, k = _network(NPR)
    h, o = tl.arange(0, HP), tl.arange(0, NOP)
    h_ok, o_ok = h < H, o < NO
    w_in = W_IN + r * sW_IN + k * (H * NI)
    w_rec = W_REC + r * sW_REC + k * (H * H)
    w_out = W_OUT + r * sW_OUT + k * (NO * H)
    b_c = _vector(B_C + r * sB_C + k * H, h, H, 0.0)[None, :]
    b_o = _vector(B_O + r * sB_O + k * NO, o, NO, 0.0)[None, :]
    eps = reciprocal(_vector(TAU + r * sTAU + k * H, h, H, 1.0))[None, :]
    for chunk in range(CHUNKS):
        lane, ok, xrow, u0j = _chunk(XROW, U0J, n, chunk, LPN, BL)
        u = load_rows(U0 + r * sU0, u0j, ok, h, H)
        s1 = u.to(tl.float64)  # float64 sums, as on the CPU: the variance is taken by difference
        s2 = s1 * s1
        # c_{-1} passes through row 0, which c_0 then takes: a barrier on either side
        _put(C, _state_row(lane, 0, T, KEEP_C), ok, h, stable_tanh(u + b_c), H)
        tl.debug_barrier()
        drive = _add_by_columns(tl.zeros((BL, HP), dtype=u.dtype), C,  # W_rec c_{t-1}, + W_in x_t
                                _state_row(lane, 0, T, KEEP_C), ok, w_rec, h, h_ok, H, 1, H)
        tl.debug_barrier()
        for t in range(T):
            for i in tl.static_range(NI):
                x_i = tl.load(X + (xrow * T + t) * NI + i, mask=ok, other=0.0)
                drive += x_i[:, None] * tl.load(w_in + h * NI + i, mask=h_ok, other=0.0)[None, :]
            u = u + eps * (drive - u)
            if KEEP_SUMS:
                u64 = u.to(tl.float64)
                s1 += u64
                s2 += u64 * u64
            if KEEP_U:
                _put(U, lane * T + t, ok, h, u, H)
            row = _state_row(lane, t, T, KEEP_C)
            _put(C, row, ok, h, stable_tanh(u + b_c), H)
            tl.debug_barrier()  # every lane's c_t written before any thread reads its columns
            drive = tl.zeros((BL, HP), dtype=u.dtype)
            out = tl.zeros((BL, NOP), dtype=u.dtype) + b_o
            for j in tl.range(0, H, loop_unroll_factor=UNROLL):  # W_rec c_t and W_out c_t at once
                c_j = tl.load(C + row * H + j, mask=ok, other=0.0)[:, None]
                drive += c_j * tl.load(w_rec + h * H + j, mask=h_ok, other=0.0)[None, :]
                out += c_j * tl.load(w_out + o * H + j, mask=o_ok, other=0.0)[None, :]
            _put(OUT, lane * T + t, ok, o, out, NO)
        if KEEP_SUMS:
            _put(SUMS, lane * 2, ok, h, s1, H)
            _put(SUMS, lane * 2 + 1, ok, h, s2, H)


@triton.jit
def rnn_backward(DO, XROW, U0J, W_REC, W_OUT, B_C, TAU, U0, C, U, SUMS, ACTIVE, FLOOR, EA, C0,
                 G_B_C, G_TAU, G_U0, sW_REC, sW_OUT, sB_C, sTAU, sU0, sG_B_C, sG_TAU, sG_U0,
                 T: tl.constexpr, H: tl.constexpr, NO: tl.constexpr, HP: tl.constexpr,
                 BL: tl.constexpr, LPN: tl.constexpr, NPR: tl.constexpr, CHUNKS: tl.constexpr,
                 LEARN_EPS: tl.constexpr, ATTRACT: tl.constexpr):
    """Backward recurrence of one network's lanes given DO (L, T, NO) = ∂L/∂o_t: writes ε a_t of
    every lane and step into EA (L, T, H) for `rnn_weight_gradients`, and the gradients that are
    sums over a lane's own steps: G_B_C (H), G_TAU (H, when LEARN_EPS; it then reads U) and each
    lane's G_U0 (H), where ACTIVE[r]. As in the forward kernel, the products with W_outᵀ and
    W_recᵀ go by columns: δo_t's from DO itself, ε a_t's from EA after a barrier, each an
    outer-product update with a row of the weight matrix read from memory. The weight matrices'
    gradients, sums over lanes, are not formed here: summing them at every step ran across the
    threads that hold the lanes (shuffles, and a (lanes, H, H) product that set the lane budget)."""
    n, r, k = _network(NPR)
    h = tl.arange(0, HP)
    on_h = tl.load(ACTIVE + r + 0 * h) != 0  # (a vector: the interpreter's masks need one)
    h_ok = h < H
    w_rec = W_REC + r * sW_REC + k * (H * H)
    w_out = W_OUT + r * sW_OUT + k * (NO * H)
    b_c = _vector(B_C + r * sB_C + k * H, h, H, 0.0)[None, :]
    eps = reciprocal(_vector(TAU + r * sTAU + k * H, h, H, 1.0))[None, :]
    dtype = b_c.dtype
    n_b_c = tl.zeros((HP,), dtype=dtype)
    n_eps = tl.zeros((HP,), dtype=dtype)
    for chunk in range(CHUNKS):
        lane, ok, _, u0j = _chunk(XROW, U0J, n, chunk, LPN, BL)
        ok = ok & (tl.load(ACTIVE + r + 0 * lane) != 0)
        u0 = load_rows(U0 + r * sU0, u0j, ok, h, H)
        c0 = stable_tanh(u0 + b_c)
        _put(C0, lane * 2, ok, h, c0, H)  # c_{-1}, for `rnn_weight_gradients`
        zero_h = tl.zeros((BL, HP), dtype=dtype)
        a, back, g_b_c, g_eps = zero_h, zero_h, zero_h, zero_h
        for step in range(T):
            t = T - 1 - step
            c = load_rows(C, lane * T + t, ok, h, H)
            back = _add_by_columns(back, DO, lane * T + t, ok, w_out, h, h_ok, NO, H, 1)  # W_outᵀδo
            dq = (1.0 - c * c) * back
            g_b_c += dq
            a = (1.0 - eps) * a + dq
            if LEARN_EPS:
                before = ok & (lane * 0 + t > 0)  # a step before t exists (a tensor: a mask's type)
                u = load_rows(U, lane * T + t, ok, h, H)
                u_prev = tl.where(t == 0, u0, load_rows(U, lane * T + t - 1, before, h, H))
                g_eps += divide(a * (u - u_prev), eps)
            _put(EA, lane * T + t, ok, h, eps * a, H)  # back = W_recᵀ ε a_t, by its columns
            tl.debug_barrier()
            back = _add_by_columns(zero_h, EA, lane * T + t, ok, w_rec, h, h_ok, H, H, 1)
        dq = (1.0 - c0 * c0) * back
        g_u0 = (1.0 - eps) * a + dq
        if ATTRACT:
            mean, var = lane_moments(SUMS, lane, ok, h, tl.load(FLOOR), T, H)
            g_u0 += divide(mean - u0, var)
        _put(G_U0 + r * sG_U0, u0j, ok, h, g_u0, H)
        n_b_c += tl.sum(g_b_c + dq, axis=0)
        n_eps += tl.sum(g_eps, axis=0)
    tl.store(G_B_C + r * sG_B_C + k * H + h, n_b_c, mask=on_h & h_ok)
    if LEARN_EPS:  # ∂/∂τ = -ε² ∂/∂ε
        eps_h = tl.sum(eps, axis=0)
        tl.store(G_TAU + r * sG_TAU + k * H + h, -n_eps * (eps_h * eps_h), mask=on_h & h_ok)


@triton.jit
def rnn_weight_gradients(EA, DO, C, C0, X, XROW, ACTIVE, G_W_IN, G_W_REC, G_W_OUT, G_B_O,
                         sG_W_IN, sG_W_REC, sG_W_OUT, sG_B_O,
                         T: tl.constexpr, NI: tl.constexpr, H: tl.constexpr, NO: tl.constexpr,
                         IG: tl.constexpr, HG: tl.constexpr, OG: tl.constexpr,
                         BR: tl.constexpr, LPN: tl.constexpr, NPR: tl.constexpr):
    """One network's weight gradients, sums over its lanes and steps (LPN·T rows, BR at a time):
        ∂W_in = Σ (ε a_t) x_tᵀ,  ∂W_rec = Σ (ε a_t) c_{t-1}ᵀ,  ∂W_out = Σ δo_t c_tᵀ,  ∂b_o = Σ δo_t
    from EA and C0 (c_{-1} = tanh(u_0 + b), in row 2l of lane l; both from `rnn_backward`), DO and
    C, written where ACTIVE[r].
    Each block of rows is a matrix product (`tl.dot`: an H200's fp64 tensor cores, DMMA; sizes
    padded to at least 16 as it requires), summed in a fixed order: reruns are exact."""
    n, r, k = _network(NPR)
    h, i, o, q = tl.arange(0, HG), tl.arange(0, IG), tl.arange(0, OG), tl.arange(0, BR)
    on_h = tl.load(ACTIVE + r + 0 * h) != 0
    on_o = tl.load(ACTIVE + r + 0 * o) != 0
    dtype = EA.dtype.element_ty
    n_w_in = tl.zeros((HG, IG), dtype=dtype)
    n_w_rec = tl.zeros((HG, HG), dtype=dtype)
    n_w_out = tl.zeros((OG, HG), dtype=dtype)
    n_b_o = tl.zeros((OG,), dtype=dtype)
    for block in range(tl.cdiv(LPN * T, BR)):
        at = block * BR + q
        ok = at < LPN * T
        t = at % T
        lane = n * LPN + at // T
        first, later = ok & (t == 0), ok & (t > 0)
        ea = load_rows(EA, lane * T + t, ok, h, H)
        do = load_rows(DO, lane * T + t, ok, o, NO)
        prev = tl.where(first[:, None], load_rows(C0, lane * 2, first, h, H),
                        load_rows(C, lane * T + t - 1, later, h, H))
        x = load_rows(X, tl.load(XROW + lane, mask=ok, other=0) * T + t, ok, i, NI)
        eat = tl.trans(ea)
        n_w_in += tl.dot(eat, x, input_precision="ieee")
        n_w_rec += tl.dot(eat, prev, input_precision="ieee")
        n_w_out += tl.dot(tl.trans(do), load_rows(C, lane * T + t, ok, h, H),
                          input_precision="ieee")
        n_b_o += tl.sum(do, axis=0)
    tl.store(G_B_O + r * sG_B_O + k * NO + o, n_b_o, mask=on_o & (o < NO))
    _put_tile(G_W_IN + r * sG_W_IN + k * (H * NI), h, i, n_w_in, on_h, H, NI)
    _put_tile(G_W_REC + r * sG_W_REC + k * (H * H), h, h, n_w_rec, on_h, H, H)
    _put_tile(G_W_OUT + r * sG_W_OUT + k * (NO * H), o, h, n_w_out, on_o, NO, H)
