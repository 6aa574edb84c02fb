"""Scalar activations for the compiled step of a learned model
(:mod:`torchslq.dynamics.network_codegen`): what torch's elementwise functions compute,
within a few units in the last place, as numba functions its generated step inlines."""

from __future__ import annotations

import math

import numba
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from .._backend import _numba_cache  # noqa: F401 (before any kernel: the library's cache stamp)


@intrinsic
def _as_float64(typingctx, i):
    """The float64 whose bits are the int64 ``i`` (a register move; SIMD in a loop)."""
    if not isinstance(i, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


@intrinsic
def _as_int64(typingctx, x):
    """The int64 whose bits are the float64 ``x``."""
    if not isinstance(x, types.Float):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def stack_array(typingctx, size):
    """A 1-d float64 array of ``size`` (an integer literal) entries on the calling
    function's stack: no allocation and no reference count, unlike ``np.empty`` (about
    0.2 of the 1 us a 5-64-64-4 network step took with four of them). It lives until
    that function returns; the generated steps use it for the nodes of one call only
    and never return it."""
    if not isinstance(size, types.IntegerLiteral) or size.literal_value < 1:
        return None
    n = size.literal_value
    array_type = types.Array(types.float64, 1, "C")

    def codegen(context, builder, signature, args):
        data = cgutils.alloca_once(builder, ir.DoubleType(), size=n)  # (in the entry block)
        array = context.make_array(array_type)(context, builder)
        itemsize = context.get_constant(types.intp, 8)
        context.populate_array(
            array,
            data=data,
            shape=[context.get_constant(types.intp, n)],
            strides=[itemsize],
            itemsize=itemsize,
            meminfo=None,
        )
        return array._getvalue()

    return array_type(size), codegen


_LN2_HI = 6.93147180369123816490e-01  # ln 2 in two pieces: k ln2_hi is exact for |k| < 2^20
_LN2_LO = 1.90821492927058770002e-10
_INV_LN2 = 1.44269504088896338700e00
_ROUND = 6755399441055744.0  # 1.5 * 2^52: x + _ROUND rounds x to an integer in the low bits
_ROUND_BITS = 0x4338000000000000  # the bits of _ROUND


@numba.njit(inline="always", error_model="numpy", fastmath={"contract"}, _nrt=False)
def _reduced(y):
    """``(2^h, 2^(k - h), expm1(r))`` for ``y = k ln 2 + r``, ``|r| <= ln(2) / 2``, ``h =
    k // 2`` (``y`` in ``[-1100, 1100]``): ``k`` rounded by adding 1.5 * 2^52, each
    power of two built from its exponent bits (normal numbers for every such ``k``, so
    that their product is ``2^k`` even where that overflows or is subnormal),
    ``expm1(r)`` by its Taylor series to ``r^14`` (truncation below 1e-19 relative).
    Branch-free: SIMD in a loop."""
    t = y * _INV_LN2 + _ROUND
    k = _as_int64(t) - _ROUND_BITS
    kf = t - _ROUND
    r = (y - kf * _LN2_HI) - kf * _LN2_LO
    h = k >> 1
    s1 = _as_float64((h + 1023) << 52)
    s2 = _as_float64(((k - h) + 1023) << 52)
    p = 1.0 / 87178291200.0
    p = p * r + 1.0 / 6227020800.0
    p = p * r + 1.0 / 479001600.0
    p = p * r + 1.0 / 39916800.0
    p = p * r + 1.0 / 3628800.0
    p = p * r + 1.0 / 362880.0
    p = p * r + 1.0 / 40320.0
    p = p * r + 1.0 / 5040.0
    p = p * r + 1.0 / 720.0
    p = p * r + 1.0 / 120.0
    p = p * r + 1.0 / 24.0
    p = p * r + 1.0 / 6.0
    p = p * r + 0.5
    return s1, s2, p * (r * r) + r


@numba.njit(inline="always", error_model="numpy", fastmath={"contract"}, _nrt=False)
def exp(a):
    """``exp(a)`` within 2 ulp, branch-free (:func:`_reduced`); overflows to inf above
    709.78, underflows to 0 below -745. NaN gives NaN."""
    s1, s2, em1 = _reduced(min(max(a, -1100.0), 1100.0))
    return ((1.0 + em1) * s1) * s2


@numba.njit(inline="always", error_model="numpy", fastmath={"contract"}, _nrt=False)
def _expm1_nonpositive(y):
    """``expm1(y)`` for ``y <= 0`` (clamped to ``[-90, 0]``: -1 to double precision below
    -90; a positive ``y``, whose value a caller's select discards, gives 0):
    ``2^k expm1(r) + (2^k - 1)``, exact in its last step's cancellation."""
    s1, s2, em1 = _reduced(min(max(y, -90.0), 0.0))
    scale = s1 * s2  # 2^k (k >= -130: a normal number)
    return scale * em1 + (scale - 1.0)


@numba.njit(inline="always", error_model="numpy", fastmath={"contract"}, _nrt=False)
def tanh(a):
    """``tanh(a)`` within 3 ulp of torch's (measured over N(0, 3^2), tiny inputs and a
    grid of [-20, 20]), as ``-e / (e + 2)`` with ``e = expm1(-2 |a|)``, the sign of ``a``
    copied on.

    Branch-free, so that the loop over a layer's entries that inlines it compiles to SIMD
    code (2.7 ns an entry against 6.8 ns for libm's ``exp`` behind a branch; a 64-wide
    tanh layer is most of a small network step's time). NaN gives NaN, infinities +-1,
    -0 -0."""
    e = _expm1_nonpositive(-2.0 * abs(a))
    return math.copysign(-e / (e + 2.0), a)


@numba.njit(inline="always", error_model="numpy", fastmath={"contract"}, _nrt=False)
def sigmoid(a):
    """``1 / (1 + exp(-a))`` on the branch-free :func:`exp` (2.1 ns an entry in a loop
    against 5.5 ns on libm's)."""
    return 1.0 / (1.0 + exp(-a))


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def relu(a):
    return 0.0 if a <= 0.0 else a  # (NaN stays NaN, as torch's)


@numba.njit(inline="always", error_model="numpy", fastmath={"contract"}, _nrt=False)
def silu(a):
    return a / (1.0 + exp(-a))


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def gelu(a):
    """The exact GELU, ``a Phi(a)``."""
    return 0.5 * a * (1.0 + math.erf(a * 0.7071067811865476))


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def softplus(a, beta, threshold):
    """torch's ``softplus``: the identity where ``beta a > threshold``."""
    z = beta * a
    return a if z > threshold else math.log1p(math.exp(z)) / beta


@numba.njit(inline="always", error_model="numpy", fastmath={"contract"}, _nrt=False)
def elu(a, alpha):
    return a if a > 0.0 else alpha * _expm1_nonpositive(a)


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def leaky_relu(a, slope):
    return a if a > 0.0 else a * slope


# ---------------------------------------------------------------- first derivatives
# (the generated Jacobians' activation slopes, :mod:`torchslq.dynamics.network_reverse`;
# the simpler ones are written inline from the activation's input and output)


@numba.njit(inline="always", error_model="numpy", fastmath={"contract"}, _nrt=False)
def silu_slope(a):
    """``d silu / da = s (1 + a (1 - s))``, ``s = sigmoid(a)``."""
    s = sigmoid(a)
    return s * (1.0 + a * (1.0 - s))


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def gelu_slope(a):
    """``d gelu / da = Phi(a) + a phi(a)`` (the exact GELU)."""
    return 0.5 * (1.0 + math.erf(a * 0.7071067811865476)) + a * 0.3989422804014327 * math.exp(
        -0.5 * a * a
    )


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def softplus_slope(a, beta, threshold):
    """torch's ``softplus`` slope: 1 where ``beta a > threshold``, else ``sigmoid(beta a)``."""
    z = beta * a
    return 1.0 if z > threshold else 1.0 / (1.0 + math.exp(-z))


# ---------------------------------------------------------------- second derivatives
# (the generated Hessians' activation curvatures, as the first derivatives above)


@numba.njit(inline="always", error_model="numpy", fastmath={"contract"}, _nrt=False)
def silu_curve(a):
    """``d2 silu / da2 = s (1 - s) (2 + a (1 - 2 s))``, ``s = sigmoid(a)``."""
    s = sigmoid(a)
    return s * (1.0 - s) * (2.0 + a * (1.0 - 2.0 * s))


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def gelu_curve(a):
    """``d2 gelu / da2 = phi(a) (2 - a^2)`` (the exact GELU)."""
    return 0.3989422804014327 * math.exp(-0.5 * a * a) * (2.0 - a * a)


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def softplus_curve(a, beta, threshold):
    """torch's ``softplus`` curvature: 0 where ``beta a > threshold``, else ``beta s (1 -
    s)``, ``s = sigmoid(beta a)``."""
    z = beta * a
    if z > threshold:
        return 0.0
    s = 1.0 / (1.0 + math.exp(-z))
    return beta * s * (1.0 - s)


@numba.njit(nogil=True, cache=True, fastmath={"contract", "reassoc"}, error_model="numpy")
def chain_curvature(rb, k, wo, C, TZ, HC):
    """``HC[i, o] += TZ_i' diag(C_io) TZ_i`` for the rows ``i < rb`` of a block: an
    activation's second-order term in a layer chain's Hessians
    (:mod:`torchslq.dynamics.network_chains`), ``C (rb * wo, width)`` the outputs'
    sensitivities times the activation's curvature, ``TZ (rb * k, width)`` the tangents
    of its input, ``HC (rb, wo, k, k)``. Its own function for ``reassoc``: each entry is
    a sum over the layer's width, which LLVM vectorises only when it may reorder it
    (the row sweep's sums keep their order)."""
    width = C.shape[1]
    for i in range(rb):
        for c in range(k):
            for d in range(c + 1):
                for o in range(wo):
                    acc = 0.0
                    for q in range(width):
                        acc += C[i * wo + o, q] * TZ[i * k + c, q] * TZ[i * k + d, q]
                    HC[i, o, c, d] += acc
                    if d != c:
                        HC[i, o, d, c] += acc
