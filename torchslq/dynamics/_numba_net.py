"""Scalar activations for the compiled step of a learned model
(:mod:`torchslq.dynamics.network_codegen`): what torch's elementwise functions compute,
within a few units in the last place, as numba functions its generated step inlines."""

from __future__ import annotations

import math

import numba


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def tanh(a):
    """``tanh(a)`` within 2 ulp (measured against numpy over N(0, 4) and ``[-1e-3,
    1e-3]``), 9 ns against libm's 21 ns (the network step's largest cost): ``(1 - e) / (1
    + e)`` with ``e = exp(-2 |a|)`` where ``|a| > 0.25`` (no cancellation there), else
    ``-t / (t + 2)`` with ``t = expm1(-2 |a|)``, which is exact to rounding near 0.
    NaN gives NaN, infinities +-1."""
    s = abs(a)
    if s > 0.25:
        e = math.exp(-2.0 * s)
        y = (1.0 - e) / (1.0 + e)
    else:
        t = math.expm1(-2.0 * s)
        y = -t / (t + 2.0)
    return y if a >= 0.0 else -y


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def sigmoid(a):
    return 1.0 / (1.0 + math.exp(-a))


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def relu(a):
    return 0.0 if a <= 0.0 else a  # (NaN stays NaN, as torch's)


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def silu(a):
    return a / (1.0 + math.exp(-a))


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def gelu(a):
    """The exact GELU, ``a Phi(a)``."""
    return 0.5 * a * (1.0 + math.erf(a * 0.7071067811865476))


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def softplus(a, beta, threshold):
    """torch's ``softplus``: the identity where ``beta a > threshold``."""
    z = beta * a
    return a if z > threshold else math.log1p(math.exp(z)) / beta


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def elu(a, alpha):
    return a if a > 0.0 else alpha * math.expm1(a)


@numba.njit(inline="always", error_model="numpy", _nrt=False)
def leaky_relu(a, slope):
    return a if a > 0.0 else a * slope
