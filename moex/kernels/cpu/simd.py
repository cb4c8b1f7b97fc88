"""Building blocks that let numba put independent chains side by side in SIMD lanes.

Without Intel's SVML (not in the PyPI llvmlite), LLVM cannot vectorise calls to libm's exp, log
or tanh; `exp`, `log` and `tanh` below are written with arithmetic and bit casts only, so a loop
over lanes compiles to vector instructions. `lanes` is a small stack array: in a loop over its
`LB` entries with a literal bound, LLVM keeps it in registers (a heap accumulator is stored and
reloaded on every iteration because it might alias the arrays it reads). numba leaves LLVM's SLP
vectoriser off by default; it is what turns those unrolled lane loops into vector instructions.
"""

import numba
import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

numba.config.SLP_VECTORIZE = 1  # read when numba builds its pass manager, before compiling

LB = 8  # lanes per block: one AVX-512 vector of float64 (two AVX2 vectors)
# Stack arrays start on a cache line: a vector of LB float64 (64 bytes) then never straddles
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
def _as_bits(typingctx, x):
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _as_float(typingctx, x):
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


def _stack_array(context, builder, dtype, rows):
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
    """A 1-D array of `LB` elements of `like`'s dtype on the stack (uninitialised); in a loop
    over its entries with the literal bound `LB` it lives in a vector register."""
    dtype = like.dtype
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
    """A (rows, LB) array of `like`'s dtype on the stack (uninitialised), for the state of one
    block of lanes. Unlike a heap array it cannot alias the arrays a kernel reads, so LLVM may
    reorder loads and stores around it and vectorise the lane loops. Call it once per function,
    outside loops (the memory lives until the function returns)."""
    array_type = types.Array(like.dtype, 2, "C")

    def codegen(context, builder, signature, args):
        return _stack_array(context, builder, like.dtype, args[1])._getvalue()

    return array_type(like, types.intp), codegen


_LOG2E = 1.4426950408889634
_LN2 = 0.6931471805599453
_LN2_HI = 0.693145751953125  # ln 2 split so that k · _LN2_HI is exact (Cody-Waite)
_LN2_LO = 1.42860682030941723212e-6
_ROUND = 6755399441055744.0  # 1.5 · 2^52: x + _ROUND holds round(x) in its low bits


@njit(inline="always", **JIT)
def exp(x):
    """e^x for |x| <= 700 (clamped), relative error below 1e-15."""
    x = float(x)
    x = x if x > -700.0 else -700.0  # conditional expressions vectorise; min/max branch
    x = x if x < 700.0 else 700.0
    shifted = fma(x, _LOG2E, _ROUND)
    k = shifted - _ROUND  # round(x / ln 2)
    r = fma(k, -_LN2_LO, fma(k, -_LN2_HI, x))  # |r| <= ln 2 / 2
    p = 1.0 / 39916800.0  # Taylor series of e^r to degree 11
    p = fma(p, r, 1.0 / 3628800.0)
    p = fma(p, r, 1.0 / 362880.0)
    p = fma(p, r, 1.0 / 40320.0)
    p = fma(p, r, 1.0 / 5040.0)
    p = fma(p, r, 1.0 / 720.0)
    p = fma(p, r, 1.0 / 120.0)
    p = fma(p, r, 1.0 / 24.0)
    p = fma(p, r, 1.0 / 6.0)
    p = fma(p, r, 0.5)
    p = fma(p, r, 1.0)
    p = fma(p, r, 1.0)
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
def tanh(x):
    """tanh x with absolute error below 1e-14."""
    return 1.0 - 2.0 / (exp(2.0 * x) + 1.0)


def zeros(shape: tuple, dtype=np.float64) -> np.ndarray:
    """np.zeros whose data start on a cache line (`ALIGN` bytes; numpy gives small arrays 16),
    for arrays of blocks of lanes: with rows of LB float64 every row is then one line."""
    dtype = np.dtype(dtype)
    size = int(np.prod(shape)) * dtype.itemsize
    raw = np.zeros(size + ALIGN, np.uint8)
    start = -raw.ctypes.data % ALIGN
    return raw[start:start + size].view(dtype).reshape(shape)


def padded(count: int) -> int:
    """`count` lanes rounded up to whole blocks."""
    return -(-count // LB) * LB
