"""The leaky RNN of Eqs. 1-3 / 5-8 over one block of lanes, teacher forced: the forward pass and its
backward pass (BPTT), compiled with numba. Every array is the block's (..., LB) part
(LB = `width(X)` lanes).

Forward, per lane (T steps, H units, NI inputs, NO outputs):
    c_{-1} = tanh(u_0 + b_c),  u_t = (1-ε) u_{t-1} + ε (W_in x_t + W_rec c_{t-1}),
    c_t = tanh(u_t + b_c),     o_t = W_out c_t + b_o   (y_t = tanh(o_t) for the experts).

The sizes H, NI and NO are the lengths of the `sizes` tuples (`lanes.sizes`) where they are not
empty: constants where the kernel is compiled, so that LLVM unrolls the loops over units, inputs
and outputs and keeps a step's vectors in registers (a kernel of its own for each network size);
empty tuples leave them to the arrays' shapes (one kernel for every size, the loops at run time).

Backward, given δo_t = ∂L/∂o_t. With a_t = ∂L/∂u_t (a_T = 0) and back_t = W_recᵀ (ε ⊙ a_{t+1}),
the part of ∂L/∂c_t that flows through the next step:
    dq_t = (1 - c_t²) ⊙ (W_outᵀ δo_t + back_t)            (∂L/∂(u_t + b_c))
    a_t  = dq_t + (1 - ε) ⊙ a_{t+1}
    ∂W_out += δo_t c_tᵀ,  ∂b_o += δo_t,  ∂b_c += dq_t,
    ∂W_in += (ε ⊙ a_t) x_tᵀ,  ∂W_rec += (ε ⊙ a_t) c_{t-1}ᵀ,
    ∂ε += a_t ⊙ (W_in x_t + W_rec c_{t-1} - u_{t-1}) = a_t ⊙ (u_t - u_{t-1}) / ε,
and at the start, where c_{-1} = tanh(u_0 + b_c) feeds step 0:
    ∂u_0 = (1 - ε) ⊙ a_0 + (1 - c_{-1}²) ⊙ back_{-1},  ∂b_c += (1 - c_{-1}²) ⊙ back_{-1}.
"""

from numba import njit

from moex.kernels.cpu.simd import JIT, fma, lanes, stack, sums, tanh, typed, width


@njit(inline="always", **JIT)
def _count(known, shape):  # pragma: no cover
    """len(known) (a constant where the kernel is compiled), or `shape` where `known` is empty."""
    return len(known) if len(known) > 0 else shape


@njit(inline="always", **JIT)
def _sizes(sizes, X, w_rec, w_out):  # pragma: no cover
    """H, NI, NO: the lengths of `sizes` (constants), or where those are empty the arrays'."""
    return (_count(sizes[0], w_rec.shape[0]), _count(sizes[1], X.shape[1]),
            _count(sizes[2], w_out.shape[0]))


@njit(**JIT)
def forward_pass(X, w_in, w_rec, w_out, b_c, b_o, eps, u0, squash, C0, C, Y, U, S1, S2,
                 sizes):  # pragma: no cover
    """One block of lanes (every array is that block's (..., LB) part): Y (T, NO, LB) = tanh(o_t)
    if `squash` else o_t; C (T, H, LB), U (T, H, LB) and the sums S1, S2 (H, LB) of u and u²
    over {u_0..u_T} are filled where their arrays are not empty."""
    T, LB = X.shape[0], width(X)
    H, NI, NO = _sizes(sizes, X, w_rec, w_out)
    keep_c, keep_u, keep_sums = C.shape[0] > 0, U.shape[0] > 0, S1.shape[0] > 0
    u, c, y = stack(X, H), stack(X, H), stack(X, NO)
    flat, c_flat = y.reshape(NO * LB), c.reshape(H * LB)
    s1, s2 = sums(X, H), sums(X, H)  # float64 sums: the variance is taken by difference
    acc, acc2 = lanes(X), lanes(X)
    for i in range(H):
        for v in range(LB):
            u[i, v] = u0[i, v]
            c[i, v] = tanh(u[i, v] + b_c[i, v])
            s1[i, v] = u[i, v]
            s2[i, v] = u[i, v] * u[i, v]
        for v in range(LB):
            C0[i, v] = c[i, v]
    for t in range(T):
        for i in range(0, H, 2):  # two rows at a time: two independent chains of fma
            k = min(i + 1, H - 1)  # (an odd H computes its last row twice)
            for v in range(LB):
                acc[v] = acc2[v] = 0.0
            for d in range(NI):
                for v in range(LB):
                    acc[v] = fma(w_in[i, d, v], X[t, d, v], acc[v])
                    acc2[v] = fma(w_in[k, d, v], X[t, d, v], acc2[v])
            for j in range(H):
                for v in range(LB):
                    acc[v] = fma(w_rec[i, j, v], c[j, v], acc[v])
                    acc2[v] = fma(w_rec[k, j, v], c[j, v], acc2[v])
            for v in range(LB):  # (1 - ε) u + ε acc
                first = fma(eps[i, v], acc[v] - u[i, v], u[i, v])
                second = fma(eps[k, v], acc2[v] - u[k, v], u[k, v])
                u[i, v], u[k, v] = first, second
        for i in range(H):
            for v in range(LB):
                c[i, v] = u[i, v] + b_c[i, v]
                s1[i, v] += u[i, v]
                s2[i, v] = fma(u[i, v], u[i, v], s2[i, v])
        for q in range(H * LB):  # the tanh in a flat loop, as the outputs' below: in the loop
            c_flat[q] = tanh(c_flat[q])  # above, float32's took 5 % longer (AVX2, H = 10-15)
        if keep_c:
            for i in range(H):
                for v in range(LB):
                    C[t, i, v] = c[i, v]
        if keep_u:
            for i in range(H):
                for v in range(LB):
                    U[t, i, v] = u[i, v]
        for o in range(NO):
            for v in range(LB):
                acc[v] = b_o[o, v]
            for i in range(H):
                for v in range(LB):
                    acc[v] = fma(w_out[o, i, v], c[i, v], acc[v])
            for v in range(LB):
                y[o, v] = acc[v]
        if squash:  # one flat loop over the (NO, LB) stack array: vectorised (a tanh per
            # output stored straight into Y ran lane by lane, a quarter of the step)
            for k in range(NO * LB):
                flat[k] = tanh(flat[k])
        for o in range(NO):
            for v in range(LB):
                Y[t, o, v] = y[o, v]
    if keep_sums:
        for i in range(H):
            for v in range(LB):
                S1[i, v] = s1[i, v]
                S2[i, v] = s2[i, v]


@njit(inline="always", **JIT)
def _back_step(t, DY, C, U, u0, w_rec, w_out, eps, a, ea, back, sum_b_c, sum_eps, acc,
               learn_eps, H, NO):  # pragma: no cover
    """One step of BPTT, from t + 1 to t: a (∂L/∂u_t), ea = ε ⊙ a_t, back = W_recᵀ ea, and the
    sums of ∂b_c and ∂ε."""
    LB, one = width(a), typed(a, 1.0)
    for i in range(H):  # a_t = (1 - c_t²)(W_outᵀ δo_t + back) + (1 - ε) a_{t+1}
        for v in range(LB):
            acc[v] = back[i, v]
        for o in range(NO):
            for v in range(LB):
                acc[v] = fma(w_out[o, i, v], DY[t, o, v], acc[v])
        for v in range(LB):
            dq = fma(-C[t, i, v], C[t, i, v], one) * acc[v]
            sum_b_c[i, v] += dq
            a[i, v] = fma(one - eps[i, v], a[i, v], dq)
            ea[i, v] = eps[i, v] * a[i, v]
    if learn_eps:  # ∂u_t/∂ε = s_t - u_{t-1} = (u_t - u_{t-1}) / ε
        u_prev = U[t - 1] if t > 0 else u0
        for i in range(H):
            for v in range(LB):
                sum_eps[i, v] += a[i, v] * (U[t, i, v] - u_prev[i, v]) / eps[i, v]
    for j in range(H):
        for v in range(LB):
            acc[v] = 0.0
        for i in range(H):
            for v in range(LB):
                acc[v] = fma(w_rec[i, j, v], ea[i, v], acc[v])
        for v in range(LB):
            back[j, v] = acc[v]


@njit(**JIT)
def backward_pass(DY, X, C0, C, U, u0, w_rec, w_out, eps, g_w_in, g_w_rec, g_w_out, g_b_c,
                  g_b_o, g_eps, g_u0, sizes):  # pragma: no cover
    """One block of lanes, given DY (T, NO, LB) = ∂L/∂o_t: every per-lane gradient (BPTT). g_eps
    is filled when U holds the potentials (learned time constants). Gradients are summed in
    stack arrays (they cannot alias the histories they read) and written once."""
    T, LB, one, zero = X.shape[0], width(X), typed(X, 1.0), typed(X, 0.0)
    H, NI, NO = _sizes(sizes, X, w_rec, w_out)
    learn_eps = U.shape[0] > 0
    a, back = stack(X, H), stack(X, H)  # ∂L/∂u_t, W_recᵀ(ε ⊙ a_{t+1})
    ea, ea2 = stack(X, H), stack(X, H)  # ε ⊙ a of the two steps in hand
    sum_b_c, sum_eps = stack(X, H), stack(X, H)
    sum_w_rec, sum_w_in, sum_w_out = stack(X, H * H), stack(X, H * NI), stack(X, NO * H)
    sum_b_o = stack(X, NO)
    acc = lanes(X)
    for i in range(H):
        for v in range(LB):
            a[i, v] = back[i, v] = sum_b_c[i, v] = sum_eps[i, v] = 0.0
    for q in range(H * H):
        for v in range(LB):
            sum_w_rec[q, v] = 0.0
    for q in range(H * NI):
        for v in range(LB):
            sum_w_in[q, v] = 0.0
    for q in range(NO * H):
        for v in range(LB):
            sum_w_out[q, v] = 0.0
    for o in range(NO):
        for v in range(LB):
            sum_b_o[o, v] = 0.0
    for t in range(T - 1, -1, -2):  # two steps back in time, then both steps' outer products
        _back_step(t, DY, C, U, u0, w_rec, w_out, eps, a, ea, back, sum_b_c, sum_eps, acc,
                   learn_eps, H, NO)
        # the second step s = t - 1; an odd T ends on a lone t = 0, whose second step adds
        # exact zeros (ea2 = 0, δo weighted 0: fma(0, x, Σ) = Σ), the same sums as one at a time
        second = t > 0
        s = t - 1 if second else t
        if second:
            _back_step(s, DY, C, U, u0, w_rec, w_out, eps, a, ea2, back, sum_b_c, sum_eps, acc,
                       learn_eps, H, NO)
        else:
            for i in range(H):
                for v in range(LB):
                    ea2[i, v] = 0.0
        weight = one if second else zero
        prev, prev2 = C[t - 1] if t > 0 else C0, C[s - 1] if s > 0 else C0
        for o in range(NO):  # each sum read and written once per two steps, added in time order
            for v in range(LB):
                sum_b_o[o, v] = sum_b_o[o, v] + DY[t, o, v] + weight * DY[s, o, v]
            for i in range(H):
                for v in range(LB):
                    sum_w_out[o * H + i, v] = fma(weight * DY[s, o, v], C[s, i, v], fma(
                        DY[t, o, v], C[t, i, v], sum_w_out[o * H + i, v]))
        for i in range(H):
            for d in range(NI):
                for v in range(LB):
                    sum_w_in[i * NI + d, v] = fma(ea2[i, v], X[s, d, v], fma(
                        ea[i, v], X[t, d, v], sum_w_in[i * NI + d, v]))
            for j in range(H):
                for v in range(LB):
                    sum_w_rec[i * H + j, v] = fma(ea2[i, v], prev2[j, v], fma(
                        ea[i, v], prev[j, v], sum_w_rec[i * H + j, v]))
    for i in range(H):  # c_{-1} = tanh(u_0 + b_c) feeds step 0
        for v in range(LB):
            dq = (one - C0[i, v] * C0[i, v]) * back[i, v]
            g_b_c[i, v] = sum_b_c[i, v] + dq
            g_u0[i, v] = (one - eps[i, v]) * a[i, v] + dq
            g_eps[i, v] = sum_eps[i, v]
        for d in range(NI):
            for v in range(LB):
                g_w_in[i, d, v] = sum_w_in[i * NI + d, v]
        for j in range(H):
            for v in range(LB):
                g_w_rec[i, j, v] = sum_w_rec[i * H + j, v]
    for o in range(NO):
        for v in range(LB):
            g_b_o[o, v] = sum_b_o[o, v]
        for i in range(H):
            for v in range(LB):
                g_w_out[o, i, v] = sum_w_out[o * H + i, v]
