"""A learned model's Jacobians as generated code: its compiled step swept backwards.

:func:`torchslq.linearize` of a learned model on torch ops walks its traced graph in
Python (:func:`~torchslq.dynamics.graph_jacobians`): per node a few batched torch ops on
``(rows, n, width)`` sensitivities, so a 5-64-64-4 MLP on a physics step took 37 ms for
3,200 rows and 3.6 ms for 50, where its products are 5 ms and 0.1 ms of arithmetic.
Here the same reverse sweep is written out beside the network's compiled step
(:mod:`torchslq.dynamics.network_codegen`), as one numba function over the rows
``jacobians(r0, r1, X, U, p, S..., A, B)``: per row the step's own forward code, then
the output's sensitivity ``G = d out / d node (n, width)`` carried back node by node
(stack arrays, row-major), as in the graph path's :func:`_reverse`:

* a layer ``y = W a + b``: ``G_a += G_y W`` (its weight's rows, contiguous, a second
  copy in ``p``): four of ``y``'s entries a pass, every output's row in registers;
* an activation ``h = s(a)``: ``G_a += G_h diag(s'(a))``, the slope from ``a`` and ``h``
  (:data:`~torchslq.dynamics.network_codegen._SLOPES`);
* sums, differences, negation, products and quotients of nodes and constants, slices,
  concatenations and stacks of the last dim;
* a Dynamics submodule on the model's own ``(x, u)``: its Jacobians, computed before the
  call by :func:`torchslq.linearize` (its own compiled derivatives), enter as the
  arrays ``S (rows, width, n)``, ``(rows, width, m)``.

What it does not write (a submodule on other nodes) keeps the graph path.
"""

from __future__ import annotations

from torch import fx

from .graph_jacobian import _Unsupported, _var

#: nodes at most this wide are scalar locals in the forward code (their entries are
#: unrolled here too); as :data:`torchslq.dynamics.network_codegen.NARROW`
_UNROLL_OUTPUTS = 8
#: a narrow layer input's accumulators (outputs x inputs) held as scalar locals
_MAX_ACCUMULATORS = 64


class _Sweep:
    """The reverse sweep's text, from a forward writer (``network_codegen._Writer``)
    whose ``rules`` say how each node was computed."""

    def __init__(self, w, n: int, narrow: int, new_array) -> None:
        self.w = w
        self.n = n
        self.narrow = narrow
        self.new_array = new_array
        self.lines: list[str] = []
        self.G: dict[fx.Node, str] = {}
        self.count = 0
        self.subs: list[str] = []  # submodule targets, in argument order

    def emit(self, line: str, indent: int = 0) -> None:
        self.lines.append("    " * (2 + indent) + line)

    def grad(self, node: fx.Node, whole: bool = False) -> tuple[str, str]:
        """The sensitivity array of ``node`` (``(n, width)``) and the operator of a write
        into it: ``+=``, or ``=`` for the first write where that is ``whole`` (it covers
        every entry: no zeros written first)."""
        if node in self.G:
            return self.G[node], "+="
        size = self.n * self.w.widths[node]
        self.count += 1
        name = self.G[node] = f"g{self.count}"
        self.emit(f"{name} = {self.new_array(size)}")
        if whole:
            return name, "="
        self.emit(f"for q in range({size}):")
        self.emit(f"{name}[q] = 0.0", 1)
        return name, "+="

    def outputs(self, body) -> list[tuple[str, int]]:
        """``body(j)`` for every output ``j``: unrolled for a few, else a loop."""
        if self.n <= _UNROLL_OUTPUTS:
            return [line for j in range(self.n) for line in body(j)]
        return [(f"for j in range({self.n}):", 0), *((t, d + 1) for t, d in body("j"))]

    def entries(self, width: int, body) -> None:
        """``body(i)`` (lines and their extra indents) for every entry ``i < width``:
        unrolled for a narrow node (its entries are locals), else a loop."""
        if width <= self.narrow:
            for i in range(width):
                for text, d in body(i):
                    self.emit(text, d)
            return
        self.emit(f"for i in range({width}):")
        for text, d in body("i"):
            self.emit(text, d + 1)

    def scaled_add(self, dst: fx.Node, src: tuple, width: int, scale=None, doff=0, soff=0):
        """``G_dst[j, doff + i] += G_src[j, soff + i] * scale(i)`` for ``i < width``, ``src``
        the source's array and width (``scale`` None: 1; a number; or ``i ->
        expression``)."""
        if not _var(dst):
            return
        wd = self.w.widths[dst]
        g, op = self.grad(dst, whole=doff == 0 and width == wd)
        src, ws = src

        def body(i):
            lines = []
            factor = ""
            if callable(scale):
                lines.append((f"s = {scale(i)}", 0))
                factor = " * s"
            elif scale is not None and scale != 1.0:
                factor = f" * {float(scale)!r}"
            return lines + self.outputs(
                lambda j: [
                    (f"{g}[{_at(j, wd, i, doff)}] {op} {src}[{_at(j, ws, i, soff)}]{factor}", 0)
                ]
            )

        self.entries(width, body)

    def linear(self, nd: fx.Node, a: fx.Node, src: str, wr: int) -> None:
        """``G_a += G_y W``, ``W (width, k)`` row-major at ``p[wr]``."""
        if not _var(a):
            return
        n, width, k = self.n, self.w.widths[nd], self.w.widths[a]
        narrow = k <= self.narrow and n * k <= _MAX_ACCUMULATORS
        g, op = self.grad(a, whole=narrow)
        if narrow:
            # every (output, input) sum a local; one pass over the layer's entries
            for j in range(n):
                for i in range(k):
                    self.emit(f"e{j}_{i} = 0.0")
            self.emit(f"for o in range({width}):")
            for i in range(k):
                self.emit(f"wt{i} = p[{wr + i} + o * {k}]", 1)
            for j in range(n):
                self.emit(f"gs = {src}[{j * width} + o]", 1)
                for i in range(k):
                    self.emit(f"e{j}_{i} += gs * wt{i}", 1)
            for j in range(n):
                for i in range(k):
                    self.emit(f"{g}[{j * k + i}] {op} e{j}_{i}")
            return
        # four of the layer's entries a pass: each output row's four sensitivities in
        # registers, the input's row read and written once per pass
        blocked = width - width % 4
        unroll = n <= _UNROLL_OUTPUTS
        rows = range(n) if unroll else ["j"]
        base = 0 if unroll else 1
        if not unroll:
            self.emit(f"for j in range({n}):")
        if blocked:
            self.emit(f"for o in range(0, {blocked}, 4):", base)
            for j in rows:
                for q in range(4):
                    self.emit(f"gs{_name(j)}_{q} = {src}[{_at(j, width, 'o', q)}]", base + 1)
            self.emit(f"for i in range({k}):", base + 1)
            for q in range(4):
                self.emit(f"wt{q} = p[{wr + q * k} + o * {k} + i]", base + 2)
            for j in rows:
                terms = " + ".join(f"gs{_name(j)}_{q} * wt{q}" for q in range(4))
                self.emit(f"{g}[{_at(j, k, 'i', 0)}] += {terms}", base + 2)
        for o in range(blocked, width):
            for j in rows:
                self.emit(f"gs{_name(j)}_0 = {src}[{_at(j, width, o, 0)}]", base)
            self.emit(f"for i in range({k}):", base)
            for j in rows:
                self.emit(
                    f"{g}[{_at(j, k, 'i', 0)}] += gs{_name(j)}_0 * p[{wr + o * k} + i]", base + 1
                )

    def submodule(self, nd: fx.Node, src: str, inputs: tuple, args: tuple) -> None:
        """``G_a += G_y S_a[r]`` for the submodule's two inputs (the model's own ``x``,
        ``u``: their Jacobians are the arrays ``S{k}a``, ``S{k}b``)."""
        if tuple(args) != tuple(inputs):
            raise _Unsupported("a Dynamics submodule on other nodes than (x, u)")
        idx = len(self.subs)
        self.subs.append(nd.target)
        width = self.w.widths[nd]
        for a, name in zip(args, (f"S{idx}a", f"S{idx}b"), strict=True):
            g, _ = self.grad(a)
            k = self.w.widths[a]
            self.emit(f"for j in range({self.n}):")
            self.emit(f"for o in range({width}):", 1)
            self.emit(f"gs = {src}[j * {width} + o]", 2)
            self.emit(f"for i in range({k}):", 2)
            self.emit(f"{g}[j * {k} + i] += gs * {name}[r, o, i]", 3)


def _name(j) -> str:
    return str(j)


def _at(j, width: int, i, offset=0) -> str:
    """The index of entry ``(j, offset + i)`` of a row-major ``(., width)`` array."""
    if isinstance(j, int) and isinstance(i, int):
        return str(j * width + offset + i)
    head = f"{j * width}" if isinstance(j, int) else f"{j} * {width}"
    tail = f"{i}" if not offset else f"{i} + {offset}"
    return f"{head} + {tail}"


def write_jacobians(w, program, root, n: int, m: int, narrow: int, new_array, weight_rows):
    """The lines of the generated ``jacobians`` function's sweep (to follow the step's
    forward lines in the row loop) and the Dynamics submodules whose Jacobians it takes
    as arguments (targets, in order). ``w`` is the forward writer after the step's nodes;
    ``weight_rows(target)`` the offset of a layer's weight rows in ``p``. Raises
    :class:`_Unsupported` for what it does not write."""
    sweep = _Sweep(w, n, narrow, new_array)
    out = program.output
    g, _ = sweep.grad(out)
    for j in range(n):
        sweep.emit(f"{g}[{j * n + j}] = 1.0")
    for nd in reversed(program.nodes):
        if nd.op in ("placeholder", "output", "get_attr") or nd not in sweep.G:
            continue
        rule = w.rules.get(nd)
        if rule is None:
            raise _Unsupported(f"no reverse rule for {nd.op} {nd.target}")
        width = w.widths[nd]
        _apply(sweep, nd, rule, (sweep.G.pop(nd), width), tuple(program.inputs), weight_rows)
    xin, uin = program.inputs
    for node, name, k in ((xin, "A", n), (uin, "B", m)):
        g = sweep.G.get(node)
        sweep.emit(f"for j in range({n}):")
        sweep.emit(f"for i in range({k}):", 1)
        sweep.emit(f"{name}[r, j, i] = {'0.0' if g is None else f'{g}[j * {k} + i]'}", 2)
    return sweep.lines, sweep.subs


def _apply(sweep: _Sweep, nd: fx.Node, rule: tuple, src: tuple, inputs: tuple, weight_rows):
    """Node ``nd``'s sensitivity ``src`` (its array and width) carried to its arguments
    by its ``rule`` (how the forward writer computed it)."""
    w, width, kind = sweep.w, src[1], rule[0]
    if kind == "linear":
        _, a, target = rule
        sweep.linear(nd, a, src[0], weight_rows(target))
    elif kind == "activation":
        _, a, slope = rule
        sweep.scaled_add(a, src, width, lambda i: slope.format(a=w.entry(a, i), h=w.entry(nd, i)))
    elif kind == "sum":
        for a, sign in rule[1]:
            sweep.scaled_add(a, src, width, sign)
    elif kind == "product":  # a b: G_a += G b, G_b += G a
        _, a, a_text, b, b_text = rule
        sweep.scaled_add(a, src, width, b_text)
        sweep.scaled_add(b, src, width, a_text)
    elif kind == "quotient":  # h = a / b: G_a += G / b, G_b -= G h / b
        _, a, _, b, b_text = rule
        sweep.scaled_add(a, src, width, lambda i: f"(1.0 / {b_text(i)})")
        sweep.scaled_add(b, src, width, lambda i: f"(-{w.entry(nd, i)} / {b_text(i)})")
    elif kind == "slice":
        _, source, start = rule
        sweep.scaled_add(source, src, width, doff=start)
    elif kind == "cat":
        start = 0
        for piece in rule[1]:
            k = w.widths[piece]
            sweep.scaled_add(piece, src, k, soff=start)
            start += k
    elif kind == "submodule":
        _, a, b = rule
        sweep.submodule(nd, src[0], inputs, (a, b))
    else:  # pragma: no cover - every rule the writer records is handled above
        raise _Unsupported(kind)
