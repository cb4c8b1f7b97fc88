"""The gpu backend's forward kernel against its earlier design, at Table 2's phase-1 sizes:
outputs compared, time per launch on a GPU, and both compiled for an H200 here (registers, spills,
shuffles, barriers), for BENCHMARKS.md's "Compiled for an H200 without one".

    python benchmarks/gpu_forward_variants.py [--networks 90 900] [--repeats 20] [--aot]

The earlier design (`forward_by_rows`, kept here only) held a lane's state c_{t-1} as a row of a
(lanes, H) tile and formed W_rec c_{t-1} as a sum over a (lanes, H, H) product along the axis
spread across the threads that hold a row (warp shuffles). `rnn_forward` (moex.kernels.gpu.rnn)
writes c_t to memory, waits at one barrier and reads it back column by column: H outer-product
updates of a (lanes, H) accumulator, no sum across threads. The same arithmetic in another order:
outputs equal to ~1e-16 where the networks contract; where some of many random networks are
chaotic, 999 steps part the two orders' last bits into visible differences (the column "weights
SD 0.5"). Without CUDA (Triton's interpreter, tiny sizes) it checks the outputs only; `--aot`
compiles both for sm_90a (no GPU needed).
"""

import argparse
import os
import sys
import time
from pathlib import Path

import torch
import triton
import triton.language as tl

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from moex.kernels.gpu.lanes import OPTIONS, PARAMS, Net, pow2, strides  # noqa: E402
from moex.kernels.gpu.rnn import (  # noqa: E402
    _chunk,
    _network,
    _put,
    _vector,
    device,
    load_rows,
    reciprocal,
    stable_tanh,
)


@device
def _tile(ptr, rows, cols, NR: tl.constexpr, NC: tl.constexpr):
    """The (RP, CP) tile of the (NR, NC) matrix at `ptr`."""
    mask = (rows < NR)[:, None] & (cols < NC)[None, :]
    return tl.load(ptr + rows[:, None] * NC + cols[None, :], mask=mask, other=0.0)


@device
def _matvec(w, v):
    """(R, C) · (BL, C) -> (BL, R)."""
    return tl.sum(w[None, :, :] * v[:, None, :], axis=2)


@triton.jit
def forward_by_rows(X, XROW, U0J, W_IN, W_REC, W_OUT, B_C, B_O, TAU, U0, OUT, C, U, SUMS,
                    sW_IN, sW_REC, sW_OUT, sB_C, sB_O, sTAU, sU0,
                    T: tl.constexpr, NI: tl.constexpr, H: tl.constexpr, NO: tl.constexpr,
                    NIP: tl.constexpr, HP: tl.constexpr, NOP: tl.constexpr, BL: tl.constexpr,
                    LPN: tl.constexpr, NPR: tl.constexpr, CHUNKS: tl.constexpr,
                    KEEP_C: tl.constexpr, KEEP_U: tl.constexpr, KEEP_SUMS: tl.constexpr):
    """The forward kernel until 2026-12-04: weights held as (H, H) tiles in registers, each
    product a sum over a (BL, H, H) product along the axis spread across threads (OUT and C;
    the histories U and the sums left out)."""
    n, r, k = _network(NPR)
    h, i, o = tl.arange(0, HP), tl.arange(0, NIP), tl.arange(0, NOP)
    w_in = _tile(W_IN + r * sW_IN + k * (H * NI), h, i, H, NI)
    w_rec = _tile(W_REC + r * sW_REC + k * (H * H), h, h, H, H)
    w_out = _tile(W_OUT + r * sW_OUT + k * (NO * H), o, h, NO, H)
    b_c = _vector(B_C + r * sB_C + k * H, h, H, 0.0)[None, :]
    b_o = _vector(B_O + r * sB_O + k * NO, o, NO, 0.0)[None, :]
    eps = reciprocal(_vector(TAU + r * sTAU + k * H, h, H, 1.0))[None, :]
    for chunk in range(CHUNKS):
        lane, ok, xrow, u0j = _chunk(XROW, U0J, n, chunk, LPN, BL)
        u = load_rows(U0 + r * sU0, u0j, ok, h, H)
        c = stable_tanh(u + b_c)
        for t in range(T):
            x = load_rows(X, xrow * T + t, ok, i, NI)
            u = u + eps * (_matvec(w_in, x) + _matvec(w_rec, c) - u)
            c = stable_tanh(u + b_c)
            if KEEP_C:
                _put(C, lane * T + t, ok, h, c, H)
            _put(OUT, lane * T + t, ok, o, _matvec(w_out, c) + b_o, NO)


def table2_net(networks: int, device: str, *, dtype=torch.float64, series: int = 10,
               T: int = 999, scale: float = 0.5):
    """Phase 1's expert networks at Table 2's sizes (2 experts of 10 units per run, 2 inputs and
    outputs), random parameters (weights of SD `scale`: 0.5 makes some of many networks chaotic,
    where two summation orders part ways over 999 steps; 0.1 contracts): the Net, its parameters
    and the inputs X."""
    K, H, D = 2, 10, 2
    runs = networks // K
    g = torch.Generator().manual_seed(0)

    def rand(*shape):
        return (scale * torch.randn(runs, *shape, generator=g, dtype=dtype)).to(device)

    params = {"w_in": rand(K, H, D), "w_rec": rand(K, H, H), "w_out": rand(K, D, H),
              "b_c": rand(K, H), "b_o": rand(K, D), "tau": 1.0 + rand(K, H).abs(),
              "u0": rand(K * series, H)}
    X = torch.randn(series, T, D, generator=g, dtype=dtype).tanh().to(device)
    lanes = torch.arange(networks * series)
    net = Net(networks, K, series, T=T, NI=D, H=H, NO=D, xrow=(lanes % series).numpy(),
              u0j=((lanes // series) % K * series + lanes % series).numpy(), learn_eps=False,
              sums=False, dtype=dtype, device=device, keep=True)
    return net, params, X


def variant(net: Net, X, params):
    """The earlier design's outputs, into net.O."""
    p = [params[k] for k in PARAMS]
    forward_by_rows[(net.networks,)](X, net.xrow, net.u0j, *p, net.O, net.C, net.U, net.S,
                                        *strides(params, PARAMS), KEEP_C=True, KEEP_U=False,
                                        KEEP_SUMS=False, num_warps=4, **OPTIONS, **net.meta,
                                        NIP=pow2(net.meta["NI"]))
    return net.O


def timed(fn, repeats: int) -> float:
    """Least ms per call over `repeats` calls after one warm-up (compile)."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        torch.cuda.synchronize()
        start = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        best = min(best, time.perf_counter() - start)
    return 1e3 * best


def aot() -> None:
    """Both kernels compiled for sm_90a at Table 2's sizes (benchmarks/gpu_aot.py's way)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import gpu_aot

    launches = []
    net, params, X = table2_net(90, "cpu")
    with gpu_aot.recording("table2", launches):
        net.forward(X, params, keep=True)
        variant(net, X, params)
    print("| kernel | registers | spilled bytes | SHFL | BAR | instructions |")
    print("|---|---|---|---|---|---|")
    for row in gpu_aot.compile_all(launches):
        print(f"| {row['kernel']} | {row['registers']} | {row['spill_bytes']} | "
              f"{row['shuffles']} | {row['barriers']} | {row['instructions']} |")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--networks", type=int, nargs="+", default=[90, 900])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--aot", action="store_true", help="compile both for sm_90a, then stop")
    args = parser.parse_args()
    if args.aot:
        return aot()
    cuda = torch.cuda.is_available() and os.environ.get("TRITON_INTERPRET") != "1"
    device = "cuda" if cuda else "cpu"
    print("| networks | by rows (earlier) ms | by columns (rnn_forward) ms | columns / rows "
          "| max |Δo|, weights SD 0.5 | max |Δo|, SD 0.1 | rerun equal |")
    print("|---|---|---|---|---|---|---|")
    for networks in args.networks if cuda else [4]:
        gaps = []
        for scale in (0.5, 0.1):
            net, params, X = table2_net(networks, device, T=999 if cuda else 7,
                                        series=10 if cuda else 3, scale=scale)
            net.forward(X, params, keep=True)
            reference = net.O.clone()
            first = variant(net, X, params).clone()
            gaps.append((first - reference).abs().max().item())
        again = "yes" if torch.equal(variant(net, X, params), first) else "NO"
        gap = " | ".join(f"{g:.1e}" for g in gaps) + f" | {again}"
        if not cuda:
            print(f"| {networks} (interpreter) | — | — | — | {gap} |")
            continue
        rows = timed(lambda net=net, X=X, p=params: variant(net, X, p), args.repeats)
        columns = timed(lambda net=net, X=X, p=params: net.forward(X, p, keep=True),
                        args.repeats)
        print(f"| {networks} | {rows:.3f} | {columns:.3f} | {columns / rows:.2f} | {gap} |")


if __name__ == "__main__":
    main()
