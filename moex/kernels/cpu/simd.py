"""Building blocks that let numba put independent chains side by side in SIMD lanes.

Without Intel's SVML (not in the PyPI llvmlite), LLVM cannot vectorise calls to libm's exp, log
or tanh; `exp`, `log` and `tanh` below are written with arithmetic and bit casts only, so a loop
over lanes compiles to vector instructions. `lanes` is a small stack array: in a loop over its
`width(x)` entries (a constant where the kernel is compiled: 8 float64, 16 float32 on AVX-512),
LLVM keeps it in registers (a heap accumulator is stored and
reloaded on every iteration because it might alias the arrays it reads). numba leaves LLVM's SLP
vectoriser off by default; it is what turns those unrolled lane loops into vector instructions.
"""

import math

import numba
import numpy as np
from llvmlite import ir
from llvmlite.binding import get_host_cpu_features
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic, overload
from numba.np.numpy_support import as_dtype

numba.config.SLP_VECTORIZE = 1  # read when numba builds its pass manager, before compiling
_FEATURES = get_host_cpu_features().flatten()
# LLVM's tuning for Intel's AVX-512 server CPUs prefers 256-bit vectors (a guard against clock
# drops on early ones); the lane loops then run as two halves. Turned off here (unless the user
# chose NUMBA_CPU_FEATURES): 1.03-1.26x per epoch on an Emerald Rapids VM, the same bits (every
# lane is computed alone). numba reads it when it first compiles and keys its cache on it.
if numba.config.CPU_FEATURES is None and "+avx512f" in _FEATURES:
    numba.config.CPU_FEATURES = _FEATURES + ",-prefer-256-bit"

# Lanes per block: one AVX-512 vector (two AVX2 vectors) of float64, and of float32 where the CPU
# has AVX-512 (16 lanes; on a CPU without it 8, one AVX2 vector). numba compiles for this CPU and
# keys its cache on the CPU's features, so the width a kernel was compiled with is this one.
WIDTHS = {np.dtype(np.float64): 8,
          np.dtype(np.float32): 16 if "+avx512f" in _FEATURES else 8}
# Stack arrays start on a cache line: a vector of 8 float64 (64 bytes) then never straddles
# two lines (a split load or store costs about twice as much, and where a stack array lands
# depends on where the process's stack does: up to 25 % of a kernel's time varied between runs).
ALIGN = 64

# Only flags that never change a finite result: `contract` (fuse a·b + c where LLVM sees fit),
# `arcp`, `afn` and `reassoc` let the same source round differently depending on what LLVM
# inlined around it, and a kernel compiled in the process then gave other last bits than the
# same kernel loaded from numba's cache (the chaotic closed loop amplified them into other
# metrics). Fused multiply-adds are written out with `fma` instead: one rounding, everywhere.
FASTMATH = {"nnan", "ninf", "nsz"}
# error_model="numpy": no ZeroDivisionError branch on float division, which blocks vectorisation;
# no_cfunc_wrapper: numba builds a C-callable wrapper of every function unless told not to, and
# nothing here takes a kernel's C address (a first run's phase-1 compile spent ~0.2 s on them).
# A function only other kernels call also goes without the wrapper that Python calls through
# (`no_cpython_wrapper=True` where it is compiled: ~0.7 s of that compile, 2026-12-07)
JIT = dict(fastmath=FASTMATH, error_model="numpy", cache=True, no_cfunc_wrapper=True)


@intrinsic
def fma(typingctx, a, b, c):
    """a·b + c rounded once (llvm.fma: a vector FMA instruction where the CPU has one), in the
    widest type of the three; written out where a product is accumulated, since the compiler
    may not fuse."""
    kind = typingctx.unify_types(a, b, c)

    def codegen(context, builder, signature, args):
        return builder.fma(*(context.cast(builder, v, t, kind) for v, t in zip(
            args, signature.args, strict=True)))

    return kind(a, b, c), codegen


def width(x) -> int:
    """Lanes per block for x's dtype (x: an array or a dtype, numpy's or numba's); in a compiled
    kernel, a constant (`width(X)` of an argument X), so that loops over a block's lanes have a
    literal bound."""
    if isinstance(x, np.ndarray | types.Array):
        x = x.dtype
    return WIDTHS[np.dtype(as_dtype(x) if isinstance(x, types.Type) else x)]


# `width` and `typed` are compiled once per type and inlined by LLVM, not by numba: numba's
# inline="always" copied and typed them at each of their ~35 call sites, 4 s of the phase-1
# kernel's 19 s compile (2026-12-05, the same machine code and bits)
@overload(width)
def _width(x):
    lb = width(x)
    return lambda x: lb


def typed(x, value):
    """`value` in x's dtype (x an array): a float literal is float64 in numba, and one in a float32
    expression would turn the whole expression into float64 (half the lanes per vector)."""
    return x.dtype.type(value)


@overload(typed)
def _typed(x, value):
    kind = np.float32 if x.dtype == types.float32 else np.float64
    return lambda x, value: kind(value)


def _stack_array(context, builder, dtype, rows, LB):
    """A C-contiguous (rows, LB) array in an alloca at the current position."""
    array_type = types.Array(dtype, 2, "C")
    llvm_type = context.get_value_type(dtype)
    size = builder.mul(rows, context.get_constant(types.intp, LB))
    buffer = builder.alloca(llvm_type, size=size)
    buffer.align = ALIGN
    array = context.make_array(array_type)(context, builder)
    itemsize = context.get_constant(types.intp, context.get_abi_sizeof(llvm_type))
    context.populate_array(array, data=buffer,
                           shape=[rows, context.get_constant(types.intp, LB)],
                           strides=[builder.mul(itemsize, context.get_constant(types.intp, LB)),
                                    itemsize], itemsize=itemsize, meminfo=None)
    return array


@intrinsic
def lanes(typingctx, like):
    """A 1-D array of `width(like)` elements of `like`'s dtype on the stack (uninitialised); in a
    loop over its entries with that constant bound it lives in a vector register."""
    dtype, LB = like.dtype, width(like)
    array_type = types.Array(dtype, 1, "C")

    def codegen(context, builder, signature, args):
        buffer = cgutils.alloca_once(builder, context.get_value_type(dtype), size=LB)
        buffer.align = ALIGN
        array = context.make_array(array_type)(context, builder)
        itemsize = context.get_constant(types.intp, context.get_abi_sizeof(
            context.get_value_type(dtype)))
        context.populate_array(array, data=buffer, shape=[context.get_constant(types.intp, LB)],
                               strides=[itemsize], itemsize=itemsize, meminfo=None)
        return array._getvalue()

    return array_type(like), codegen


@intrinsic
def stack(typingctx, like, rows):
    """A (rows, width(like)) array of `like`'s dtype on the stack (uninitialised), for the state
    of one block of lanes. Unlike a heap array it cannot alias the arrays a kernel reads, so LLVM
    may reorder loads and stores around it and vectorise the lane loops. Call it once per
    function, outside loops (the memory lives until the function returns)."""
    return _stack_of(like, like.dtype)


@intrinsic
def sums(typingctx, like, rows):
    """`stack` in float64 whatever `like`'s dtype (rows of width(like) lanes): for sums that a
    float32 run keeps in float64."""
    return _stack_of(like, types.float64)


def _stack_of(like, dtype):
    """The signature and code of a (rows, width(like)) stack array of `dtype` (`stack`, `sums`)."""
    LB = width(like)

    def codegen(context, builder, signature, args):
        return _stack_array(context, builder, dtype, args[1], LB)._getvalue()

    return types.Array(dtype, 2, "C")(like, types.intp), codegen


# exp, log and tanh are emitted as LLVM instructions where they are called (`intrinsic`s): the
# same operations, one by one, as the njit functions they were until 2026-12-05 (the same bits),
# without numba inlining and typing a copy of their code at every call site: the phase-1
# kernel's compile 19.1-19.2 s against 20.0-21.6 s, in turn (17.7 s with libm's in their place).
_LOG2E = 1.4426950408889634
_LN2 = 0.6931471805599453
_LN2_HI = 0.693145751953125  # ln 2 split so that k · _LN2_HI is exact (Cody-Waite)
_LN2_LO = 1.42860682030941723212e-6
_ROUND = 6755399441055744.0  # 1.5 · 2^52: x + _ROUND holds round(x) in its low bits
_E = tuple(1.0 / math.factorial(n) for n in range(12))  # e^r's Taylor coefficients
_F = np.float32
_ROUND32 = _F(12582912.0)  # 1.5 · 2^23: x + _ROUND32 holds round(x) in its low bits
_LN2_HI32, _LN2_LO32 = _F(0.693359375), _F(-2.12194440e-4)  # ln 2 = hi + lo, k · hi exact
_C = tuple(_F(1.0 / math.factorial(n)) for n in range(2, 8))  # 1/2!, ..., 1/7!
# fdlibm's logf (e_logf.c): its split of ln 2 = hi + lo and R(z)'s coefficients
_LN2_HI32_LOG, _LN2_LO32_LOG = _F(6.9313812256e-01), _F(9.0580006145e-06)
_LG = tuple(_F(c) for c in (0.66666662693, 0.40000972152, 0.28498786688, 0.24279078841))
# float32's tanh x, y = x / 2: t = tanh y ≈ y + y³ P(y²) / Q(y²) on 0 <= y <= 4.75 (P, Q of degree
# 2), fitted for the error it leaves in tanh x = 2t / (1 + t²): an error in t, 1 / cosh x times
# itself (tools/fit_tanh_rational.py: 1.5e-8); beyond x = 9.5 tanh x rounds to within an ulp of 1
_TANH_P = tuple(_F(c) for c in (-0.3333330556879677, -0.015570671603659055, -4.389952217539283e-06))
_TANH_Q = tuple(_F(c) for c in (1.0, 0.44670858908403677, 0.01679606042202513))
_TANH_SMALL = 1.0986  # 2 atanh ½: below, tanh x = x + (a small term); above, 1 - (a small term)
_F64, _F32, _I64, _I32 = ir.DoubleType(), ir.FloatType(), ir.IntType(64), ir.IntType(32)


class _Emit:
    """Arithmetic on LLVM values in one float type, written as in Python: the instructions of
    `exp`, `log` and `tanh` (each operation rounds as numba's would; numba's fastmath flags are
    added to them afterwards, as to every instruction of a kernel)."""

    def __init__(self, builder, kind):
        self.b, self.kind = builder, kind

    def c(self, value):
        return ir.Constant(self.kind, float(value))

    def fma(self, a, b, c):
        return self.b.fma(*(self.c(v) if isinstance(v, float | np.floating) else v
                            for v in (a, b, c)))

    def poly(self, x, coefficients):
        """Horner's rule by fma, the highest coefficient first."""
        p = self.c(coefficients[0])
        for a in coefficients[1:]:
            p = self.fma(p, x, a)
        return p

    def clamp(self, x, lo, hi):
        """x held within [lo, hi], NaN kept NaN: two compare-and-selects (maxpd/minpd with x
        second), where llvm.maxnum would turn NaN into lo."""
        x = self.b.select(self.b.fcmp_ordered(">", self.c(lo), x), self.c(lo), x)
        return self.b.select(self.b.fcmp_ordered("<", self.c(hi), x), self.c(hi), x)


def _exp_ir(builder, x):
    """e^x of a double (see `exp`)."""
    f, b = _Emit(builder, _F64), builder
    x = f.clamp(x, -700.0, 700.0)
    shifted = f.fma(x, _LOG2E, _ROUND)
    k = b.fsub(shifted, f.c(_ROUND))  # round(x / ln 2)
    r = f.fma(k, -_LN2_LO, f.fma(k, -_LN2_HI, x))  # |r| <= ln 2 / 2
    r2 = b.fmul(r, r)  # e^r's Taylor series to degree 11 by Estrin's scheme (pairs, then r²,
    r4 = b.fmul(r2, r2)  # r⁴, r⁸): 5 roundings deep, not 12 as Horner's, for the same error
    p = f.fma(b.fmul(r4, r4), f.fma(r2, f.fma(r, _E[11], _E[10]), f.fma(r, _E[9], _E[8])), f.fma(
        r4, f.fma(r2, f.fma(r, _E[7], _E[6]), f.fma(r, _E[5], _E[4])),
        f.fma(r2, f.fma(r, _E[3], _E[2]), f.fma(r, _E[1], _E[0]))))
    return b.fmul(p, _pow2(f, shifted, _I64, 52, 1023))


def _pow2(f, shifted, bits_type, mantissa, bias):
    """2^k as f's float type, from `shifted` = x / ln 2 + 1.5 · 2^mantissa, whose low bits hold k
    (|k| <= bias): (k + bias) << mantissa in integers of the float's width (`bits_type`), the
    shift moving the high bits out; `_split`'s inverse."""
    b = f.b
    return b.bitcast(b.shl(b.add(b.bitcast(shifted, bits_type), ir.Constant(bits_type, bias)),
                           ir.Constant(bits_type, mantissa)), f.kind)


def _split(f, x, bits_type, mantissa, bias):
    """A normal x > 0 of f's float type as m 2^e, m in [√½, √2): e (an integer of bits_type, the
    float's width) and m, from x's bits (`mantissa` bits of fraction, exponent `bias`)."""
    b, one = f.b, ir.Constant(bits_type, 1)
    bits = b.bitcast(x, bits_type)
    e = b.sub(b.and_(b.ashr(bits, ir.Constant(bits_type, mantissa)), ir.Constant(
        bits_type, 2 * bias + 1)), ir.Constant(bits_type, bias))
    m = b.bitcast(b.or_(b.and_(bits, ir.Constant(bits_type, (1 << mantissa) - 1)), ir.Constant(
        bits_type, bias << mantissa)), f.kind)  # in [1, 2)
    big = b.fcmp_ordered(">", m, f.c(1.4142135623730951))
    return b.select(big, b.add(e, one), e), b.select(big, b.fmul(m, f.c(0.5)), m)


def _log_ir(builder, x):
    """ln x of a double (see `log`)."""
    f, b = _Emit(builder, _F64), builder
    e, m = _split(f, x, _I64, 52, 1023)  # |z| <= 0.172 below
    z = b.fdiv(b.fsub(m, f.c(1.0)), b.fadd(m, f.c(1.0)))
    p = f.poly(b.fmul(z, z), [1.0 / n for n in range(21, 0, -2)])  # 2 atanh z / (2z)
    return f.fma(b.fmul(f.c(2.0), z), p, b.fmul(b.sitofp(e, _F64), f.c(_LN2)))


def _tanh64_ir(builder, x):
    """tanh of a double (see `tanh`)."""
    f, b = _Emit(builder, _F64), builder
    e = _exp_ir(b, b.fmul(f.c(2.0), x))
    return b.fsub(f.c(1.0), b.fdiv(f.c(2.0), b.fadd(e, f.c(1.0))))


def _tanh32_ir(builder, x):
    """tanh of a float in float32 arithmetic (see `tanh`). With a = |x|, y = a / 2, z = y², the
    rational's t = y n / q (n = q + z p) and S = q² + (y n)² (so 1 + t² = S / q²):
    tanh a = a + a z (q p - n²) / S below `_TANH_SMALL`, 1 - (q - y n)² / S above; one division
    either way, and the last operation adds a term small beside the result, so the roundings
    before it count for little (the halving damps t's own error by 1 / cosh x)."""
    f, b = _Emit(builder, _F32), builder
    a = b.call(b.module.declare_intrinsic("llvm.fabs", [_F32]), [x])
    a = b.select(b.fcmp_ordered("<", f.c(9.5), a), f.c(9.5), a)  # NaN kept NaN
    y = b.fmul(f.c(0.5), a)
    z = b.fmul(y, y)
    p, q = f.poly(z, _TANH_P[::-1]), f.poly(z, _TANH_Q[::-1])
    n = f.fma(z, p, q)
    yn = b.fmul(y, n)
    s = f.fma(yn, yn, b.fmul(q, q))
    small = b.fcmp_ordered("<", a, f.c(_TANH_SMALL))
    m = f.fma(b.fneg(y), n, q)  # q - y n
    g = f.fma(q, p, b.fneg(b.fmul(n, n)))
    d = b.fdiv(b.select(small, g, b.fmul(m, m)), s)
    near_zero, near_one = f.fma(b.fmul(a, z), d, a), b.fsub(f.c(1.0), d)
    copysign = b.module.declare_intrinsic("llvm.copysign", [_F32, _F32],
                                          ir.FunctionType(_F32, [_F32, _F32]))
    return b.call(copysign, [b.select(small, near_zero, near_one), x])


def _exp32_ir(builder, x):
    """e^x of a float in float32 arithmetic (see `exp`)."""
    f, b = _Emit(builder, _F32), builder
    x = f.clamp(x, -87.0, 88.0)  # -126 <= k <= 127: 2^k a normal float
    shifted = f.fma(x, _F(_LOG2E), _ROUND32)
    k = b.fsub(shifted, f.c(_ROUND32))  # round(x / ln 2)
    r = f.fma(k, -_LN2_LO32, f.fma(k, -_LN2_HI32, x))  # |r| <= ln 2 / 2
    p = f.fma(b.fmul(r, r), f.poly(r, _C[::-1]), r)  # e^r - 1, to r^7 / 7!
    return b.fmul(b.fadd(p, f.c(1.0)), _pow2(f, shifted, _I32, 23, 127))


def _log32_ir(builder, x):
    """ln x of a float in float32 arithmetic (see `log`)."""
    f, b = _Emit(builder, _F32), builder
    e, m = _split(f, x, _I32, 23, 127)
    e = b.sitofp(e, _F32)
    # ln(1 + g), g = m - 1 (exact), as fdlibm's logf: with s = g / (2 + g), ln(1 + g) =
    # g - g²/2 + s (g²/2 + R(s²)); the leading g is exact, so the error stays within an ulp
    # near x = 1 (the atanh series of float64's `log` gave 2.8 ulp there in float32)
    g = b.fsub(m, f.c(1.0))
    s = b.fdiv(g, b.fadd(g, f.c(2.0)))
    z = b.fmul(s, s)
    w = b.fmul(z, z)
    r = b.fadd(b.fmul(z, b.fadd(f.c(_LG[0]), b.fmul(w, f.c(_LG[2])))),
               b.fmul(w, b.fadd(f.c(_LG[1]), b.fmul(w, f.c(_LG[3])))))
    half_g2 = b.fmul(f.c(0.5), b.fmul(g, g))
    low = b.fadd(b.fmul(s, b.fadd(half_g2, r)), b.fmul(e, f.c(_LN2_LO32_LOG)))
    return b.fsub(b.fmul(e, f.c(_LN2_HI32_LOG)), b.fsub(b.fsub(half_g2, low), g))


def _elementwise(emit, x, kind=types.float64):
    """The signature and code of an intrinsic of one float argument x that returns
    `emit(builder, x)` (x cast to `kind`)."""
    def codegen(context, builder, signature, args):
        return emit(builder, context.cast(builder, args[0], signature.args[0], kind))

    return kind(x), codegen


@intrinsic
def exp(typingctx, x):
    """e^x in x's precision. float64 (and integers): |x| <= 700 (clamped), relative error below
    1e-14 (the degree-11 Taylor series at |r| = ln 2 / 2: 6e-15). float32, in float32
    arithmetic: -87 <= x <= 88 (clamped), within 2 ulp (tests/test_kernels.py); x = k ln 2 + r,
    e^r = 1 + r + r²(1/2! + ... + r^5/7!)."""
    if x == types.float32:
        return _elementwise(_exp32_ir, x, types.float32)
    return _elementwise(_exp_ir, x)


@intrinsic
def log(typingctx, x):
    """ln x of a normal x > 0 in x's precision: x = m 2^e, ln m = 2 atanh((m-1)/(m+1)).
    float64 (and integers): error below 1e-15. float32, in float32 arithmetic: within 2 ulp."""
    if x == types.float32:
        return _elementwise(_log32_ir, x, types.float32)
    return _elementwise(_log_ir, x)


@intrinsic
def tanh(typingctx, x):
    """tanh x in x's precision. float64: 1 - 2 / (e^{2x} + 1), absolute error below 1e-14.
    float32, in float32 arithmetic: tanh of x / 2 by a rational of degrees (2, 2) in x², doubled by
    tanh x = 2t / (1 + t²) (`_tanh32_ir`; clamped at |x| = 9.5), within 1.88 ulp over every float32
    (tests/test_kernels.py); about 25 operations and one division per vector of 8 or 16 lanes.
    Since 2026-12-06; before, the rational of degrees (5, 4) evaluated in float64 and rounded once
    (within 0.52 ulp, two conversions and a division of doubles per 4 lanes): the float32 forward
    pass 0.89-0.92x its time (AVX2, H = 10-15; `rnn.forward_pass` alone)."""
    if x == types.float32:
        return _elementwise(_tanh32_ir, x, types.float32)
    return _elementwise(_tanh64_ir, x)


def zeros(shape: tuple, dtype=np.float64) -> np.ndarray:
    """np.zeros whose data start on a cache line (`ALIGN` bytes; numpy gives small arrays 16),
    for arrays of blocks of lanes: with rows of 8 float64 every row is then one line."""
    dtype = np.dtype(dtype)
    size = int(np.prod(shape)) * dtype.itemsize
    raw = np.zeros(size + ALIGN, np.uint8)
    start = -raw.ctypes.data % ALIGN
    return raw[start:start + size].view(dtype).reshape(shape)


@njit(inline="always", **JIT)
def line_rows(rows, length, like):  # pragma: no cover
    """An uninitialised (rows, m) heap array of `like`'s dtype in a compiled kernel, m ≥ `length`
    a whole number of cache lines' worth, so that every row starts on a line (`ALIGN` bytes;
    numba's allocator gives 16): a vector load from a row's start never straddles two lines."""
    per_line = ALIGN // like.itemsize
    m = -(-length // per_line) * per_line
    raw = np.empty(rows * m + per_line, like.dtype)
    start = (-raw.ctypes.data % ALIGN) // like.itemsize
    return raw[start:start + rows * m].reshape(rows, m)


def padded(count: int, dtype) -> int:
    """`count` lanes rounded up to whole blocks of `dtype`."""
    return -(-count // width(dtype)) * width(dtype)


@intrinsic
def transpose_tile(typingctx, src, src_start, src_step, dst, dst_start, dst_step):
    """A square tile of width(src) × width(src) elements moved across its diagonal: for i, j <
    LB, element j of row i of `src` (LB contiguous elements from flat index src_start + i ·
    src_step) to element i of row j of `dst` (from dst_start + j · dst_step); src and dst
    C-contiguous arrays of one dtype, indices into their data as if flat, unchecked. LB vector
    loads, log2(LB) rounds of LB two-vector shuffles (each interleaves the low or high halves of
    rows i and i + LB/2: after log2(LB) rounds row j holds column j), LB vector stores: 24
    shuffles per 8 × 8 float64 tile, 64 per 16 × 16 float32, where an element at a time is a
    load and a store each. Moves bits only (the same numbers). Arrays of two dtypes or not
    C-contiguous are refused where the kernel is compiled (numba's TypingError)."""
    if src.dtype != dst.dtype or src.layout != "C" or dst.layout != "C":
        return None  # no signature: numba reports the call as one it cannot type
    LB = width(src)

    def codegen(context, builder, signature, args):
        element = context.get_value_type(signature.args[0].dtype)
        vector, size = ir.VectorType(element, LB), context.get_abi_sizeof(element)

        def rows(at):  # the LB row pointers of argument `at` (the array) and the two after it
            array_type, array, start, step = signature.args[at], *args[at:at + 3]
            start, step = (context.cast(builder, v, t, types.intp) for v, t in zip(
                (start, step), signature.args[at + 1:at + 3], strict=True))
            data = context.make_array(array_type)(context, builder, array).data
            return [builder.bitcast(builder.gep(data, [builder.add(start, builder.mul(
                context.get_constant(types.intp, i), step))]), vector.as_pointer())
                for i in range(LB)]

        loaded = [builder.load(p, align=size) for p in rows(0)]
        half = LB // 2
        masks = [ir.Constant(ir.VectorType(_I32, LB), [ir.Constant(_I32, m) for i in range(
            first, first + half) for m in (i, LB + i)]) for first in (0, half)]
        for _ in range(LB.bit_length() - 1):
            loaded = [builder.shuffle_vector(loaded[i], loaded[i + half], mask)
                      for i in range(half) for mask in masks]
        for value, p in zip(loaded, rows(3), strict=True):
            builder.store(value, p, align=size)
        return context.get_dummy_value()

    return types.void(src, src_start, src_step, dst, dst_start, dst_step), codegen
