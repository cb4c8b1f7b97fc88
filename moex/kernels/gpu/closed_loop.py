"""The closed loop of the whole mixture (Sec. 2.2) with KT Lyapunov tangent vectors, as one Triton
kernel: `moex.model.closed_loop_step` and its tangent map, repeated for a chunk of steps.

A program runs one run's network for a block of samples through every step of the chunk, so the
weights are one copy per program (no lane axis); the products with W_rec and W_out (experts and
gating, and the tangent map's) go by columns, as in `moex.kernels.gpu.rnn`: the vector is written
to the lane's scratch row, one barrier, and each column updates the accumulators with a column of
the weights read from memory (no sum across threads; c_t serves both the output at t and the
recurrence at t + 1). A lane is one (sample, tangent) pair: BN lanes =
BN / KTP samples × KTP tangent slots, each lane carrying its sample's state (computed once per
slot, so the state's arithmetic repeats KTP times: the price of keeping the tangent map the
one-vector code) and one tangent. Shapes inside: experts (BN, K, M), gating (BN, H), delay lines
x (BN, τ, D) and g (BN, τ, K); sizes padded to powers of two (masked: padded units stay 0, padded
gates get logit -inf, padded tangent slots stay 0).

One step (m is the gating RNN's time), with x_m = x-line[0] (+ noise) and g_m = g-line[0]:
    experts:  u_k ← u_k + ε (W_in x_m + W_rec tanh(u_k + b) - u_k),  y^k = tanh(W_out c_k + b_o),
              y_m = Σ_k g_m^k y^k                                               (Eqs. 1-4)
    gating:   u^g ← u^g + ε^g (W^g_1 g_m + W^g_2 x_m + W^g_3 tanh(u^g + v^g_1) - u^g),
              g_{m+τ} = softmax(W^g_4 c^g + v^g_2)                              (Eqs. 5-8)
    delay lines shift by one; y_m and g_{m+τ} enter at the end.
The tangents follow the exact Jacobian of the same map (written out as in `closed_loop_step`) and
are re-orthonormalised after every step by modified Gram-Schmidt among the slots of a sample (a
QR decomposition); ln |R_ii| is tangent i's growth (Benettin et al. 1980).
"""

import torch
import triton
import triton.language as tl

from moex.kernels.gpu.lanes import CLOSED_LOOP_BUDGET, OPTIONS, launched, pow2
from moex.kernels.gpu.rnn import UNROLL, device, divide, exp, log, reciprocal, stable_tanh
from moex.model import ClosedLoopRun

CLOSED_LOOP_WARPS = 8  # with `CLOSED_LOOP_BUDGET`'s lanes: no spill at Table 2 (4 warps: 12-64 B)


@device
def _first(line, tt):
    """Entry 0 of a delay line (BN, TP, C) -> (BN, C)."""
    return tl.sum(tl.where((tt == 0)[None, :, None], line, 0.0), axis=1)


@device
def _shift(line, new, tt, TAU: tl.constexpr):
    """The delay line moved one step: entries 1..τ-1 to 0..τ-2, `new` (BN, C) into τ-1."""
    move = ((tt[:, None] + 1) == tt[None, :]).to(line.dtype)  # (TP out, TP in)
    moved = tl.sum(move[None, :, :, None] * line[:, None, :, :], axis=2)
    return tl.where((tt == TAU - 1)[None, :, None], new[:, None, :], moved)


@device
def _orthonormalise(veu, vgu, vxl, vgl, growth, SB: tl.constexpr, KT: tl.constexpr,
                    KTP: tl.constexpr, KP: tl.constexpr, MP: tl.constexpr, HP: tl.constexpr,
                    TP: tl.constexpr, DP: tl.constexpr, COUNT: tl.constexpr):
    """Modified Gram-Schmidt among the KT tangent slots of each sample (the pieces of one
    vector: veu (BN, KP, MP), vgu (BN, HP), vxl (BN, TP, DP), vgl (BN, TP, KP) with BN = SB·KTP
    lanes); growth (SB, KTP) += ln of each vector's norm after the earlier ones were removed
    (|R_ii| of the QR decomposition). A zero vector (a padded lane) is left zero."""
    e = tl.reshape(veu, (SB, KTP, KP, MP))
    g = tl.reshape(vgu, (SB, KTP, HP))
    x = tl.reshape(vxl, (SB, KTP, TP, DP))
    q = tl.reshape(vgl, (SB, KTP, TP, KP))
    slot = tl.arange(0, KTP)
    for i in tl.static_range(KT):
        this = (slot == i)[None, :]  # (1, KTP)
        this3, this4 = this[:, :, None], this[:, :, None, None]
        e_i = tl.sum(tl.where(this4, e, 0.0), axis=1)  # vector i, (SB, ...)
        g_i = tl.sum(tl.where(this3, g, 0.0), axis=1)
        x_i = tl.sum(tl.where(this4, x, 0.0), axis=1)
        q_i = tl.sum(tl.where(this4, q, 0.0), axis=1)
        norm = tl.sqrt(tl.sum(tl.sum(e_i * e_i, axis=2), axis=1) + tl.sum(g_i * g_i, axis=1)
                       + tl.sum(tl.sum(x_i * x_i, axis=2), axis=1)
                       + tl.sum(tl.sum(q_i * q_i, axis=2), axis=1))
        safe = tl.where(norm > 0, norm, 1.0)
        if COUNT:
            growth += tl.where(this, log(safe)[:, None], 0.0)
        scale = reciprocal(safe)
        e_i, g_i = e_i * scale[:, None, None], g_i * scale[:, None]
        x_i, q_i = x_i * scale[:, None, None], q_i * scale[:, None, None]
        # every later vector loses its component along vector i; vector i is replaced by its unit
        dot = (tl.sum(tl.sum(e * e_i[:, None], axis=3), axis=2) + tl.sum(g * g_i[:, None], axis=2)
               + tl.sum(tl.sum(x * x_i[:, None], axis=3), axis=2)
               + tl.sum(tl.sum(q * q_i[:, None], axis=3), axis=2))  # (SB, KTP)
        dot = tl.where((slot > i)[None, :], dot, 0.0)
        e = tl.where(this4, e_i[:, None], e - dot[:, :, None, None] * e_i[:, None])
        g = tl.where(this3, g_i[:, None], g - dot[:, :, None] * g_i[:, None])
        x = tl.where(this4, x_i[:, None], x - dot[:, :, None, None] * x_i[:, None])
        q = tl.where(this4, q_i[:, None], q - dot[:, :, None, None] * q_i[:, None])
    return (tl.reshape(e, (SB * KTP, KP, MP)), tl.reshape(g, (SB * KTP, HP)),
            tl.reshape(x, (SB * KTP, TP, DP)), tl.reshape(q, (SB * KTP, TP, KP)), growth)


@device
def _load(ptr, offs, mask):
    return tl.load(ptr + offs, mask=mask, other=0.0)


@device
def _expert_columns(acc, out, EC, base, v, W, w_at, w_ok, WO, wo_at, wo_ok, k, m, lanes_k,
                    v_ok, M: tl.constexpr, MP: tl.constexpr, REC: tl.constexpr,
                    OUT: tl.constexpr):
    """acc + W v (REC) and out + W_out v (OUT) for every lane's K expert vectors v (BN, KP, MP),
    by columns: v is written to the lane's scratch row EC[base ...], one barrier, then each
    column v_j (BN, KP) updates the (BN, KP, ·) accumulators with column j of the weights, read
    from memory (W at w_at + j, W_out at wo_at + j). No sum runs across threads."""
    tl.store(EC + base[:, None, None] + (k * MP)[None, :, None] + m[None, None, :], v,
             mask=v_ok)
    tl.debug_barrier()
    for col in tl.range(0, M, loop_unroll_factor=UNROLL):
        v_j = tl.load(EC + base[:, None] + (k * MP)[None, :] + col, mask=lanes_k, other=0.0)
        if REC:
            acc += v_j[:, :, None] * tl.load(W + w_at + col, mask=w_ok, other=0.0)[None]
        if OUT:
            out += v_j[:, :, None] * tl.load(WO + wo_at + col, mask=wo_ok, other=0.0)[None]
    return acc, out


@device
def _gating_columns(acc, out, GC, base, v, W, w_at, w_ok, WO, wo_at, wo_ok, h, lanes, v_ok,
                    H: tl.constexpr, REC: tl.constexpr, OUT: tl.constexpr):
    """acc + W v (REC) and out + W_out v (OUT) for every lane's gating vector v (BN, HP), by
    columns through the lane's scratch row GC[base ...], as `_expert_columns`."""
    tl.store(GC + base[:, None] + h[None, :], v, mask=v_ok)
    tl.debug_barrier()
    for col in tl.range(0, H, loop_unroll_factor=UNROLL):
        v_j = tl.load(GC + base + col, mask=lanes, other=0.0)[:, None]
        if REC:
            acc += v_j * tl.load(W + w_at + col, mask=w_ok, other=0.0)[None, :]
        if OUT:
            out += v_j * tl.load(WO + wo_at + col, mask=wo_ok, other=0.0)[None, :]
    return acc, out


@triton.jit(do_not_specialize=["N", "STEPS"])  # one compile whatever the chunk and samples
def closed_loop_kernel(E_W_IN, E_W_REC, E_W_OUT, E_B_C, E_B_O, E_EPS,
                       G_W_IN, G_W_REC, G_W_OUT, G_B_C, G_B_O, G_EPS,
                       EU, GU, XL, GL, VEU, VGU, VXL, VGL, NOISE, OUT_Y, OUT_G, OUT_U, GROWTH,
                       EC, GC, N, STEPS, K: tl.constexpr, M: tl.constexpr, D: tl.constexpr,
                       H: tl.constexpr, TAU: tl.constexpr, KP: tl.constexpr, MP: tl.constexpr,
                       DP: tl.constexpr, HP: tl.constexpr, TP: tl.constexpr, BN: tl.constexpr,
                       KT: tl.constexpr, KTP: tl.constexpr,
                       EXPERTS: tl.constexpr, TANGENT: tl.constexpr, NOISY: tl.constexpr,
                       COUNT: tl.constexpr, UNIFORM: tl.constexpr, KEEP_U: tl.constexpr):
    """STEPS steps of BN / KTP trajectories of run program_id(0); the state (EU (R, N, K, M), GU
    (R, N, H), XL (R, N, τ, D), GL (R, N, τ, K)) and the KT tangents (VEU (R, N, KT, K, M), VGU
    (R, N, KT, H), VXL (R, N, KT, τ, D), VGL (R, N, KT, τ, K)) are read and written back; records
    OUT_Y (R, N, STEPS, D), OUT_G (R, N, STEPS, K), OUT_U (R, N, STEPS, H) when KEEP_U; GROWTH
    (R, N, KT) += Σ ln |R_ii| when COUNT. EC (programs·BN, 3, KP, MP) and GC (programs·BN, 3,
    HP): each lane's scratch rows for the products by columns (the state's, and the tangent's
    before and after the update)."""
    r = tl.program_id(0).to(tl.int64)
    lane = tl.arange(0, BN)
    n, j = tl.program_id(1) * (BN // KTP) + lane // KTP, lane % KTP  # sample, tangent slot
    ok = n < N
    first = ok & (j == 0)  # the lane that writes its sample's state and records
    row = r * N + n  # (BN,) trajectory index
    trow = row * KT + j  # (BN,) tangent index
    tok = ok & (j < KT)
    slot = (r * tl.num_programs(1) + tl.program_id(1)) * BN + lane  # the lane's scratch rows
    e_base, g_base = slot * (3 * KP * MP), slot * (3 * HP)
    k, m, d = tl.arange(0, KP), tl.arange(0, MP), tl.arange(0, DP)
    h, tt = tl.arange(0, HP), tl.arange(0, TP)
    km, dm, hm, tm = k < K, d < D, h < H, tt < TAU
    mm = m < M
    # ---- the run's weights: the small ones in registers, W_rec and W_out read by columns
    k3, m3 = k[:, None, None], m[None, :, None]
    e_w_in = _load(E_W_IN, r * K * M * D + k3 * M * D + m3 * D + d[None, None, :],
                   km[:, None, None] & mm[None, :, None] & dm[None, None, :])
    e_km = km[:, None] & mm[None, :]
    e_rec_at = r * K * M * M + k[:, None] * M * M + m[None, :] * M  # + column j
    e_out_at = r * K * D * M + k[:, None] * D * M + d[None, :] * M
    e_kd = km[:, None] & dm[None, :]
    e_b_c = _load(E_B_C, r * K * M + k[:, None] * M + m[None, :], e_km)
    e_eps = _load(E_EPS, r * K * M + k[:, None] * M + m[None, :], e_km)
    e_b_o = _load(E_B_O, r * K * D + k[:, None] * D + d[None, :], e_kd)
    NI = K + D
    gwg = _load(G_W_IN, r * H * NI + h[:, None] * NI + k[None, :], hm[:, None] & km[None, :])
    gwx = _load(G_W_IN, r * H * NI + h[:, None] * NI + K + d[None, :], hm[:, None] & dm[None, :])
    g_rec_at, g_out_at = r * H * H + h * H, r * K * H + k * H
    g_b_c, g_eps = _load(G_B_C, r * H + h, hm), _load(G_EPS, r * H + h, hm)
    g_b_o = _load(G_B_O, r * K + k, km)
    # ---- the state of each trajectory
    ok3 = ok[:, None, None]
    e_off = row[:, None, None] * K * M + k[None, :, None] * M + m[None, None, :]
    e_mask = ok3 & e_km[None]
    g_off, g_mask = row[:, None] * H + h[None, :], ok[:, None] & hm[None, :]
    x_off = row[:, None, None] * TAU * D + tt[None, :, None] * D + d[None, None, :]
    x_mask = ok3 & tm[None, :, None] & dm[None, None, :]
    l_off = row[:, None, None] * TAU * K + tt[None, :, None] * K + k[None, None, :]
    l_mask = ok3 & tm[None, :, None] & km[None, None, :]
    eu, gu = _load(EU, e_off, e_mask), _load(GU, g_off, g_mask)
    xl, gl = _load(XL, x_off, x_mask), _load(GL, l_off, l_mask)
    if TANGENT:  # the state's layouts, indexed by tangent (trow) instead of trajectory (row)
        tok3 = tok[:, None, None]
        v_e = trow[:, None, None] * K * M + k[None, :, None] * M + m[None, None, :]
        v_x = trow[:, None, None] * TAU * D + tt[None, :, None] * D + d[None, None, :]
        v_l = trow[:, None, None] * TAU * K + tt[None, :, None] * K + k[None, None, :]
        v_em, v_g = tok3 & e_km[None], trow[:, None] * H + h[None, :]
        v_gm = tok[:, None] & hm[None, :]
        v_xm = tok3 & tm[None, :, None] & dm[None, None, :]
        v_lm = tok3 & tm[None, :, None] & km[None, None, :]
        veu, vgu = _load(VEU, v_e, v_em), _load(VGU, v_g, v_gm)
        vxl, vgl = _load(VXL, v_x, v_xm), _load(VGL, v_l, v_lm)
        growth = tl.zeros((BN // KTP, KTP), dtype=g_b_c.dtype)
    rec_d, rec_k = first[:, None] & dm[None, :], first[:, None] & km[None, :]
    e_scr = ok3 & e_km[None]  # the scratch entries a lane writes (all its rows exist)
    g_scr = ok[:, None] & hm[None, :]
    zero_e, zero_g = tl.zeros_like(eu), tl.zeros_like(gu)
    zero_o = tl.zeros((BN, KP, DP), dtype=eu.dtype)
    zero_l = tl.zeros((BN, KP), dtype=eu.dtype)
    # W_rec c_{-1} and W^g_3 c^g_{-1}, by columns: each step then adds the next ones
    lanes_k = ok[:, None] & km[None, :]
    if EXPERTS:
        c_old = stable_tanh(eu + e_b_c[None])
        rec, _unused = _expert_columns(zero_e, zero_o, EC, e_base, c_old, E_W_REC, e_rec_at,
                                       e_km, E_W_OUT, e_out_at, e_kd, k, m, lanes_k, e_scr, M, MP,
                                       True, False)
    cg_old = stable_tanh(gu + g_b_c[None])
    grec, _unused_g = _gating_columns(zero_g, zero_l, GC, g_base, cg_old, G_W_REC, g_rec_at, hm,
                                      G_W_OUT, g_out_at, km, h, ok, g_scr, H, True, False)
    for t in range(STEPS):
        x, g = _first(xl, tt), _first(gl, tt)
        if NOISY:
            x += _load(NOISE, (row[:, None] * STEPS + t) * D + d[None, :],
                       ok[:, None] & dm[None, :])
        y = x
        if EXPERTS:  # Eqs. 1-4, every expert on the same input
            drive = tl.sum(e_w_in[None] * x[:, None, None, :], axis=3)
            eu_new = eu + e_eps[None] * (drive + rec - eu)
            c = stable_tanh(eu_new + e_b_c[None])
            rec, o = _expert_columns(zero_e, zero_o + e_b_o[None], EC, e_base, c, E_W_REC, e_rec_at,
                                     e_km, E_W_OUT, e_out_at, e_kd, k, m, lanes_k, e_scr, M, MP,
                                     True, True)
            out = stable_tanh(o)  # (BN, KP, DP)
            y = tl.sum(g[:, :, None] * out, axis=1)
        # Eqs. 5-8: the gating RNN reads (g_m, x_m) and emits g_{m+τ}
        drive_g = tl.sum(gwg[None] * g[:, None, :], axis=2) + tl.sum(gwx[None] * x[:, None, :],
                                                                     axis=2)
        gu_new = gu + g_eps[None] * (drive_g + grec - gu)
        cg = stable_tanh(gu_new + g_b_c[None])
        grec, logits = _gating_columns(zero_g, zero_l + g_b_o[None], GC, g_base, cg, G_W_REC,
                                       g_rec_at, hm, G_W_OUT, g_out_at, km, h, ok, g_scr, H, True,
                                       True)
        logits = tl.where(km[None, :], logits, float("-inf"))
        e = exp(logits - tl.max(logits, axis=1)[:, None])
        new_g = divide(e, tl.sum(e, axis=1)[:, None])
        tl.store(OUT_Y + (row[:, None] * STEPS + t) * D + d[None, :], y, mask=rec_d)
        tl.store(OUT_G + (row[:, None] * STEPS + t) * K + k[None, :], g, mask=rec_k)
        if KEEP_U:
            tl.store(OUT_U + (row[:, None] * STEPS + t) * H + h[None, :], gu_new,
                     mask=first[:, None] & hm[None, :])
        if TANGENT:  # the exact Jacobian of the same step applied to v
            dx, dg = _first(vxl, tt), _first(vgl, tt)
            dy = dx
            if EXPERTS:
                d_drive = tl.sum(e_w_in[None] * dx[:, None, None, :], axis=3)
                d_rec, _no_out = _expert_columns(zero_e, zero_o, EC, e_base + KP * MP,
                                           (1.0 - c_old * c_old) * veu, E_W_REC, e_rec_at, e_km,
                                           E_W_OUT, e_out_at, e_kd, k, m, lanes_k, e_scr, M, MP,
                                           True, False)
                veu = (1.0 - e_eps[None]) * veu + e_eps[None] * (d_drive + d_rec)
                _no_rec, d_o = _expert_columns(zero_e, zero_o, EC, e_base + 2 * KP * MP,
                                         (1.0 - c * c) * veu, E_W_REC, e_rec_at, e_km, E_W_OUT,
                                         e_out_at, e_kd, k, m, lanes_k, e_scr, M, MP, False, True)
                d_out = (1.0 - out * out) * d_o
                if UNIFORM:  # 1/K in the state's precision (a Python 1.0 / K would be float32)
                    weight = tl.where(km[None, :], g * 0.0 + 1.0, 0.0) / K
                else:
                    weight = g
                dy = tl.sum(dg[:, :, None] * out + weight[:, :, None] * d_out, axis=1)
            d_drive_g = tl.sum(gwg[None] * dg[:, None, :], axis=2) + tl.sum(
                gwx[None] * dx[:, None, :], axis=2)
            d_rec_g, _no_out_g = _gating_columns(zero_g, zero_l, GC, g_base + HP,
                                         (1.0 - cg_old * cg_old) * vgu, G_W_REC, g_rec_at, hm,
                                         G_W_OUT, g_out_at, km, h, ok, g_scr, H, True, False)
            vgu = (1.0 - g_eps[None]) * vgu + g_eps[None] * (d_drive_g + d_rec_g)
            _no_rec_g, d_logits = _gating_columns(zero_g, zero_l, GC, g_base + 2 * HP,
                                          (1.0 - cg * cg) * vgu, G_W_REC, g_rec_at, hm, G_W_OUT,
                                          g_out_at, km, h, ok, g_scr, H, False, True)
            d_g = new_g * (d_logits - tl.sum(new_g * d_logits, axis=1)[:, None])
            vxl, vgl = _shift(vxl, dy, tt, TAU), _shift(vgl, d_g, tt, TAU)
            veu, vgu, vxl, vgl, growth = _orthonormalise(veu, vgu, vxl, vgl, growth, BN // KTP, KT,
                                                         KTP, KP, MP, HP, TP, DP, COUNT)
        if EXPERTS:
            eu, c_old = eu_new, c
        gu, cg_old = gu_new, cg
        xl, gl = _shift(xl, y, tt, TAU), _shift(gl, new_g, tt, TAU)
    first3 = first[:, None, None]
    tl.store(EU + e_off, eu, mask=e_mask & first3)
    tl.store(GU + g_off, gu, mask=g_mask & first[:, None])
    tl.store(XL + x_off, xl, mask=x_mask & first3)
    tl.store(GL + l_off, gl, mask=l_mask & first3)
    if TANGENT:
        tl.store(VEU + v_e, veu, mask=v_em)
        tl.store(VGU + v_g, vgu, mask=v_gm)
        tl.store(VXL + v_x, vxl, mask=v_xm)
        tl.store(VGL + v_l, vgl, mask=v_lm)
        if COUNT:
            grown = tl.load(GROWTH + trow, mask=tok, other=0.0) + tl.reshape(growth, (BN,))
            tl.store(GROWTH + trow, grown, mask=tok)


def grid(num_runs: int, num_samples: int, block: int) -> tuple[int, int]:
    return num_runs, triton.cdiv(num_samples, block)


_NET = ("w_in", "w_rec", "w_out", "b_c", "b_o")


def closed_loop(experts, gating, state, steps: int, *, noise=None, tangents=None,
                count: bool = False, uniform_gates: bool = False,
                potentials: bool = True, device: str = "cpu") -> ClosedLoopRun:
    """`moex.kernels.reference.closed_loop` as one kernel launch: same arguments and results (on
    the device of `state`)."""
    num_tangents = 0 if tangents is None else tangents.shape[-1]
    device = torch.device(device)
    home, dtype = state.gates.device, state.gates.dtype
    R, N, TAU, K = state.gates.shape
    D, H = state.inputs.shape[-1], state.gating_u.shape[-1]
    M = state.experts_u.shape[-1] if experts else 0
    dummy = torch.zeros(1, dtype=dtype, device=device)

    def put(x):  # a contiguous copy on the device (kernels write into some of them)
        x = x.detach().to(device=device, dtype=dtype).contiguous().clone()
        return x if x.numel() else dummy

    def weights(net):
        if not net:
            return [dummy] * 6
        return [put(net[n]) for n in _NET] + [put(1 / net["tau"])]

    parts = [put(x) for x in (state.experts_u, state.gating_u, state.inputs, state.gates)]
    sizes = [K * M, H, TAU * D, TAU * K]
    # tangents (R, N, dim, KT) -> per piece (R, N, KT, size): one vector's piece is contiguous
    vec = ([put(p.transpose(-1, -2)) for p in tangents.split(sizes, dim=-2)] if num_tangents
           else [dummy] * 4)
    out_y = torch.zeros((R, N, steps, D), dtype=dtype, device=device)
    out_g = torch.zeros((R, N, steps, K), dtype=dtype, device=device)
    out_u = torch.zeros((R, N, steps, H), dtype=dtype, device=device) if potentials else dummy
    growth = torch.zeros((R, N, num_tangents), dtype=dtype, device=device)
    pad = {name: pow2(size) for name, size in (("KP", K), ("MP", M), ("DP", D), ("HP", H),
                                                 ("TP", TAU), ("KTP", num_tangents))}
    # the largest tiles per lane: the experts' (KP, MP) state and their W_in x, (KP, MP, DP)
    per_lane = max(pad["KP"] * pad["MP"] * pad["DP"], pad["HP"] * max(pad["KP"], pad["DP"]))
    # lanes per program: no spill at Table 2 in the compile for an H200 with 8 warps (4 samples;
    # 16 spilled 1.2 KB), BENCHMARKS.md "Compiled for an H200 without one"
    samples = max(1, min(16, CLOSED_LOOP_BUDGET // (per_lane * pad["KTP"])))
    lanes = R * triton.cdiv(N, samples) * samples * pad["KTP"]  # scratch rows, one per lane
    scratch_e = torch.empty(lanes * 3 * pad["KP"] * pad["MP"], dtype=dtype, device=device)
    scratch_g = torch.empty(lanes * 3 * pad["HP"], dtype=dtype, device=device)
    launched("closed_loop", closed_loop_kernel[grid(R, N, samples)](
        *weights(experts), *weights(gating), *parts, *vec,
        put(noise) if noise is not None else dummy, out_y, out_g, out_u, growth, scratch_e,
        scratch_g, N,
        STEPS=steps, K=K, M=M, D=D, H=H, TAU=TAU, BN=samples * pad["KTP"],
        KT=max(num_tangents, 1), EXPERTS=bool(experts), TANGENT=bool(num_tangents),
        NOISY=noise is not None, COUNT=bool(count and num_tangents),
        UNIFORM=bool(uniform_gates), KEEP_U=bool(potentials), **pad, **OPTIONS,
        num_warps=CLOSED_LOOP_WARPS))

    def back(x, shape):
        """x as `shape` where the state came from; to the host through pinned memory (a
        chunk's records at Table 2's scale, 72 MB, took 43 ms from pageable memory on an H200,
        1.7x the kernel; pinned memory copies at the bus's rate)."""
        if x is dummy:
            return torch.zeros(shape, dtype=dtype)
        if home.type == "cpu" and x.is_cuda:
            out = torch.empty(shape, dtype=dtype, pin_memory=True)
            return out.copy_(x.reshape(shape))
        return x.reshape(shape).to(home)

    nxt = type(state)(back(parts[0], state.experts_u.shape), back(parts[1], (R, N, H)),
                      back(parts[2], (R, N, TAU, D)), back(parts[3], (R, N, TAU, K)))
    new_tangents = None
    if num_tangents:
        new_tangents = torch.cat([back(v, (R, N, num_tangents, size)).transpose(-1, -2)
                                  for v, size in zip(vec, sizes, strict=True)], -2)
    return ClosedLoopRun(nxt, back(out_y, (R, N, steps, D)), back(out_g, (R, N, steps, K)),
                         back(out_u, (R, N, steps, H)) if potentials else None, new_tangents,
                         growth.to(home))
