"""Fused per-element kernels of the parallel-in-time LQ scan (Triton).

Why: the torch-op scan (:mod:`.scan`) builds every combination of two value-function
elements out of batched BLAS/LAPACK calls on tiny matrices (``lu_factor``, two
``lu_solve``, five ``matmul``, ``cat``): a dozen kernels per level, each re-reading the
elements from memory, and LAPACK's batched small-matrix routines are slow on a GPU. At
large ``B * T`` the scan is then throughput-bound far below the device's bandwidth
(0.13 us per element at ``B * T = 16.7M`` on an H100, ``parallel_lq_cuda.md``). Here
each step is one kernel: a lane holds one element, reads its numbers once, computes in
registers and writes once.

The kernels are generated per state and control size ``(n, m)`` as straight-line code
(every matrix entry a variable; zeros known at generation time are skipped) and compiled
by Triton for the tensor's dtype. They compute the same quantities as the torch ops of
:mod:`.scan`, equation by equation:

* :func:`value_elements` - the elements (S1) of every step, ``R`` by Cholesky;
* :func:`combine_value` - the paper's operator (S2), ``(I + C_ij J_jk)^{-1}`` applied by
  Gauss-Jordan elimination with partial pivoting (``I + C J`` is not symmetric, and
  without pivoting a non-singular one can meet a zero pivot); the symmetric results
  ``C`` and ``J`` are computed on and above the diagonal and mirrored;
* :func:`gains` - the gains (S4) and the value's constant increments;
* :func:`combine_affine` - the composition of affine maps (S5);
* :func:`closed_loop` - ``(A + B K, B k + c)`` of every step.

If a kernel fails to compile or launch (a Triton or toolchain that cannot build it), the
scan warns once and runs as torch ops from then on (:class:`FusedKernelError`).

A singular pivot (exactly zero, as LAPACK's ``info``) or a non-positive Cholesky pivot
is reported per element, as the torch ops report it, so the scan's redo of failed
elements by the recursion is unchanged.

The kernels run where :func:`enabled` says: on CUDA tensors when Triton is installed and
``n, m <= MAX_DIM`` (4). The straight-line code grows as ``n^3``. Above ``n = 4`` the
float64 combination spills registers (ptxas for sm_90: 344 bytes at ``n = 5``, 1.8 kB at
``n = 6``, 65 kB at ``n = 8``) and no GPU has measured those sizes: the torch ops serve
them. Compile time: Triton's coalescing pass, which walks the whole kernel for every load
and store, took 98% of it (the value combination for an H100 on a 2-core CPU: 6.7 s at
``n = 4``, 128 s at ``n = 6``) and changes nothing in these kernels' code, so
:func:`_without_coalescing` skips it (0.9 s and 2 s). Each kernel compiles once per dtype
(no specialisation on the levels' strides) and Triton keeps it in its on-disk cache.
:func:`interpreted` runs them on CPU tensors through Triton's interpreter, which the
tests use to check them without a GPU; :func:`disabled` switches them off (benchmarks
compare the two).
"""

from __future__ import annotations

import contextlib
import importlib.util
import inspect
import linecache
import threading
import warnings
from collections.abc import Iterator, Sequence

import torch
from torch import Tensor

# optional: the torch ops of .scan serve where Triton is missing. Imported on first use
# (importing it costs about 0.1 s, which a CPU-only process need not pay)
HAVE_TRITON = importlib.util.find_spec("triton") is not None

__all__ = [
    "MAX_DIM",
    "FusedKernelError",
    "closed_loop",
    "combine_affine",
    "combine_value",
    "disabled",
    "enabled",
    "gains",
    "interpreted",
    "kernel_source",
    "value_elements",
]

MAX_DIM = 4
_BLOCK = 128
# one lane per thread; multiply-adds contracted to FMAs (Triton's default until 3.10,
# asked for by name so that later versions keep it)
_GPU_OPTIONS = {"num_warps": 4, "enable_fp_fusion": True}
_MODE: dict = {"interpret": False, "off": False, "broken": None}


class FusedKernelError(RuntimeError):
    """A fused kernel failed to compile or launch. The scan's entry points catch it and
    run as torch ops; :func:`enabled` is False for the rest of the process."""


@contextlib.contextmanager
def _mode(**changes) -> Iterator[None]:
    old = dict(_MODE)
    _MODE.update(changes)
    try:
        yield
    finally:
        _MODE.update(old)


def interpreted() -> contextlib.AbstractContextManager[None]:
    """Within: the kernels run on CPU tensors too, through Triton's interpreter (slow;
    for tests)."""
    return _mode(interpret=True, off=False)


def disabled() -> contextlib.AbstractContextManager[None]:
    """Within: the scan uses its torch ops everywhere (to compare the two)."""
    return _mode(off=True)


def enabled(t: Tensor, n: int, m: int = 1) -> bool:
    """Whether the fused kernels serve data like ``t`` with state size ``n`` and control
    size ``m``."""
    if not HAVE_TRITON or _MODE["off"] or _MODE["broken"]:
        return False
    if not (1 <= n <= MAX_DIM and 1 <= m <= MAX_DIM):
        return False
    if t.dtype not in (torch.float32, torch.float64):
        return False
    return t.is_cuda or (_MODE["interpret"] and t.device.type == "cpu")


# ----------------------------------------------------------------------------- code emitter


class _Emitter:
    """Straight-line kernel source: each value a fresh variable (a ``(BLOCK,)`` vector of
    lanes, one element per lane); matrices are lists of rows of variable names, ``None``
    for an entry known to be zero."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.args: list[str] = []
        self._k = 0

    def let(self, expr: str) -> str:
        name = f"v{self._k}"
        self._k += 1
        self.lines.append(f"{name} = {expr}")
        return name

    def tensor(self, name: str) -> str:
        self.args.append(name)
        return name

    def _addr(self, t: str, i: int, j: int) -> str:
        return f"{t} + o_{t} + {i} * {t}_si + {j} * {t}_sj"

    def load(self, t: str, i: int = 0, j: int = 0) -> str:
        return self.let(f"tl.load({self._addr(t, i, j)}, mask=mask, other=0.0)")

    def load_mat(self, t: str, rows: int, cols: int, i0: int = 0, j0: int = 0) -> list[list[str]]:
        return [[self.load(t, i0 + i, j0 + j) for j in range(cols)] for i in range(rows)]

    def load_sym(self, t: str, size: int) -> list[list[str]]:
        """A symmetric matrix from its upper triangle."""
        X = [[None] * size for _ in range(size)]
        for i in range(size):
            for j in range(i, size):
                X[i][j] = X[j][i] = self.load(t, i, j)
        return X

    def load_vec(self, t: str, size: int, i0: int = 0) -> list[str]:
        return [self.load(t, i0 + i) for i in range(size)]

    def load_flag(self, t: str) -> str:
        """A per-element bool (stored as uint8)."""
        return self.let(f"tl.load({t} + o_{t}, mask=mask, other=0) != 0")

    def store_flag(self, t: str, value: str) -> None:
        self.lines.append(f"tl.store({t} + o_{t}, ({value}).to(tl.uint8), mask=mask)")

    def store(self, t: str, value: str | None, i: int = 0, j: int = 0) -> None:
        value = "zero" if value is None else value
        self.lines.append(f"tl.store({self._addr(t, i, j)}, {value}, mask=mask)")

    def store_mat(self, t: str, X: list[list[str | None]]) -> None:
        for i, row in enumerate(X):
            for j, x in enumerate(row):
                self.store(t, x, i, j)

    def store_vec(self, t: str, x: list[str | None]) -> None:
        for i, xi in enumerate(x):
            self.store(t, xi, i)

    # arithmetic on names; None is zero
    def lin(
        self,
        terms: Sequence[tuple[str | None, str | None]],
        add: str | None = None,
        sign: str = "+",
    ) -> str | None:
        """``add + sign * sum(a * b)`` over the terms with neither factor zero."""
        prods = [f"{a} * {b}" for a, b in terms if a is not None and b is not None]
        if not prods:
            return add
        body = " + ".join(prods)
        if add is None:
            return self.let(body if sign == "+" else f"-({body})")
        return self.let(f"{add} {sign} ({body})")

    def add(self, a: str | None, b: str | None, sign: str = "+") -> str | None:
        if b is None:
            return a
        if a is None:
            return b if sign == "+" else self.let(f"-{b}")
        return self.let(f"{a} {sign} {b}")

    def scale(self, a: str | None, s: str) -> str | None:
        return None if a is None else self.let(f"{a} * {s}")

    def matmul(self, X, Y, add=None, sign="+", transpose_x=False):
        """``add + sign * op(X) @ Y`` with ``op`` the transpose if ``transpose_x``."""
        rows = len(X[0]) if transpose_x else len(X)
        inner = len(Y)
        cols = len(Y[0])

        def x(i, k):
            return X[k][i] if transpose_x else X[i][k]

        return [
            [
                self.lin(
                    [(x(i, k), Y[k][j]) for k in range(inner)],
                    None if add is None else add[i][j],
                    sign,
                )
                for j in range(cols)
            ]
            for i in range(rows)
        ]

    def matvec(self, X, y, add=None, sign="+", transpose_x=False):
        col = [[v] for v in y]
        out = self.matmul(X, col, None if add is None else [[a] for a in add], sign, transpose_x)
        return [r[0] for r in out]

    def sym_product(self, X, Y, add=None):
        """``add + X @ Y'`` for a product known to be symmetric: entries on and above the
        diagonal, mirrored below."""
        size = len(X)
        out = [[None] * size for _ in range(size)]
        for i in range(size):
            for j in range(i, size):
                out[i][j] = self.lin(
                    [(X[i][k], Y[j][k]) for k in range(len(Y[0]))],
                    None if add is None else add[i][j],
                )
                out[j][i] = out[i][j]
        return out

    def materialise(self, x: str | None) -> str:
        return "zero" if x is None else x

    def cholesky(self, A):
        """Lower Cholesky factor of the symmetric ``A`` (its lower triangle read), the
        reciprocals of its diagonal and a flag ``ok`` (every pivot positive)."""
        size = len(A)
        L = [[None] * size for _ in range(size)]
        inv = [None] * size
        ok = None
        for j in range(size):
            d = self.lin([(L[j][k], L[j][k]) for k in range(j)], A[j][j], "-")
            d = self.materialise(d)
            okj = f"({d} > 0)"
            ok = self.let(okj if ok is None else f"{ok} & {okj}")
            L[j][j] = self.let(f"tl.sqrt({d})")
            inv[j] = self.let(f"1.0 / {L[j][j]}")
            for i in range(j + 1, size):
                s = self.lin([(L[i][k], L[j][k]) for k in range(j)], A[i][j], "-")
                L[i][j] = self.scale(s, inv[j])
        return L, inv, ok

    def chol_solve(self, L, inv, Y):
        """``(L L')^{-1} Y``."""
        size, cols = len(L), len(Y[0])
        Z = [[None] * cols for _ in range(size)]
        for i in range(size):  # L Z = Y
            for c in range(cols):
                s = self.lin([(L[i][k], Z[k][c]) for k in range(i)], Y[i][c], "-")
                Z[i][c] = self.scale(s, inv[i])
        X = [[None] * cols for _ in range(size)]
        for i in reversed(range(size)):  # L' X = Z
            for c in range(cols):
                s = self.lin([(L[k][i], X[k][c]) for k in range(i + 1, size)], Z[i][c], "-")
                X[i][c] = self.scale(s, inv[i])
        return X

    def solve_pivoted(self, M, Y):
        """``M^{-1} Y`` by Gauss-Jordan elimination with partial pivoting, and a flag
        ``singular`` (a zero pivot). Row exchanges are selects per lane: for each column,
        each lower row is swapped up where its entry is larger in magnitude."""
        size = len(M)
        rows = [[self.materialise(v) for v in M[i] + Y[i]] for i in range(size)]
        width = len(rows[0])
        singular = None
        for k in range(size):
            for r in range(k + 1, size):
                cond = self.let(f"tl.abs({rows[r][k]}) > tl.abs({rows[k][k]})")
                for j in range(k, width):
                    a, b = rows[k][j], rows[r][j]
                    rows[k][j] = self.let(f"tl.where({cond}, {b}, {a})")
                    rows[r][j] = self.let(f"tl.where({cond}, {a}, {b})")
            p = rows[k][k]
            zk = f"({p} == 0)"
            singular = self.let(zk if singular is None else f"{singular} | {zk}")
            ip = self.let(f"1.0 / {p}")
            for j in range(k + 1, width):
                rows[k][j] = self.let(f"{rows[k][j]} * {ip}")
            for r in range(size):
                if r == k:
                    continue
                f = rows[r][k]
                for j in range(k + 1, width):
                    rows[r][j] = self.let(f"{rows[r][j]} - {f} * {rows[k][j]}")
        return [row[size:] for row in rows], singular

    def source(self, name: str) -> str:
        """The kernel ``name``: one lane per element of the flat ``(B, T')`` domain of
        ``N = B T'`` elements; every tensor argument ``X`` comes with its four strides
        (batch, time, row, column). The first argument is a float tensor: ``zero`` has
        its dtype."""
        params = []
        for t in self.args:
            params += [t, f"{t}_sb", f"{t}_st", f"{t}_si", f"{t}_sj"]
        head = [
            f"def {name}({', '.join(params)}, N, Tp, BLOCK: tl.constexpr):",
            "    i = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)",
            "    mask = i < N",
            "    bb = i // Tp",
            "    tt = i - bb * Tp",
            f"    zero = tl.full([BLOCK], 0, {self.args[0]}.dtype.element_ty)",
        ]
        head += [f"    o_{t} = bb * {t}_sb + tt * {t}_st" for t in self.args]
        return "\n".join(head + ["    " + line for line in self.lines]) + "\n"


# ----------------------------------------------------------------------------- kernels


def _src_value_elements(n: int, m: int) -> str:
    """Elements (S1) of the steps: ``F (n+1, m+n+1)``, ``H (m+n+1, m+n+1)`` -> ``A~, b, C,
    eta, J`` and ``bad`` (``R`` not positive definite). Each input is read where it is
    first needed and each result written as soon as it is known (fewer live registers)."""
    e = _Emitter()
    F, H = e.tensor("F"), e.tensor("H")
    oA, ob, oC, oeta, oJ, obad = (e.tensor(t) for t in ("oA", "ob", "oC", "oeta", "oJ", "obad"))
    R = [[e.load(H, i, j) if j <= i else None for j in range(m)] for i in range(m)]
    L, inv, ok = e.cholesky(R)
    Bm = e.load_mat(F, n, m)
    S = e.load_mat(H, m, n, 0, m)
    r = [e.load(H, i, m + n) for i in range(m)]
    rhs = [[Bm[j][i] for j in range(n)] + S[i] + [r[i]] for i in range(m)]  # [B', S, r]
    W = e.chol_solve(L, inv, rhs)
    WB = [row[:n] for row in W]
    WS = [row[n : 2 * n] for row in W]
    Wr = [row[2 * n] for row in W]
    e.store_mat(oA, e.matmul(Bm, WS, add=e.load_mat(F, n, n, 0, m), sign="-"))
    e.store_vec(ob, e.matvec(Bm, Wr, add=[e.load(F, i, m + n) for i in range(n)], sign="-"))
    e.store_mat(oC, e.sym_product(Bm, [[WB[k][j] for k in range(m)] for j in range(n)]))
    eta = e.matvec(S, Wr, transpose_x=True)  # S' R^-1 r - q
    e.store_vec(oeta, [e.add(eta[i], e.load(H, m + i, m + n), "-") for i in range(n)])
    StWS = e.sym_product(
        [[S[k][i] for k in range(m)] for i in range(n)],
        [[WS[k][j] for k in range(m)] for j in range(n)],
    )
    J = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i, n):
            qs = e.let(f"0.5 * ({e.load(H, m + i, m + j)} + {e.load(H, m + j, m + i)})")
            J[i][j] = J[j][i] = e.add(qs, StWS[i][j], "-")  # sym(Q) - S' R^-1 S
    e.store_mat(oJ, J)
    e.store_flag(obad, f"tl.where({ok}, 0, 1)")
    return e.source("value_elements_kernel")


def _src_combine_value(n: int) -> str:
    """The operator (S2) on ``e1 = (A1, b1, C1, eta1, J1, bad1)`` (earlier) and ``e2``.

    ``C`` and ``J`` are symmetric (the elements are built so, the results mirrored), so
    only their upper triangles are read. The order of the code keeps few values live at
    once (a float64 lane has 255 registers): each input is read where it is first
    needed and each result written as soon as it is known."""
    e = _Emitter()
    names = ("A", "b", "C", "eta", "J", "bad")
    t1 = [e.tensor(f"{x}1") for x in names]
    t2 = [e.tensor(f"{x}2") for x in names]
    to = [e.tensor(f"o{x}") for x in names]
    C1, J2 = e.load_sym(t1[2], n), e.load_sym(t2[4], n)
    A1, b1, eta2 = e.load_mat(t1[0], n, n), e.load_vec(t1[1], n), e.load_vec(t2[3], n)
    M = e.matmul(C1, J2)
    M = [[e.add(M[i][j], "1.0") if i == j else M[i][j] for j in range(n)] for i in range(n)]
    JA = e.matmul(J2, A1)
    Jb = e.matvec(J2, b1)
    d = [e.add(eta2[i], Jb[i], "-") for i in range(n)]  # eta2 - J2 b1
    bc = e.matvec(C1, eta2, add=b1)  # b1 + C1 eta2
    rhs = [A1[i] + [bc[i]] + C1[i] for i in range(n)]
    X, singular = e.solve_pivoted(M, rhs)  # W [A1, b1 + C1 eta2, C1]
    WA = [row[:n] for row in X]
    Wb = [row[n] for row in X]
    WC = [row[n + 1 :] for row in X]
    WAt = [[WA[k][i] for k in range(n)] for i in range(n)]
    JAt = [[JA[k][j] for k in range(n)] for j in range(n)]
    e.store_mat(to[4], e.sym_product(WAt, JAt, add=e.load_sym(t1[4], n)))  # A1'W'J2 A1 + J1
    eta1 = e.load_vec(t1[3], n)
    e.store_vec(to[3], e.matvec(WA, d, add=eta1, transpose_x=True))  # A1'W'(eta2 - J2 b1) + eta1
    A2 = e.load_mat(t2[0], n, n)
    e.store_mat(to[0], e.matmul(A2, WA))
    e.store_vec(to[1], e.matvec(A2, Wb, add=e.load_vec(t2[1], n)))
    T2 = e.matmul(A2, WC)
    e.store_mat(to[2], e.sym_product(T2, A2, add=e.load_sym(t2[2], n)))  # A2 W C1 A2' + C2
    e.store_flag(to[5], f"{e.load_flag(t1[5])} | {e.load_flag(t2[5])} | {singular}")
    return e.source("combine_value_kernel")


def _src_gains(n: int, m: int) -> str:
    """Gains (S4) from ``V_{t+1} (n, n)``, ``v_{t+1} (n)``, ``F_t``, ``H_t``: ``Kk (m, n+1)``,
    the Cholesky factor of ``Quu``, ``fail`` (``Quu`` not positive definite) and the
    value constant's increment ``c'V c + 2 v'c + qu'k``."""
    e = _Emitter()
    V, v, F, H = (e.tensor(t) for t in ("V", "v", "F", "H"))
    oK, oL, ofail, oinc = (e.tensor(t) for t in ("oK", "oL", "ofail", "oinc"))
    Vm = e.load_mat(V, n, n)
    vv = e.load_vec(v, n)
    Ft = e.load_mat(F, n + 1, m + n + 1)
    Hu = e.load_mat(H, m, m + n + 1)
    # P = [V, v] F  (rows :n of Vh_{t+1} times the homogeneous dynamics)
    P = e.matmul(Vm, Ft[:n])
    P = [[e.lin([(vv[i], Ft[n][j])], P[i][j]) for j in range(m + n + 1)] for i in range(n)]
    Bm = [row[:m] for row in Ft[:n]]
    Qu = e.matmul(Bm, P, add=Hu, transpose_x=True)  # H[:m] + B' P
    Quu = [
        [e.let(f"0.5 * ({Qu[i][j]} + {Qu[j][i]})") if j <= i else None for j in range(m)]
        for i in range(m)
    ]
    L, inv, ok = e.cholesky(Quu)
    Kk = e.chol_solve(L, inv, [row[m:] for row in Qu])
    Kk = [[e.let(f"-{x}") for x in row] for row in Kk]
    c = [Ft[i][m + n] for i in range(n)]
    Vc = e.matvec(Vm, c)
    inc = e.lin(
        [(c[i], Vc[i]) for i in range(n)]
        + [(vv[i], f"(2.0 * {c[i]})") for i in range(n)]
        + [(Qu[i][m + n], Kk[i][n]) for i in range(m)]
    )
    e.store_mat(oK, Kk)
    e.store_mat(oL, L)
    e.store_flag(ofail, f"tl.where({ok}, 0, 1)")
    e.store(oinc, inc)
    return e.source("gains_kernel")


def _src_combine_affine(n: int) -> str:
    """``(M2, a2) o (M1, a1) = (M2 M1, M2 a1 + a2)``."""
    e = _Emitter()
    M1, a1, M2, a2, oM, oa = (e.tensor(t) for t in ("M1", "a1", "M2", "a2", "oM", "oa"))
    X1, X2 = e.load_mat(M1, n, n), e.load_mat(M2, n, n)
    y1, y2 = e.load_vec(a1, n), e.load_vec(a2, n)
    e.store_mat(oM, e.matmul(X2, X1))
    e.store_vec(oa, e.matvec(X2, y1, add=y2))
    return e.source("combine_affine_kernel")


def _src_closed_loop(n: int, m: int) -> str:
    """``F (n+1, m+n+1)``, ``Kk (m, n+1)`` -> ``M = A + B K``, ``a = B k + c``."""
    e = _Emitter()
    F, Kk, oM, oa = (e.tensor(t) for t in ("F", "Kk", "oM", "oa"))
    Ft = e.load_mat(F, n, m + n + 1)
    K = e.load_mat(Kk, m, n + 1)
    G = e.matmul([row[:m] for row in Ft], K, add=[row[m:] for row in Ft])
    e.store_mat(oM, [row[:n] for row in G])
    e.store_vec(oa, [row[n] for row in G])
    return e.source("closed_loop_kernel")


_SOURCES = {
    "value_elements": _src_value_elements,
    "combine_value": lambda n, m: _src_combine_value(n),
    "gains": _src_gains,
    "combine_affine": lambda n, m: _src_combine_affine(n),
    "closed_loop": _src_closed_loop,
}
_KERNELS: dict[tuple, object] = {}


def kernel_source(kind: str, n: int, m: int = 1) -> str:
    """The generated source of one kernel (for inspection)."""
    return _SOURCES[kind](n, m)


def _kernel(kind: str, n: int, m: int, interpret: bool):
    key = (kind, n, m, interpret)
    fn = _KERNELS.get(key)
    if fn is None:
        import triton
        import triton.language as tl

        src = kernel_source(kind, n, m)
        filename = f"<torchslq.lq.scan_kernels {kind} n={n} m={m}>"
        # Triton reads a kernel's source through inspect, which finds it in linecache
        linecache.cache[filename] = (len(src), None, src.splitlines(True), filename)
        namespace = {"tl": tl, "triton": triton}
        exec(compile(src, filename, "exec"), namespace)
        raw = namespace[f"{kind}_kernel"]
        if interpret:
            from triton.runtime.interpreter import InterpretedFunction

            fn = InterpretedFunction(raw)
        else:
            # one compilation per kernel and dtype: the scan's levels pass slices whose
            # sizes, strides and offsets vary, and each of Triton's specialisations on
            # them (a 1, a multiple of 16, an aligned pointer) would compile it again
            names = list(inspect.signature(raw).parameters)[:-1]  # all but BLOCK
            fn = triton.jit(raw, do_not_specialize=names, do_not_specialize_on_alignment=names)
        _KERNELS[key] = fn
    return fn


def _strides(t: Tensor) -> list:
    """``t`` shaped ``(B, T', ...)`` (up to two trailing dims): the pointer and its four
    strides (a missing trailing dim has stride 0)."""
    s = list(t.stride()) + [0] * (4 - t.dim())
    return [t, *s[:4]]


def _launch(kind: str, n: int, m: int, tensors: Sequence[Tensor], batch: int, steps: int) -> None:
    total = batch * steps
    if total == 0:
        return
    interpret = not tensors[0].is_cuda
    args = [a for t in tensors for a in _strides(t)]
    grid = ((total + _BLOCK - 1) // _BLOCK,)
    try:
        fn = _kernel(kind, n, m, interpret)
        if interpret:
            fn[grid](*args, total, steps, BLOCK=_BLOCK)
        else:
            key = (kind, n, m, tensors[0].dtype, tensors[0].device)
            first = key not in _COMPILED  # the launch that compiles it
            with _without_coalescing() if first else contextlib.nullcontext():
                fn[grid](*args, total, steps, BLOCK=_BLOCK, **_GPU_OPTIONS)
            _COMPILED.add(key)
    except Exception as err:  # a Triton or toolchain that cannot build it here
        _MODE["broken"] = repr(err)
        warnings.warn(
            f"torchslq: the fused scan kernel {kind!r} (n={n}, m={m}) failed ({err!r}); the "
            "scan runs as torch ops from here on",
            RuntimeWarning,
            stacklevel=2,
        )
        raise FusedKernelError(repr(err)) from err


_COMPILED: set = set()
_PATCH_LOCK = threading.Lock()


@contextlib.contextmanager
def _without_coalescing() -> Iterator[None]:
    """Within: Triton's coalescing pass is skipped. It chooses the memory layouts of
    block loads and stores; these kernels load one scalar per lane at runtime strides,
    whose layout it leaves as it was (the PTX is the same with and without it:
    ``tests/test_scan_kernels.py``), while its analysis, which walks the whole
    straight-line kernel for every load and store, took 98% of the compile time (the
    value combination at ``n = 4``: 6.7 s -> 0.9 s; ``n = 6``: 128 s -> 2 s). The pass
    is switched off by replacing the function that adds it to the pipeline, only around
    a first launch (where the compilation happens), under a lock; a Triton without that
    function compiles as it is."""
    try:
        from triton._C.libtriton import passes

        adds = passes.ttgpuir
        original = adds.add_coalesce
    except (ImportError, AttributeError):  # another Triton layout: nothing to skip
        yield
        return
    with _PATCH_LOCK:
        adds.add_coalesce = lambda pm: None
        try:
            yield
        finally:
            adds.add_coalesce = original


def _flags(t: Tensor) -> Tensor:
    return t.view(torch.uint8) if t.dtype == torch.bool else t


# ----------------------------------------------------------------------------- entry points


def value_elements(F: Tensor, H: Tensor, out: Sequence[Tensor]) -> None:
    """Writes the elements (S1) of steps ``0..T-1`` into ``out = (A~, b, C, eta, J,
    bad)``, views ``(B, T, ...)`` (``bad`` bool). ``F (B, T, n+1, m+n+1)`` and ``H (B, T,
    m+n+1, m+n+1)`` (batch strides may be 0)."""
    n = F.shape[-2] - 1
    m = F.shape[-1] - n - 1
    B, T = out[0].shape[:2]
    tensors = [F, H, *out[:5], _flags(out[5])]
    _launch("value_elements", n, m, tensors, B, T)


def combine_value(e1: Sequence[Tensor], e2: Sequence[Tensor]) -> tuple[Tensor, ...]:
    """The operator (S2), as :func:`torchslq.lq.scan._combine_value`."""
    A1 = e1[0]
    B, Tp, n = A1.shape[0], A1.shape[1], A1.shape[-1]
    out = tuple(torch.empty((B, Tp, *t.shape[2:]), dtype=t.dtype, device=t.device) for t in e1)
    tensors = [*e1[:5], _flags(e1[5]), *e2[:5], _flags(e2[5]), *out[:5], _flags(out[5])]
    _launch("combine_value", n, 1, tensors, B, Tp)
    return out


def gains(V: Tensor, v: Tensor, F: Tensor, H: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Gains (S4): ``V (B, T, n, n)``, ``v (B, T, n)`` (the values of steps ``1..T``), ``F
    (B, T, n+1, m+n+1)``, ``H (B, T, m+n+1, m+n+1)`` -> ``Kk (B, T, m, n+1)``, ``L (B, T, m,
    m)`` (Cholesky factor of ``Quu``), ``failed (B, T)`` bool and the value constant's
    increments ``(B, T)``."""
    n = F.shape[-2] - 1
    m = F.shape[-1] - n - 1
    B, T = V.shape[:2]
    kw = {"dtype": V.dtype, "device": V.device}
    Kk = torch.empty(B, T, m, n + 1, **kw)
    L = torch.empty(B, T, m, m, **kw)
    failed = torch.empty(B, T, dtype=torch.bool, device=V.device)
    inc = torch.empty(B, T, **kw)
    _launch("gains", n, m, [V, v, F, H, Kk, L, _flags(failed), inc], B, T)
    return Kk, L, failed, inc


def combine_affine(e1: Sequence[Tensor], e2: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
    """``e2 o e1`` of affine maps ``(M (B, T', p, p), a (B, T', p))``."""
    M1, a1 = e1
    M2, a2 = e2
    B, Tp, p = M1.shape[0], M1.shape[1], M1.shape[-1]
    oM = torch.empty(B, Tp, p, p, dtype=M1.dtype, device=M1.device)
    oa = torch.empty(B, Tp, p, dtype=M1.dtype, device=M1.device)
    _launch("combine_affine", p, 1, [M1, a1, M2, a2, oM, oa], B, Tp)
    return oM, oa


def closed_loop(F: Tensor, Kk: Tensor) -> tuple[Tensor, Tensor]:
    """``(A + B K, B k + c)`` of every step: ``F (B, T, n+1, m+n+1)``, ``Kk (B, T, m,
    n+1)`` (batch strides may be 0) -> ``(B, T, n, n)``, ``(B, T, n)``."""
    n = F.shape[-2] - 1
    m = F.shape[-1] - n - 1
    B, T = Kk.shape[:2]
    M = torch.empty(B, T, n, n, dtype=Kk.dtype, device=Kk.device)
    a = torch.empty(B, T, n, dtype=Kk.dtype, device=Kk.device)
    _launch("closed_loop", n, m, [F, Kk, M, a], B, T)
    return M, a
