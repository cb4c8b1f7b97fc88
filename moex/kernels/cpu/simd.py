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
import warnings

import numba
import numpy as np
from llvmlite import ir
from llvmlite.binding import get_host_cpu_features
from numba import njit, types
from numba.core import cgutils
from numba.core.errors import NumbaIRAssumptionWarning
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
# error_model="numpy": no ZeroDivisionError branch on float division, which blocks vectorisation
JIT = dict(fastmath=FASTMATH, error_model="numpy", cache=True)


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


@intrinsic
def clamp(typingctx, x, lo, hi):
    """x held within [lo, hi] in x's float type, NaN kept NaN: two compare-and-selects (each one
    vector instruction on x86, maxpd/minpd with x second), where a conditional expression's
    branch can keep a loop from being vectorised and llvm.maxnum would turn NaN into lo."""
    kind = types.float32 if x == types.float32 else types.float64

    def codegen(context, builder, signature, args):
        x, lo, hi = (context.cast(builder, v, t, kind) for v, t in zip(
            args, signature.args, strict=True))
        x = builder.select(builder.fcmp_ordered(">", lo, x), lo, x)
        return builder.select(builder.fcmp_ordered("<", hi, x), hi, x)

    return kind(x, lo, hi), codegen


@intrinsic
def _as_bits(typingctx, x):
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _as_bits32(typingctx, x):
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return types.int32(types.float32), codegen


@intrinsic
def _as_float32(typingctx, x):  # the low 32 bits of an int64 (numba widens int32 arithmetic)
    def codegen(context, builder, signature, args):
        return builder.bitcast(builder.trunc(args[0], ir.IntType(32)), ir.FloatType())

    return types.float32(types.int64), codegen


@intrinsic
def _as_float(typingctx, x):
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


def width(x) -> int:
    """Lanes per block for x's dtype (x: an array or a dtype, numpy's or numba's); in a compiled
    kernel, a constant (`width(X)` of an argument X), so that loops over a block's lanes have a
    literal bound."""
    if isinstance(x, np.ndarray | types.Array):
        x = x.dtype
    return WIDTHS[np.dtype(as_dtype(x) if isinstance(x, types.Type) else x)]


@overload(width, inline="always")
def _width(x):
    lb = width(x)
    return lambda x: lb


def typed(x, value):
    """`value` in x's dtype (x an array): a float literal is float64 in numba, and one in a float32
    expression would turn the whole expression into float64 (half the lanes per vector)."""
    return x.dtype.type(value)


@overload(typed, inline="always")
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


_LOG2E = 1.4426950408889634
_LN2 = 0.6931471805599453
_LN2_HI = 0.693145751953125  # ln 2 split so that k · _LN2_HI is exact (Cody-Waite)
_LN2_LO = 1.42860682030941723212e-6
_ROUND = 6755399441055744.0  # 1.5 · 2^52: x + _ROUND holds round(x) in its low bits
_E = tuple(1.0 / math.factorial(n) for n in range(12))  # e^r's Taylor coefficients


@njit(inline="always", **JIT)
def exp(x):
    """e^x for |x| <= 700 (clamped), relative error below 1e-14 (the degree-11 Taylor series
    at |r| = ln 2 / 2: 6e-15)."""
    x = clamp(x, -700.0, 700.0)
    shifted = fma(x, _LOG2E, _ROUND)
    k = shifted - _ROUND  # round(x / ln 2)
    r = fma(k, -_LN2_LO, fma(k, -_LN2_HI, x))  # |r| <= ln 2 / 2
    r2 = r * r  # e^r's Taylor series to degree 11 by Estrin's scheme (pairs, then r², r⁴,
    r4 = r2 * r2  # r⁸): 5 roundings deep, not 12 as Horner's, for the same error
    p = fma(r4 * r4, fma(r2, fma(r, _E[11], _E[10]), fma(r, _E[9], _E[8])), fma(
        r4, fma(r2, fma(r, _E[7], _E[6]), fma(r, _E[5], _E[4])),
        fma(r2, fma(r, _E[3], _E[2]), fma(r, _E[1], _E[0]))))
    return p * _as_float((_as_bits(shifted) + 1023) << 52)  # times 2^k


@njit(inline="always", **JIT)
def log(x):
    """ln x for normal x > 0, error below 1e-15: x = m 2^e, ln m = 2 atanh((m-1)/(m+1))."""
    bits = _as_bits(float(x))
    e = ((bits >> 52) & 0x7FF) - 1023
    m = _as_float((bits & 0xFFFFFFFFFFFFF) | 0x3FF0000000000000)  # in [1, 2)
    big = m > 1.4142135623730951  # bring m into [√½, √2): |z| <= 0.172
    m = m * 0.5 if big else m
    e = e + 1 if big else e
    z = (m - 1.0) / (m + 1.0)
    z2 = z * z
    p = 1.0 / 21.0
    p = fma(p, z2, 1.0 / 19.0)
    p = fma(p, z2, 1.0 / 17.0)
    p = fma(p, z2, 1.0 / 15.0)
    p = fma(p, z2, 1.0 / 13.0)
    p = fma(p, z2, 1.0 / 11.0)
    p = fma(p, z2, 1.0 / 9.0)
    p = fma(p, z2, 1.0 / 7.0)
    p = fma(p, z2, 1.0 / 5.0)
    p = fma(p, z2, 1.0 / 3.0)
    p = fma(p, z2, 1.0)
    return fma(2.0 * z, p, e * _LN2)


@njit(inline="always", **JIT)
def _tanh64(x):
    """tanh x with absolute error below 1e-14."""
    return 1.0 - 2.0 / (exp(2.0 * x) + 1.0)


_F = np.float32
_ROUND32 = _F(12582912.0)  # 1.5 · 2^23: x + _ROUND32 holds round(x) in its low bits
_LN2_HI32, _LN2_LO32 = _F(0.693359375), _F(-2.12194440e-4)  # ln 2 = hi + lo, k · hi exact
_C2, _C3, _C4, _C5, _C6, _C7, _C8 = (_F(1.0 / math.factorial(n)) for n in range(2, 9))
# (tanh x - x) / x³ as a polynomial in x² on |x| <= 0.625: weighted least squares (relative error
# of tanh) at Chebyshev nodes, rounded to float32; within 0.8 ulp there in float32 arithmetic
_T0, _T1, _T2, _T3, _T4, _T5 = (_F(c) for c in (
    -0.3333333134651184, 0.1333320140838623, -0.053946252912282944, 0.021698208525776863,
    -0.008171784691512585, 0.0021382225677371025))


@njit(inline="always", **JIT)
def _tanh32(x):
    """tanh x in float32 arithmetic (16 lanes a vector), within 2 ulp of the exact value
    (tests/test_kernels.py): for |x| <= 0.625 x + x³ P(x²); above, tanh |x| = e / (e + 2) with
    e = e^{2|x|} - 1 = 2^k (e^r - 1) + 2^k - 1, e^r - 1 = r + r²(1/2! + ... + r^6/8!)
    (|r| <= ln 2 / 2). Both are computed and one selected (vectorised)."""
    z = x * x
    near = fma(fma(fma(fma(fma(_T5, z, _T4), z, _T3), z, _T2), z, _T1), z, _T0)
    near = fma(x * z, near, x)
    y = abs(x + x)
    y = clamp(y, _F(0.0), _F(80.0))  # tanh(40) rounds to 1 in float32
    shifted = fma(y, _F(1.4426950408889634), _ROUND32)
    k = shifted - _ROUND32  # round(y / ln 2)
    r = fma(k, -_LN2_LO32, fma(k, -_LN2_HI32, y))
    p = fma(fma(fma(fma(fma(fma(_C8, r, _C7), r, _C6), r, _C5), r, _C4), r, _C3), r, _C2)
    q = fma(r * r, p, r)  # e^r - 1
    scale = _as_float32((_as_bits32(shifted) + 127) << 23)  # 2^k
    e = fma(scale, q, scale - _F(1.0))
    far = e / (e + _F(2.0))
    far = far if x >= _F(0.0) else -far
    return near if y <= _F(1.25) else far


def tanh(x):
    """tanh x in x's precision, vectorisable (see `_tanh64`, `_tanh32`)."""
    return math.tanh(x)


# Inlined into the lane loops (a call per lane does not vectorise: 1.7x slower forward pass).
# numba's SSA self-check then warns that a variable of the inlined exp's conditional expressions
# "is not in scope" (NumbaIRAssumptionWarning, a pedantic internal check): the compiled code is
# right (the law tests; float64 bits equal to those before the overload), so that one is hushed.
warnings.filterwarnings("ignore", message=".*variable '_tanh__locals",
                        category=NumbaIRAssumptionWarning)


@overload(tanh, inline="always", jit_options=dict(fastmath=FASTMATH, error_model="numpy"))
def _tanh(x):
    if x == types.float32:
        return lambda x: _tanh32(x)
    return lambda x: _tanh64(x)


def zeros(shape: tuple, dtype=np.float64) -> np.ndarray:
    """np.zeros whose data start on a cache line (`ALIGN` bytes; numpy gives small arrays 16),
    for arrays of blocks of lanes: with rows of 8 float64 every row is then one line."""
    dtype = np.dtype(dtype)
    size = int(np.prod(shape)) * dtype.itemsize
    raw = np.zeros(size + ALIGN, np.uint8)
    start = -raw.ctypes.data % ALIGN
    return raw[start:start + size].view(dtype).reshape(shape)


def padded(count: int, dtype) -> int:
    """`count` lanes rounded up to whole blocks of `dtype`."""
    return -(-count // width(dtype)) * width(dtype)
