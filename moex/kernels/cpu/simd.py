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
from numba import types
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
_C = tuple(_F(1.0 / math.factorial(n)) for n in range(2, 9))  # 1/2!, ..., 1/8!
# (tanh x - x) / x³ as a polynomial in x² on |x| <= 0.625: weighted least squares (relative error
# of tanh) at Chebyshev nodes, rounded to float32; within 0.8 ulp there in float32 arithmetic
_T = tuple(_F(c) for c in (
    -0.3333333134651184, 0.1333320140838623, -0.053946252912282944, 0.021698208525776863,
    -0.008171784691512585, 0.0021382225677371025))
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
    scale = b.shl(b.add(b.bitcast(shifted, _I64), ir.Constant(_I64, 1023)), ir.Constant(_I64, 52))
    return b.fmul(p, b.bitcast(scale, _F64))  # times 2^k


def _log_ir(builder, x):
    """ln x of a double (see `log`)."""
    f, b = _Emit(builder, _F64), builder
    bits = b.bitcast(x, _I64)
    e = b.sub(b.and_(b.ashr(bits, ir.Constant(_I64, 52)), ir.Constant(_I64, 0x7FF)),
              ir.Constant(_I64, 1023))
    m = b.bitcast(b.or_(b.and_(bits, ir.Constant(_I64, 0xFFFFFFFFFFFFF)),
                        ir.Constant(_I64, 0x3FF0000000000000)), _F64)  # in [1, 2)
    big = b.fcmp_ordered(">", m, f.c(1.4142135623730951))  # bring m into [√½, √2): |z| <= 0.172
    m = b.select(big, b.fmul(m, f.c(0.5)), m)
    e = b.select(big, b.add(e, ir.Constant(_I64, 1)), e)
    z = b.fdiv(b.fsub(m, f.c(1.0)), b.fadd(m, f.c(1.0)))
    p = f.poly(b.fmul(z, z), [1.0 / n for n in range(21, 0, -2)])  # 2 atanh z / (2z)
    return f.fma(b.fmul(f.c(2.0), z), p, b.fmul(b.sitofp(e, _F64), f.c(_LN2)))


def _tanh64_ir(builder, x):
    """tanh of a double (see `tanh`)."""
    f, b = _Emit(builder, _F64), builder
    e = _exp_ir(b, b.fmul(f.c(2.0), x))
    return b.fsub(f.c(1.0), b.fdiv(f.c(2.0), b.fadd(e, f.c(1.0))))


def _tanh32_ir(builder, x):
    """tanh of a float in float32 arithmetic (see `tanh`)."""
    f, b = _Emit(builder, _F32), builder
    z = b.fmul(x, x)
    near = f.fma(b.fmul(x, z), f.poly(z, _T[::-1]), x)
    y = b.call(b.module.declare_intrinsic("llvm.fabs", [_F32]), [b.fadd(x, x)])
    y = f.clamp(y, 0.0, 80.0)  # tanh(40) rounds to 1 in float32
    shifted = f.fma(y, _F(1.4426950408889634), _ROUND32)
    k = b.fsub(shifted, f.c(_ROUND32))  # round(y / ln 2)
    r = f.fma(k, -_LN2_LO32, f.fma(k, -_LN2_HI32, y))
    q = f.fma(b.fmul(r, r), f.poly(r, _C[::-1]), r)  # e^r - 1
    bits = b.shl(b.add(b.sext(b.bitcast(shifted, _I32), _I64), ir.Constant(_I64, 127)),
                 ir.Constant(_I64, 23))
    scale = b.bitcast(b.trunc(bits, _I32), _F32)  # 2^k
    e = f.fma(scale, q, b.fsub(scale, f.c(1.0)))
    far = b.fdiv(e, b.fadd(e, f.c(2.0)))
    far = b.select(b.fcmp_ordered(">=", x, f.c(0.0)), far, b.fneg(far))
    return b.select(b.fcmp_ordered("<=", y, f.c(1.25)), near, far)


def _elementwise(emit, x, kind=types.float64):
    """The signature and code of an intrinsic of one float argument x that returns
    `emit(builder, x)` (x cast to `kind`)."""
    def codegen(context, builder, signature, args):
        return emit(builder, context.cast(builder, args[0], signature.args[0], kind))

    return kind(x), codegen


@intrinsic
def exp(typingctx, x):
    """e^x for |x| <= 700 (clamped), relative error below 1e-14 (the degree-11 Taylor series
    at |r| = ln 2 / 2: 6e-15); in float64 whatever x's type."""
    return _elementwise(_exp_ir, x)


@intrinsic
def log(typingctx, x):
    """ln x for normal x > 0, error below 1e-15: x = m 2^e, ln m = 2 atanh((m-1)/(m+1)); in
    float64 whatever x's type."""
    return _elementwise(_log_ir, x)


@intrinsic
def tanh(typingctx, x):
    """tanh x in x's precision. float64: 1 - 2 / (e^{2x} + 1), absolute error below 1e-14.
    float32, in float32 arithmetic (16 lanes a vector), within 2 ulp of the exact value
    (tests/test_kernels.py): for |x| <= 0.625 x + x³ P(x²); above, tanh |x| = e / (e + 2) with
    e = e^{2|x|} - 1 = 2^k (e^r - 1) + 2^k - 1, e^r - 1 = r + r²(1/2! + ... + r^6/8!)
    (|r| <= ln 2 / 2). Both are computed and one selected (vectorised)."""
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


def padded(count: int, dtype) -> int:
    """`count` lanes rounded up to whole blocks of `dtype`."""
    return -(-count // width(dtype)) * width(dtype)
