"""The LQ data as arrays at their tensors' addresses, inside the compiled kernels.

A tensor's numpy view (``Tensor.numpy()``) costs about 1.8 us, and a small solve passes
nine of them: at ``(n, m) = (4, 1)``, ``B = 1``, ``T = 100`` that was more than the
Riccati pass itself (about 10 us). The launchers of the small solves pass each tensor's
address (``Tensor.data_ptr()``, 0.1 us) and its batch and time sizes instead, and these
helpers make the arrays inside the kernel (``numba.carray``: a view, nothing copied).

The caller (:func:`.dispatch.gain_addresses`) has checked every shape, dtype and
contiguity, and keeps the tensors alive for the call: an array made here is only a
view of memory the caller owns.
"""

from __future__ import annotations

import numba
from numba import types
from numba.extending import intrinsic

from . import _numba_cache  # noqa: F401 (before any kernel: the library's cache stamp)


@intrinsic
def _pointer(typingctx, address, like):
    """``address`` (an integer) as a pointer to ``like``'s dtype."""
    sig = types.CPointer(like.dtype)(address, like)

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], context.get_value_type(signature.return_type))

    return sig, codegen


@numba.njit(cache=True, nogil=True, inline="always")
def pieces_at(addresses, dims, x0_address, nb, n, m, like):
    """The kernels' ``pieces`` ``(A, B, c, Q, R, S, q, r)`` and ``x0 (nb, n)`` at
    ``addresses`` (8 integers) and ``x0_address``, in
    ``like``'s dtype; ``dims`` (16 integers): each piece's batch and time sizes, ``(0,
    0)`` for an absent piece (an empty array, as the array launchers pass)."""
    d = dims
    A = numba.carray(_pointer(addresses[0], like), (d[0], d[1], n, n))
    B = numba.carray(_pointer(addresses[1], like), (d[2], d[3], n, m))
    c = numba.carray(_pointer(addresses[2], like), (d[4], d[5], n))
    Q = numba.carray(_pointer(addresses[3], like), (d[6], d[7], n, n))
    R = numba.carray(_pointer(addresses[4], like), (d[8], d[9], m, m))
    S = numba.carray(_pointer(addresses[5], like), (d[10], d[11], m, n))
    q = numba.carray(_pointer(addresses[6], like), (d[12], d[13], n))
    r = numba.carray(_pointer(addresses[7], like), (d[14], d[15], m))
    x0 = numba.carray(_pointer(x0_address, like), (nb, n))
    return (A, B, c, Q, R, S, q, r), x0
