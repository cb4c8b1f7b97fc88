"""The leaky RNN of Eqs. 1-3 / 5-8, teacher forced, as two Triton kernels: the forward pass and
its backward pass (BPTT). Both training phases of the GPU backend (`moex.kernels.gpu.phases`) are
these two kernels with the phase's objective between them.

Layout (the same lanes as the CPU backend, `moex.kernels.cpu`): every independent recurrence is a
*lane* — an (expert, series) pair of a run in phase 1, a series of a run in phase 2. A program
runs a block of `BL` lanes through the whole time loop, each lane holding its own network's
weights in registers as a (BL, rows, cols) tile; lane l reads its weights from network `net[l]`,
its inputs from row `xrow[l]` of X (NX, T, NI) and its initial state from row `u0row[l]` of
U0 (·, H). Sizes are padded to powers of two inside (masked).

Forward (per lane, Eqs. 1-2 with the output layer):
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
Gradients are per lane; the caller sums the lanes of each network.

Real-valued constants are never kernel arguments: a Python float reaches a GPU kernel as a
float32 scalar (ε = 0.2 became 0.2000000030 in float64 runs), so ε is read from memory.
Loop bounds are `tl.constexpr` (the interpreter that runs these kernels on a CPU needs it).
"""

import triton
import triton.language as tl


@triton.jit
def _tanh(x):
    """tanh(x) = 2σ(2x) - 1: finite for every x, ≤ 3e-16 from tanh in float64, and the same
    formula on a GPU and in the interpreter."""
    return 2.0 * tl.sigmoid(2.0 * x) - 1.0


@triton.jit
def _matvec(w, v):
    """(BL, R, C) · (BL, C) -> (BL, R)."""
    return tl.sum(w * v[:, None, :], axis=2)


@triton.jit
def _matvec_t(w, v):
    """(BL, R, C)ᵀ · (BL, R) -> (BL, C)."""
    return tl.sum(w * v[:, :, None], axis=1)


@triton.jit
def _tile(ptr, net, lane_ok, rows, cols, NR: tl.constexpr, NC: tl.constexpr):
    """The (BL, RP, CP) weight tile of each lane's network from (networks, NR, NC) memory."""
    offs = net[:, None, None] * (NR * NC) + rows[None, :, None] * NC + cols[None, None, :]
    mask = lane_ok[:, None, None] & (rows < NR)[None, :, None] & (cols < NC)[None, None, :]
    return tl.load(ptr + offs, mask=mask, other=0.0)


@triton.jit
def _row(ptr, index, lane_ok, cols, NC: tl.constexpr):
    """(BL, CP): row index[l] of (·, NC) memory for each lane."""
    mask = lane_ok[:, None] & (cols < NC)[None, :]
    return tl.load(ptr + index[:, None] * NC + cols[None, :], mask=mask, other=0.0)


@triton.jit
def _put(ptr, index, lane_ok, cols, value, NC: tl.constexpr):
    mask = lane_ok[:, None] & (cols < NC)[None, :]
    tl.store(ptr + index[:, None] * NC + cols[None, :], value, mask=mask)


@triton.jit
def _put_tile(ptr, lane, lane_ok, rows, cols, value, NR: tl.constexpr, NC: tl.constexpr):
    offs = lane[:, None, None] * (NR * NC) + rows[None, :, None] * NC + cols[None, None, :]
    mask = lane_ok[:, None, None] & (rows < NR)[None, :, None] & (cols < NC)[None, None, :]
    tl.store(ptr + offs, value, mask=mask)


@triton.jit
def _lanes(NET, XROW, num_lanes, BL: tl.constexpr):
    """This program's BL lanes (int64: offsets past 2³¹), which exist, and each lane's network and
    input row."""
    lane = (tl.program_id(0) * BL + tl.arange(0, BL)).to(tl.int64)
    ok = lane < num_lanes
    return (lane, ok, tl.load(NET + lane, mask=ok, other=0),
            tl.load(XROW + lane, mask=ok, other=0))


@triton.jit
def rnn_forward(X, XROW, NET, U0ROW, WI, WR, WO, BC, BO, EPS, U0, OUT, C, U, SUMS, num_lanes,
                T: tl.constexpr, NI: tl.constexpr, H: tl.constexpr, NO: tl.constexpr,
                NIP: tl.constexpr, HP: tl.constexpr, NOP: tl.constexpr, BL: tl.constexpr,
                KEEP_C: tl.constexpr, KEEP_U: tl.constexpr, KEEP_SUMS: tl.constexpr):
    """Forward pass of BL lanes: OUT (L, T, NO) always; C, U (L, T, H) and SUMS (L, 2, H) when
    KEEP_C, KEEP_U, KEEP_SUMS."""
    lane, ok, net, xrow = _lanes(NET, XROW, num_lanes, BL)
    h, i, o = tl.arange(0, HP), tl.arange(0, NIP), tl.arange(0, NOP)
    wi = _tile(WI, net, ok, h, i, H, NI)
    wr = _tile(WR, net, ok, h, h, H, H)
    wo = _tile(WO, net, ok, o, h, NO, H)
    bc, eps = _row(BC, net, ok, h, H), _row(EPS, net, ok, h, H)
    bo = _row(BO, net, ok, o, NO)
    u = _row(U0, tl.load(U0ROW + lane, mask=ok, other=0), ok, h, H)
    c = _tanh(u + bc)
    s1, s2 = u, u * u
    for t in range(T):
        x = _row(X, xrow * T + t, ok, i, NI)
        u = u + eps * (_matvec(wi, x) + _matvec(wr, c) - u)
        c = _tanh(u + bc)
        if KEEP_SUMS:
            s1 += u
            s2 += u * u
        if KEEP_C:
            _put(C, lane * T + t, ok, h, c, H)
        if KEEP_U:
            _put(U, lane * T + t, ok, h, u, H)
        _put(OUT, lane * T + t, ok, o, _matvec(wo, c) + bo, NO)
    if KEEP_SUMS:
        _put(SUMS, lane * 2, ok, h, s1, H)
        _put(SUMS, lane * 2 + 1, ok, h, s2, H)


@triton.jit
def rnn_backward(DO, X, XROW, NET, U0ROW, WI, WR, WO, BC, EPS, U0, C, U,
                 G_WI, G_WR, G_WO, G_BC, G_BO, G_EPS, G_U0, num_lanes,
                 T: tl.constexpr, NI: tl.constexpr, H: tl.constexpr, NO: tl.constexpr,
                 NIP: tl.constexpr, HP: tl.constexpr, NOP: tl.constexpr, BL: tl.constexpr,
                 LEARN_EPS: tl.constexpr):
    """Backward pass of BL lanes given DO (L, T, NO) = ∂L/∂o_t: every per-lane gradient,
    G_WI (L, H, NI), G_WR (L, H, H), G_WO (L, NO, H), G_BC, G_EPS, G_U0 (L, H), G_BO (L, NO)
    (G_EPS only when LEARN_EPS; it then reads U)."""
    lane, ok, net, xrow = _lanes(NET, XROW, num_lanes, BL)
    h, i, o = tl.arange(0, HP), tl.arange(0, NIP), tl.arange(0, NOP)
    wr = _tile(WR, net, ok, h, h, H, H)
    wo = _tile(WO, net, ok, o, h, NO, H)
    bc, eps = _row(BC, net, ok, h, H), _row(EPS, net, ok, h, H)
    u0 = _row(U0, tl.load(U0ROW + lane, mask=ok, other=0), ok, h, H)
    c0 = _tanh(u0 + bc)
    zero_h = tl.zeros((BL, HP), dtype=bc.dtype)
    a, back, gbc, geps = zero_h, zero_h, zero_h, zero_h
    gwi = tl.zeros((BL, HP, NIP), dtype=bc.dtype)
    gwr = tl.zeros((BL, HP, HP), dtype=bc.dtype)
    gwo = tl.zeros((BL, NOP, HP), dtype=bc.dtype)
    gbo = tl.zeros((BL, NOP), dtype=bc.dtype)
    for step in range(T):
        t = T - 1 - step
        c = _row(C, lane * T + t, ok, h, H)
        first = t == 0
        before = ok & (lane * 0 + t > 0)  # a step before t exists (a tensor: a mask's type)
        prev = tl.where(first, c0, _row(C, lane * T + t - 1, before, h, H))
        do = _row(DO, lane * T + t, ok, o, NO)
        dq = (1.0 - c * c) * (_matvec_t(wo, do) + back)
        gbc += dq
        a = (1.0 - eps) * a + dq
        ea = eps * a
        gbo += do
        gwo += do[:, :, None] * c[:, None, :]
        gwi += ea[:, :, None] * _row(X, xrow * T + t, ok, i, NI)[:, None, :]
        gwr += ea[:, :, None] * prev[:, None, :]
        if LEARN_EPS:
            u = _row(U, lane * T + t, ok, h, H)
            u_prev = tl.where(first, u0, _row(U, lane * T + t - 1, before, h, H))
            geps += a * (u - u_prev) / tl.where(eps != 0.0, eps, 1.0)  # padding: ε = 0
        back = _matvec_t(wr, ea)
    dq = (1.0 - c0 * c0) * back
    _put(G_BC, lane, ok, h, gbc + dq, H)
    _put(G_U0, lane, ok, h, (1.0 - eps) * a + dq, H)
    _put(G_EPS, lane, ok, h, geps, H)
    _put(G_BO, lane, ok, o, gbo, NO)
    _put_tile(G_WI, lane, ok, h, i, gwi, H, NI)
    _put_tile(G_WR, lane, ok, h, h, gwr, H, H)
    _put_tile(G_WO, lane, ok, o, h, gwo, NO, H)
