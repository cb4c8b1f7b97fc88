"""The closed loop of the whole mixture (Sec. 2.2) with KT Lyapunov tangent vectors, as one Triton
kernel: `moex.model.closed_loop_step` and its tangent map, repeated for a chunk of steps.

A program runs one run's network for a block of samples through every step of the chunk, so the
weights are one copy per program (no lane axis). A lane is one (sample, tangent) pair: BN lanes =
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

import triton
import triton.language as tl

from moex.kernels.gpu_rnn import _tanh


@triton.jit
def _first(line, tt):
    """Entry 0 of a delay line (BN, TP, C) -> (BN, C)."""
    return tl.sum(tl.where((tt == 0)[None, :, None], line, 0.0), axis=1)


@triton.jit
def _shift(line, new, tt, TAU: tl.constexpr):
    """The delay line moved one step: entries 1..τ-1 to 0..τ-2, `new` (BN, C) into τ-1."""
    move = ((tt[:, None] + 1) == tt[None, :]).to(line.dtype)  # (TP out, TP in)
    moved = tl.sum(move[None, :, :, None] * line[:, None, :, :], axis=2)
    return tl.where((tt == TAU - 1)[None, :, None], new[:, None, :], moved)


@triton.jit
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
            growth += tl.where(this, tl.log(safe)[:, None], 0.0)
        scale = 1.0 / safe
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


@triton.jit
def _load(ptr, offs, mask):
    return tl.load(ptr + offs, mask=mask, other=0.0)


@triton.jit
def closed_loop_kernel(EWI, EWR, EWO, EBC, EBO, EEPS, GWI, GWR, GWO, GBC, GBO, GEPS,
                       EU, GU, XL, GL, VEU, VGU, VXL, VGL, NOISE, OUT_Y, OUT_G, OUT_U, GROWTH, N,
                       STEPS: tl.constexpr, K: tl.constexpr, M: tl.constexpr, D: tl.constexpr,
                       H: tl.constexpr, TAU: tl.constexpr, KP: tl.constexpr, MP: tl.constexpr,
                       DP: tl.constexpr, HP: tl.constexpr, TP: tl.constexpr, BN: tl.constexpr,
                       KT: tl.constexpr, KTP: tl.constexpr,
                       EXPERTS: tl.constexpr, TANGENT: tl.constexpr, NOISY: tl.constexpr,
                       COUNT: tl.constexpr, UNIFORM: tl.constexpr, KEEP_U: tl.constexpr):
    """STEPS steps of BN / KTP trajectories of run program_id(0); the state (EU (R, N, K, M), GU
    (R, N, H), XL (R, N, τ, D), GL (R, N, τ, K)) and the KT tangents (VEU (R, N, KT, K, M), VGU
    (R, N, KT, H), VXL (R, N, KT, τ, D), VGL (R, N, KT, τ, K)) are read and written back; records
    OUT_Y (R, N, STEPS, D), OUT_G (R, N, STEPS, K), OUT_U (R, N, STEPS, H) when KEEP_U; GROWTH
    (R, N, KT) += Σ ln |R_ii| when COUNT."""
    r = tl.program_id(0).to(tl.int64)
    lane = tl.arange(0, BN)
    n, j = tl.program_id(1) * (BN // KTP) + lane // KTP, lane % KTP  # sample, tangent slot
    ok = n < N
    first = ok & (j == 0)  # the lane that writes its sample's state and records
    row = r * N + n  # (BN,) trajectory index
    trow = row * KT + j  # (BN,) tangent index
    tok = ok & (j < KT)
    k, m, d = tl.arange(0, KP), tl.arange(0, MP), tl.arange(0, DP)
    h, tt = tl.arange(0, HP), tl.arange(0, TP)
    km, dm, hm, tm = k < K, d < D, h < H, tt < TAU
    mm = m < M
    # ---- the run's weights: experts (KP, ...), gating (HP, ...)
    k3, m3 = k[:, None, None], m[None, :, None]
    ewi = _load(EWI, r * K * M * D + k3 * M * D + m3 * D + d[None, None, :],
                km[:, None, None] & mm[None, :, None] & dm[None, None, :])
    ewr = _load(EWR, r * K * M * M + k3 * M * M + m3 * M + m[None, None, :],
                km[:, None, None] & mm[None, :, None] & mm[None, None, :])
    ewo = _load(EWO, r * K * D * M + k3 * D * M + d[None, :, None] * M + m[None, None, :],
                km[:, None, None] & dm[None, :, None] & mm[None, None, :])
    e_km = km[:, None] & mm[None, :]
    ebc = _load(EBC, r * K * M + k[:, None] * M + m[None, :], e_km)
    eeps = _load(EEPS, r * K * M + k[:, None] * M + m[None, :], e_km)
    ebo = _load(EBO, r * K * D + k[:, None] * D + d[None, :], km[:, None] & dm[None, :])
    NI = K + D
    gwg = _load(GWI, r * H * NI + h[:, None] * NI + k[None, :], hm[:, None] & km[None, :])
    gwx = _load(GWI, r * H * NI + h[:, None] * NI + K + d[None, :], hm[:, None] & dm[None, :])
    gwr = _load(GWR, r * H * H + h[:, None] * H + h[None, :], hm[:, None] & hm[None, :])
    gwo = _load(GWO, r * K * H + k[:, None] * H + h[None, :], km[:, None] & hm[None, :])
    gbc, geps = _load(GBC, r * H + h, hm), _load(GEPS, r * H + h, hm)
    gbo = _load(GBO, r * K + k, km)
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
        growth = tl.zeros((BN // KTP, KTP), dtype=gbc.dtype)
    rec_d, rec_k = first[:, None] & dm[None, :], first[:, None] & km[None, :]
    for t in range(STEPS):
        x, g = _first(xl, tt), _first(gl, tt)
        if NOISY:
            x += _load(NOISE, (row[:, None] * STEPS + t) * D + d[None, :],
                       ok[:, None] & dm[None, :])
        y = x
        if EXPERTS:  # Eqs. 1-4, every expert on the same input
            c_old = _tanh(eu + ebc[None])
            drive = tl.sum(ewi[None] * x[:, None, None, :], axis=3)
            eu_new = eu + eeps[None] * (drive + tl.sum(ewr[None] * c_old[:, :, None, :], axis=3)
                                        - eu)
            c = _tanh(eu_new + ebc[None])
            out = _tanh(tl.sum(ewo[None] * c[:, :, None, :], axis=3) + ebo[None])  # (BN, KP, DP)
            y = tl.sum(g[:, :, None] * out, axis=1)
        # Eqs. 5-8: the gating RNN reads (g_m, x_m) and emits g_{m+τ}
        cg_old = _tanh(gu + gbc[None])
        drive_g = tl.sum(gwg[None] * g[:, None, :], axis=2) + tl.sum(gwx[None] * x[:, None, :],
                                                                     axis=2)
        gu_new = gu + geps[None] * (drive_g + tl.sum(gwr[None] * cg_old[:, None, :], axis=2)
                                    - gu)
        cg = _tanh(gu_new + gbc[None])
        logits = tl.sum(gwo[None] * cg[:, None, :], axis=2) + gbo[None]
        logits = tl.where(km[None, :], logits, float("-inf"))
        e = tl.exp(logits - tl.max(logits, axis=1)[:, None])
        new_g = e / tl.sum(e, axis=1)[:, None]
        tl.store(OUT_Y + (row[:, None] * STEPS + t) * D + d[None, :], y, mask=rec_d)
        tl.store(OUT_G + (row[:, None] * STEPS + t) * K + k[None, :], g, mask=rec_k)
        if KEEP_U:
            tl.store(OUT_U + (row[:, None] * STEPS + t) * H + h[None, :], gu_new,
                     mask=first[:, None] & hm[None, :])
        if TANGENT:  # the exact Jacobian of the same step applied to v
            dx, dg = _first(vxl, tt), _first(vgl, tt)
            dy = dx
            if EXPERTS:
                d_drive = tl.sum(ewi[None] * dx[:, None, None, :], axis=3)
                d_rec = tl.sum(ewr[None] * ((1.0 - c_old * c_old) * veu)[:, :, None, :], axis=3)
                veu = (1.0 - eeps[None]) * veu + eeps[None] * (d_drive + d_rec)
                d_out = (1.0 - out * out) * tl.sum(
                    ewo[None] * ((1.0 - c * c) * veu)[:, :, None, :], axis=3)
                if UNIFORM:  # 1/K in the state's precision (a Python 1.0 / K would be float32)
                    weight = tl.where(km[None, :], g * 0.0 + 1.0, 0.0) / K
                else:
                    weight = g
                dy = tl.sum(dg[:, :, None] * out + weight[:, :, None] * d_out, axis=1)
            d_drive_g = tl.sum(gwg[None] * dg[:, None, :], axis=2) + tl.sum(
                gwx[None] * dx[:, None, :], axis=2)
            d_rec_g = tl.sum(gwr[None] * ((1.0 - cg_old * cg_old) * vgu)[:, None, :], axis=2)
            vgu = (1.0 - geps[None]) * vgu + geps[None] * (d_drive_g + d_rec_g)
            d_logits = tl.sum(gwo[None] * ((1.0 - cg * cg) * vgu)[:, None, :], axis=2)
            d_g = new_g * (d_logits - tl.sum(new_g * d_logits, axis=1)[:, None])
            vxl, vgl = _shift(vxl, dy, tt, TAU), _shift(vgl, d_g, tt, TAU)
            veu, vgu, vxl, vgl, growth = _orthonormalise(veu, vgu, vxl, vgl, growth, BN // KTP, KT,
                                                         KTP, KP, MP, HP, TP, DP, COUNT)
        if EXPERTS:
            eu = eu_new
        gu = gu_new
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


@triton.jit
def nearest_kernel(X, PROTO, SYM, OUT, n, P: tl.constexpr, D: tl.constexpr, PP: tl.constexpr,
                   DP: tl.constexpr, BLOCK: tl.constexpr):
    """OUT[i] = SYM[argmin_p ‖X[i] - PROTO[p]‖²] for a block of points X (n, D); ties go to the
    first prototype, as on the CPU."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    ok = i < n
    p, d = tl.arange(0, PP), tl.arange(0, DP)
    x = tl.load(X + i[:, None].to(tl.int64) * D + d[None, :], mask=ok[:, None] & (d < D)[None, :],
                other=0.0)
    proto = tl.load(PROTO + p[:, None] * D + d[None, :], mask=(p < P)[:, None] & (d < D)[None, :],
                    other=0.0)
    diff = x[:, None, :] - proto[None, :, :]
    dist = tl.where((p < P)[None, :], tl.sum(diff * diff, axis=2), float("inf"))
    best = tl.argmin(dist, axis=1, tie_break_left=True)
    tl.store(OUT + i, tl.load(SYM + best, mask=ok, other=0), mask=ok)


def grid(num_runs: int, num_samples: int, block: int) -> tuple[int, int]:
    return num_runs, triton.cdiv(num_samples, block)
