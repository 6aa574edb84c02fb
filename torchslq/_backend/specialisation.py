"""Which LQ problem sizes get kernels compiled for their own ``(n, m)``.

Small problems run on kernels compiled for their sizes: the gain-form passes with
constant trip counts (:func:`._numba_kernels.size_witness`, up to
:data:`~._numba_kernels.FIXED_MAX_N` states and :data:`~._numba_kernels.FIXED_MAX_M`
controls) and the pass written out as straight-line code (:mod:`.gain_codegen`). Each
new size is compiled once, 5-20 s on one core, then cached on disk. A program that
meets many sizes, and cares more for its first calls than for the last factor of two
on them, names the sizes that are worth it with :func:`limit_specialised_sizes`; every
other size then runs the kernels that read their sizes at run time (the same results
to rounding, compiled once for all sizes). :func:`limit_specialised_qp_sizes` does the
same for the compiled interior point of :mod:`torchslq.lqdo` (its kernels are compiled
for the reduced size ``r`` of a QP, the variables left free by its equality
constraints: 10-12 s for each ``r``, the set-up's and the iterations' kernels).
"""

from __future__ import annotations

from collections.abc import Iterable

_only: frozenset[tuple[int, int]] | None = None


def specialised(n: int, m: int) -> bool:
    """Whether ``n`` states and ``m`` controls may get kernels of their own (the size
    limits of each kind of kernel apply on top of this)."""
    return _only is None or (n, m) in _only


def limit_specialised_sizes(
    sizes: Iterable[tuple[int, int]] | None,
) -> frozenset[tuple[int, int]] | None:
    """Compile size-specialised LQ kernels only for ``sizes`` (pairs ``(n, m)``); None
    (the default) lets every size small enough have them. Returns the previous setting
    (pass it back to restore). Process-wide; kernels already compiled stay in use for
    the sizes still named."""
    global _only
    old = _only
    if sizes is None:
        _only = None
    else:
        pairs = []
        for pair in sizes:
            if len(pair) != 2 or not all(isinstance(v, int) and v >= 1 for v in pair):
                raise ValueError(f"sizes must be pairs (n, m) of positive ints, got {pair!r}")
            pairs.append((int(pair[0]), int(pair[1])))
        _only = frozenset(pairs)
    return old


_only_qp: frozenset[int] | None = None


def specialised_qp(r: int) -> bool:
    """Whether a QP of reduced size ``r`` may get interior-point kernels of its own (up
    to :data:`torchslq._backend._numba_qp.WITNESS_MAX_R`)."""
    return _only_qp is None or r in _only_qp


def limit_specialised_qp_sizes(sizes: Iterable[int] | None) -> frozenset[int] | None:
    """Compile the QP interior point's kernels (the reduced Newton system's set-up and
    iterations of :func:`torchslq.lqdo.qp_solve` on the CPU) for their own reduced size
    ``r`` (the number of variables left free by the equality constraints) only for
    ``sizes``; None (the default) lets every ``r`` small enough have them. Every other
    ``r`` runs the kernels that read it at run time (the same results, compiled once).
    Returns the previous setting (pass it back to restore). Process-wide."""
    global _only_qp
    old = _only_qp
    if sizes is None:
        _only_qp = None
    else:
        rs = []
        for r in sizes:
            if not isinstance(r, int) or isinstance(r, bool) or r < 1:
                raise ValueError(f"sizes must be positive ints (reduced sizes r), got {r!r}")
            rs.append(int(r))
        _only_qp = frozenset(rs)
    return old
