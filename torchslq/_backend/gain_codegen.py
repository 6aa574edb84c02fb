"""The gain-form element pass of :mod:`._numba_gain` written out for one ``(n, m)``.

:func:`._numba_gain._gain_pass` keeps the step's matrices in small scratch arrays. LLVM
unrolls its loops for sizes fixed when compiled, but cannot keep the entries in
registers: every store to one scratch array may alias the others (numba passes no
aliasing information), so each product reloads what the previous one stored. Written
out as straight-line code, every entry of ``P``, ``P'A``, ``Quu``, ``L``, ``K`` of a
step is a local variable: registers, scheduled freely, and the value function carried
to the next step without a store and a load.

The statements are the element pass's operations in its order (the same sums, started
the same way), but LLVM contracts products into FMAs where it sees fit in either
version, so the two agree to rounding, not bit for bit (a few 1e-15 relative;
``tests/test_gain_codegen.py`` checks 1e-12). Only the pass without second-order terms
(the LQ layer's, iLQR's) is generated, for sizes up to :data:`MAX_ENTRIES` ``n (n + m)``:
larger ones would be thousands of statements to compile (not measured; their products
are register-blocked by :mod:`._numba_gemm` already).

:func:`module_source` gives a module with kernels of :mod:`._numba_gain` on this
element pass: ``riccati_gain_kernel`` and ``gain_solve_kernel`` (the same arguments and
outputs), and ``riccati_gain_reg_first`` (the solvers' pass, its first try only: an
element that fails it is run again by :func:`._numba_gain.riccati_gain_reg_kernel`,
with its restarts). :func:`gain_kernels` writes the module once per size and text
(beside the package, else in torchslq's cache directory; named by a hash of its text) and imports it; numba caches
its compiled code beside it, as the library's own kernels.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from types import ModuleType

from .source_modules import cache_root, import_source, write_atomic
from .specialisation import specialised

#: the largest ``n (n + m)`` generated
MAX_ENTRIES = 48


def _sym(name: str, i: int, j: int) -> str:
    """The local of a symmetric matrix's entry (upper triangle kept)."""
    return f"{name}{min(i, j)}_{max(i, j)}"


def _chain(out: str, terms: list[str], start: str | None = None) -> list[str]:
    """``out = start; out += t for t in terms`` as the element pass's running sums: the
    first product alone where there is no start (``0 + a b`` is ``a b``), then one
    addition per term (contracted into an FMA, as the loops' ``+=``)."""
    lines = []
    if start is None:
        lines.append(f"{out} = {terms[0]}")
        terms = terms[1:]
    else:
        lines.append(f"{out} = {start}")
    lines += [f"{out} = {out} + {t}" for t in terms]
    return lines


def pass_source(n: int, m: int) -> str:
    """``gain_pass(e, pieces, Kk, P, p, L, s2, reg)``: :func:`._numba_gain._gain_pass`
    without second-order terms, for ``n`` states and ``m`` controls (same arguments
    less ``Hz, Hb, scratch, nt, mt``; same returns ``(ok, s_0)``)."""
    rn, rm = range(n), range(m)
    b: list[str] = []  # body lines, indented by the loop level in the text

    def emit(level: int, lines) -> None:
        b.extend("    " * level + ln for ln in ([lines] if isinstance(lines, str) else lines))

    emit(1, "T = Kk.shape[1]")
    emit(1, "A, Bm, c, Q, R, S, q, r = pieces")
    emit(1, "has_c, has_S = c.shape[0] > 0, S.shape[0] > 0")
    emit(1, "has_q, has_r = q.shape[0] > 0, r.shape[0] > 0")
    emit(1, "steps = s2.shape[0] > 0")
    emit(1, "bq, tq = _idx(Q, e, T)")
    emit(1, "Qt = Q[bq, tq]")
    emit(1, "Pe = P[e, T]")
    for i in rn:
        for j in range(i, n):
            emit(1, f"{_sym('P', i, j)} = 0.5 * (Qt[{i}, {j}] + Qt[{j}, {i}])")
    for i in rn:
        for j in rn:
            emit(1, f"Pe[{i}, {j}] = {_sym('P', i, j)}")
    for i in rn:
        emit(1, f"p{i} = 0.0")
    emit(1, "if has_q:")
    emit(2, "bl, tl = _idx(q, e, T)")
    for i in rn:
        emit(2, f"p{i} = q[bl, tl, {i}]")
    emit(1, "pe = p[e, T]")
    for i in rn:
        emit(1, f"pe[{i}] = p{i}")
    emit(1, "sv = 0.0")
    emit(1, "if steps:")
    emit(2, "s2[e, T] = 0.0")
    emit(1, "ok = True")
    emit(1, "for t in range(T - 1, -1, -1):")
    emit(2, "ba, ta = _idx(A, e, t)")
    emit(2, "At = A[ba, ta]")
    emit(2, "bb, tb = _idx(Bm, e, t)")
    emit(2, "Bt = Bm[bb, tb]")
    for i in rn:
        for j in rn:
            emit(2, f"a{i}_{j} = At[{i}, {j}]")
        for j in rm:
            emit(2, f"b{i}_{j} = Bt[{i}, {j}]")
    # w = p' + P'c;  s += p''c + c'P'c / 2
    emit(2, "if has_c:")
    emit(3, "bc, tc = _idx(c, e, t)")
    emit(3, "ct = c[bc, tc]")
    for i in rn:
        emit(3, _chain(f"w{i}", [f"ct[{j}] * {_sym('P', j, i)}" for j in rn], f"p{i}"))
    for i in rn:
        emit(3, f"sv += ct[{i}] * (0.5 * (p{i} + w{i}))")
    emit(2, "else:")
    for i in rn:
        emit(3, f"w{i} = p{i}")
    # PA = P'A, PB = P'B (P' symmetric)
    for i in rn:
        for j in rn:
            emit(2, _chain(f"PA{i}_{j}", [f"{_sym('P', k, i)} * a{k}_{j}" for k in rn]))
        for j in rm:
            emit(2, _chain(f"PB{i}_{j}", [f"{_sym('P', k, i)} * b{k}_{j}" for k in rn]))
    # Quu = R (+ reg) + B'PB (lower triangle), qu = B'w, Qux = B'PA (+ S), (+ r)
    emit(2, "br, tr = _idx(R, e, t)")
    emit(2, "Rt = R[br, tr]")
    for i in rm:
        for j in range(i + 1):
            emit(2, f"U{i}_{j} = 0.5 * (Rt[{i}, {j}] + Rt[{j}, {i}])")
        emit(2, f"U{i}_{i} = U{i}_{i} + reg")
        emit(2, _chain(f"y{i}", [f"b{k}_{i} * w{k}" for k in rn]))
    for i in rm:
        for j in range(i + 1):
            emit(2, _chain(f"U{i}_{j}", [f"b{k}_{i} * PB{k}_{j}" for k in rn], f"U{i}_{j}"))
    for i in rm:
        for j in rn:
            emit(2, _chain(f"Y{i}_{j}", [f"b{k}_{i} * PA{k}_{j}" for k in rn]))
    emit(2, "if has_S:")
    emit(3, "bs, ts = _idx(S, e, t)")
    emit(3, "St = S[bs, ts]")
    for i in rm:
        for j in rn:
            emit(3, f"Y{i}_{j} = Y{i}_{j} + St[{i}, {j}]")
    emit(2, "if has_r:")
    emit(3, "bl, tl = _idx(r, e, t)")
    for i in rm:
        emit(3, f"y{i} = y{i} + r[bl, tl, {i}]")
    # Cholesky Quu = L L' (the pass stops at a pivot that is not positive, or NaN)
    for j in rm:
        emit(2, f"d = U{j}_{j}")
        for k in range(j):
            emit(2, f"d = d - L{j}_{k} * L{j}_{k}")
        emit(2, "if not d > 0.0:")
        emit(3, "ok = False")
        emit(3, "break")
        emit(2, f"L{j}_{j} = math.sqrt(d)")
        for i in range(j + 1, m):
            emit(2, f"acc = U{i}_{j}")
            for k in range(j):
                emit(2, f"acc = acc - L{i}_{k} * L{j}_{k}")
            emit(2, f"L{i}_{j} = acc / L{j}_{j}")
    # Y = L^{-1} Qux, y = L^{-1} qu
    for i in rm:
        emit(2, f"di = 1.0 / L{i}_{i}")
        for j in rn:
            emit(2, f"acc = Y{i}_{j}")
            for k in range(i):
                emit(2, f"acc = acc - L{i}_{k} * Y{k}_{j}")
            emit(2, f"Y{i}_{j} = acc * di")
        emit(2, f"acc = y{i}")
        for k in range(i):
            emit(2, f"acc = acc - L{i}_{k} * y{k}")
        emit(2, f"y{i} = acc * di")
    # P = Q + A'PA - Y'Y (upper triangle), p = q + A'w - Y'y
    emit(2, "bq, tq = _idx(Q, e, t)")
    emit(2, "Qt = Q[bq, tq]")
    for i in rn:
        for j in range(i, n):
            emit(2, f"N{i}_{j} = 0.5 * (Qt[{i}, {j}] + Qt[{j}, {i}])")
        emit(2, _chain(f"n{i}", [f"a{k}_{i} * w{k}" for k in rn]))
        for k in rm:
            emit(2, f"n{i} = n{i} - Y{k}_{i} * y{k}")
    for k in rn:
        for i in rn:
            for j in range(i, n):
                emit(2, f"N{i}_{j} = N{i}_{j} + a{k}_{i} * PA{k}_{j}")
    for k in rm:
        for i in rn:
            emit(2, f"g = -1.0 * Y{k}_{i}")
            for j in range(i, n):
                emit(2, f"N{i}_{j} = N{i}_{j} + g * Y{k}_{j}")
    emit(2, "if has_q:")
    emit(3, "bl, tl = _idx(q, e, t)")
    for i in rn:
        emit(3, f"n{i} = n{i} + q[bl, tl, {i}]")
    for k in rm:
        emit(2, f"sv -= 0.5 * y{k} * y{k}")
    # [K k] = -L'^{-1} [Y y]
    for i in reversed(rm):
        emit(2, f"di = 1.0 / L{i}_{i}")
        for j in range(n + 1):
            emit(2, f"acc = {f'Y{i}_{j}' if j < n else f'y{i}'}")
            for k in range(i + 1, m):
                emit(2, f"acc = acc - L{k}_{i} * G{k}_{j}")
            emit(2, f"G{i}_{j} = acc * di")
    for i in rm:
        for j in range(n + 1):
            emit(2, f"G{i}_{j} = -G{i}_{j}")
    emit(2, "if reg != 0.0:  # the value of the regularised gains: - reg [K k]'[K k]")
    for k in rm:
        for i in rn:
            emit(3, f"g = reg * G{k}_{i}")
            for j in range(i, n):
                emit(3, f"N{i}_{j} = N{i}_{j} - g * G{k}_{j}")
            emit(3, f"n{i} = n{i} - g * G{k}_{n}")
        emit(3, f"sv -= 0.5 * reg * G{k}_{n} * G{k}_{n}")
    # this step's outputs; its value function is the next step's
    emit(2, "Kt = Kk[e, t]")
    emit(2, "Lt = L[e, t]")
    for i in rm:
        for j in range(n + 1):
            emit(2, f"Kt[{i}, {j}] = G{i}_{j}")
        for j in rm:
            emit(2, f"Lt[{i}, {j}] = {f'L{i}_{j}' if j <= i else '0.0'}")
    emit(2, "Pc = P[e, t]")
    emit(2, "pc = p[e, t]")
    for i in rn:
        for j in rn:
            emit(2, f"Pc[{i}, {j}] = {_sym('N', i, j)}")
        emit(2, f"pc[{i}] = n{i}")
    emit(2, "if steps:")
    emit(3, "s2[e, t] = 2.0 * sv")
    for i in rn:
        for j in range(i, n):
            emit(2, f"P{i}_{j} = N{i}_{j}")
        emit(2, f"p{i} = n{i}")
    emit(1, "return ok, sv")
    head = (
        '@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", '
        "_nrt=False)\ndef gain_pass(e, pieces, Kk, P, p, L, s2, reg):\n"
        f'    """The element pass for n = {n}, m = {m} (see the module docstring)."""\n'
    )
    return head + "\n".join(b) + "\n"


_MODULE_TAIL = """

@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def riccati_gain_kernel(b0, b1, pieces, Kk, P, p, L, s, failed, nt, mt):
    \"\"\"_numba_gain.riccati_gain_kernel on the generated element pass.\"\"\"
    _gain_rows(b0, b1, pieces, Kk, P, p, L, s, failed, np.zeros((0, 0), dtype=P.dtype))


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", _nrt=False)
def _gain_rows(b0, b1, pieces, Kk, P, p, L, s, failed, no_s2):
    for e in range(b0, b1):
        ok, sv = gain_pass(e, pieces, Kk, P, p, L, no_s2, 0.0)
        s[e] = sv
        failed[e] = not ok


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def gain_solve_kernel(pieces, x0, Kk, P, p, L, s, failed, x, u, lam, cost, finite, nt, mt):
    \"\"\"_numba_gain.gain_solve_kernel on the generated element pass.\"\"\"
    first = np.intp(0)  # not a literal 0: the launchers' signature, compiled once
    _gain_rows(first, Kk.shape[0], pieces, Kk, P, p, L, s, failed, np.zeros((0, 0), dtype=P.dtype))
    rollout_value_kernel(
        first, x.shape[0], pieces[0], pieces[1], pieces[2], Kk, P, p, s, x0, x, u, lam, cost,
        finite, nt, mt,
    )


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def gain_solve_at_kernel(
    addresses, dims, x0_address, Kk, P, p, L, s, failed, x, u, lam, cost, finite, nt, mt
):
    \"\"\"_numba_gain.gain_solve_at_kernel on the generated element pass.\"\"\"
    pieces, x0 = pieces_at(addresses, dims, x0_address, x.shape[0], Kk.shape[3] - 1, Kk.shape[2], P)
    gain_solve_kernel(pieces, x0, Kk, P, p, L, s, failed, x, u, lam, cost, finite, nt, mt)


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def riccati_gain_reg_first(b0, b1, pieces, reg, Kk, Vh, L, failed, mu_io):
    \"\"\"The first pass of _numba_gain.riccati_gain_reg_kernel for elements b0 <= b < b1
    (regularisation mu_io[b], or reg where mu_io is empty): failed[b] where it failed or
    its gains are not finite (the caller runs those again with their restarts); Vh's
    last row mirrored where it succeeded.\"\"\"
    n = Kk.shape[3] - 1
    _reg_first_rows(
        b0, b1, pieces, reg, Kk, Vh[:, :, :n, :n], Vh[:, :, :n, n], L, Vh[:, :, n, n], Vh,
        failed, mu_io,
    )


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", _nrt=False)
def _reg_first_rows(b0, b1, pieces, reg, Kk, P, p, L, s2, Vh, failed, mu_io):
    restarting = mu_io.shape[0] > 0
    for b in range(b0, b1):
        r = mu_io[b] if restarting else reg[b if reg.shape[0] > 1 else 0]
        ok, _ = gain_pass(b, pieces, Kk, P, p, L, s2, r)
        if ok:
            ok = finite_gains(Kk[b])
        failed[b] = not ok
        if ok:
            mirror_last_row(Vh, b)
"""


def module_source(n: int, m: int) -> str:
    """The generated module for ``n`` states and ``m`` controls (module docstring)."""
    head = (
        f"# generated by torchslq._backend.gain_codegen for n = {n}, "
        f"m = {m}; do not edit\n"
        "import math\n\nimport numba\nimport numpy as np\n\n"
        "from torchslq._backend._numba_address import pieces_at\n"
        "from torchslq._backend._numba_gain import mirror_last_row, rollout_value_kernel\n"
        "from torchslq._backend._numba_kernels import _idx, finite_gains\n"
        "\n\n"
    )
    return head + pass_source(n, m) + _MODULE_TAIL


_MODULES: dict = {}  # (n, m) -> module, or None where it could not be made
_enabled = True


def set_generated(enabled: bool) -> bool:
    """Switch the generated kernels on or off (process-wide; off: the element kernels of
    :mod:`._numba_gain` run every size); returns the old setting."""
    global _enabled
    old, _enabled = _enabled, bool(enabled)
    return old


def _directories() -> list[Path]:
    """Where generated modules are written, in order of preference: beside the package
    (numba caches the library's own kernels there too), then torchslq's cache directory
    (``TORCHSLQ_CACHE_DIR``, by default ``~/.cache/torchslq``)."""
    return [Path(__file__).resolve().parent / "_generated", cache_root() / "lq_generated"]


def gain_kernels(n: int, m: int) -> ModuleType | None:
    """The generated kernels for ``n`` states and ``m`` controls, or None where the size
    is not generated (``n (n + m) > MAX_ENTRIES``, or left out by
    :func:`.specialisation.limit_specialised_sizes`) or no directory is writable."""
    if not _enabled or not specialised(n, m):
        return None
    key = (n, m)
    if key in _MODULES:
        return _MODULES[key]
    module = None
    if n * (n + m) <= MAX_ENTRIES and n >= 1 and m >= 1:
        source = module_source(n, m)
        # named by its text: library versions sharing a directory keep their own files
        # (one file rewritten by each in turn would make numba recompile it every time)
        digest = hashlib.sha256(source.encode()).hexdigest()[:12]
        name = f"lq_gain_n{n}_m{m}_{digest}"
        for d in _directories():
            try:
                module = _load(d / f"{name}.py", f"torchslq_{name}", source)
                break
            except OSError:
                continue
    _MODULES[key] = module
    return module


def _load(path: Path, name: str, source: str) -> ModuleType:
    """Import ``path`` as ``name``, writing ``source`` there first where the file is
    missing or holds another text (OSError where its directory is not writable)."""
    if not path.exists() or path.read_text() != source:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, source)
    return import_source(path, name)
