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
            lines, factor = _factor(scale, i)
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

    def chain(self, src: str, rule: tuple) -> None:
        """``G_a += G_y J[row]`` for a layer chain's output ``y`` on its input ``a``, ``J
        (rows, wo, k)`` the chain's Jacobian of the block
        (:mod:`torchslq.dynamics.network_chains`)."""
        _, c, a, wo = rule
        self.times_jacobian(a, src, wo, f"JC{c}[ii, o, i]")

    def times_jacobian(self, a: fx.Node, src: str, width: int, entry: str) -> None:
        """``G_a += G_y J`` for a node ``y`` (``width`` wide, sensitivity array ``src``)
        whose Jacobian in its argument ``a`` is given per row: ``entry`` the text of
        ``J[o, i]`` (a layer chain's block array, a submodule's Jacobian array)."""
        g, _ = self.grad(a)
        k = self.w.widths[a]
        self.emit(f"for j in range({self.n}):")
        self.emit(f"for o in range({width}):", 1)
        self.emit(f"gs = {src}[j * {width} + o]", 2)
        self.emit(f"for i in range({k}):", 2)
        self.emit(f"{g}[j * {k} + i] += gs * {entry}", 3)

    def sub_index(self, target: str) -> int:
        """The argument index of a Dynamics submodule's arrays (one per submodule)."""
        if target not in self.subs:
            self.subs.append(target)
        return self.subs.index(target)

    def submodule(self, nd: fx.Node, src: str, inputs: tuple, args: tuple) -> None:
        """``G_a += G_y S_a[r]`` for the submodule's two inputs (the model's own ``x``,
        ``u``: their Jacobians are the arrays ``S{k}a``, ``S{k}b``)."""
        if tuple(args) != tuple(inputs):
            raise _Unsupported("a Dynamics submodule on other nodes than (x, u)")
        idx = self.sub_index(nd.target)
        width = self.w.widths[nd]
        for a, name in zip(args, (f"S{idx}a", f"S{idx}b"), strict=True):
            self.times_jacobian(a, src, width, f"{name}[r, o, i]")


class _Second(_Sweep):
    """The sweep with every output's Hessian: the nodes' tangents ``T = d node / d z (k,
    width)``, ``z = (x, u)``, pushed forward first, and each nonlinear node adding
    ``T_in' (sum_j G_j d2 node) T_in`` to ``hz (n, k, k)`` in the backward sweep (as
    :func:`~torchslq.dynamics.graph_hessians` does on torch ops)."""

    def __init__(self, w, n: int, m: int, narrow: int, new_array) -> None:
        super().__init__(w, n, narrow, new_array)
        self.k = n + m
        self.T: dict[fx.Node, str] = {}

    def tangent(self, node: fx.Node) -> str:
        """The tangent array of ``node`` (``(k, width)``, zeros when new)."""
        if node not in self.T:
            size = self.k * self.w.widths[node]
            self.count += 1
            name = self.T[node] = f"t{self.count}"
            self.emit(f"{name} = {self.new_array(size)}")
            self.emit(f"for q in range({size}):")
            self.emit(f"{name}[q] = 0.0", 1)
        return self.T[node]

    def push(self, dst: fx.Node, a, width: int, scale=None, doff=0, soff=0) -> None:
        """``T_dst[c, doff + i] += T_a[c, soff + i] * scale(i)`` for ``i < width`` (``scale``
        None, a number or ``i -> expression``); nothing for a constant ``a``."""
        if not _var(a):
            return
        t, ta = self.tangent(dst), self.T[a]
        wd, wa, k = self.w.widths[dst], self.w.widths[a], self.k

        def body(i):
            lines, factor = _factor(scale, i)
            return [
                *lines,
                (f"for c in range({k}):", 0),
                (f"{t}[{_at('c', wd, i, doff)}] += {ta}[{_at('c', wa, i, soff)}]{factor}", 1),
            ]

        self.entries(width, body)

    def forward_tangents(self, program, inputs: tuple, rules: dict, woffsets) -> None:
        """Every node's tangent, in the program's order."""
        n, k, w = self.n, self.k, self.w
        for node, first in zip(inputs, (0, n), strict=True):
            t = self.tangent(node)
            for i in range(w.widths[node]):
                self.emit(f"{t}[{(first + i) * w.widths[node] + i}] = 1.0")
        needed = _tangents_needed(program, rules)
        for nd in program.nodes:
            if nd.op in ("placeholder", "output", "get_attr") or nd not in needed:
                continue
            rule, width = rules[nd], w.widths[nd]
            kind = rule[0]
            if kind == "linear":
                _, a, target = rule
                t, ta, ka, off = self.tangent(nd), self.T[a], w.widths[a], woffsets(target)
                self.emit(f"for c in range({k}):")
                blocked = ka - ka % 4  # four inputs a pass, as the step's layer
                if blocked:
                    self.emit(f"for i in range(0, {blocked}, 4):", 1)
                    for q in range(4):
                        self.emit(f"s{q} = {ta}[c * {ka} + i + {q}]", 2)
                    terms = " + ".join(
                        f"s{q} * p[{off + q * width} + i * {width} + o]" for q in range(4)
                    )
                    self.emit(f"for o in range({width}):", 2)
                    self.emit(f"{t}[c * {width} + o] += {terms}", 3)
                if blocked < ka:
                    self.emit(f"for i in range({blocked}, {ka}):", 1)
                    self.emit(f"s = {ta}[c * {ka} + i]", 2)
                    self.emit(f"for o in range({width}):", 2)
                    self.emit(f"{t}[c * {width} + o] += s * p[{off} + i * {width} + o]", 3)
            elif kind in _ELEMENTWISE:
                for a, span, scale, a_off, off in _elementwise_terms(w, nd, rule):
                    self.push(nd, a, span, scale, doff=off, soff=a_off)
            elif kind == "chain":  # T_y = T_a J' (J the chain's Jacobian at the row)
                _, c, a, wo = rule
                t, ta, ka = self.tangent(nd), self.T[a], w.widths[a]
                self.emit(f"for c in range({k}):")
                self.emit(f"for o in range({wo}):", 1)
                self.emit("acc = 0.0", 2)
                self.emit(f"for i in range({ka}):", 2)
                self.emit(f"acc += {ta}[c * {ka} + i] * JC{c}[ii, o, i]", 3)
                self.emit(f"{t}[c * {wo} + o] = acc", 2)
            elif kind == "submodule":  # on (x, u): its Jacobians' columns
                idx = self.sub_index(nd.target)
                t = self.tangent(nd)
                self.emit(f"for o in range({width}):")
                self.emit(f"for c in range({n}):", 1)
                self.emit(f"{t}[c * {width} + o] = S{idx}a[r, o, c]", 2)
                self.emit(f"for c in range({k - n}):", 1)
                self.emit(f"{t}[(c + {n}) * {width} + o] = S{idx}b[r, o, c]", 2)

    def curvature(self, nd: fx.Node, rule: tuple, src: tuple) -> None:
        """Node ``nd``'s second-order term with its sensitivity ``src``."""
        g, width = src
        w, kind = self.w, rule[0]

        def each(coef, a, b, symmetric):
            # hz_j += sum_i C_ji T_a[:, i] T_b[:, i]' (+ its transpose), C = G diag(coef):
            # the pairs c >= d of the symmetric sum, every output's sum a local over i
            ta, tb, k, n = self.T[a], self.T[b], self.k, self.n
            self.count += 1
            C = f"cw{self.count}"
            self.emit(f"{C} = {self.new_array(n * width)}")
            self.entries(
                width,
                lambda i: (
                    [(f"s = {coef(i)}", 0)]
                    + self.outputs(
                        lambda j: [(f"{C}[{_at(j, width, i)}] = {g}[{_at(j, width, i)}] * s", 0)]
                    )
                ),
            )
            pair = f"{ta}[c * {width} + i] * {tb}[d * {width} + i]"
            if symmetric:
                pair = f"({pair} + {tb}[c * {width} + i] * {ta}[d * {width} + i])"
            rows = range(n) if n <= _UNROLL_OUTPUTS else ["j"]
            base = 2 if n <= _UNROLL_OUTPUTS else 3
            self.emit(f"for c in range({k}):")
            self.emit("for d in range(c + 1):", 1)
            if n > _UNROLL_OUTPUTS:
                self.emit(f"for j in range({n}):", 2)
            for j in rows:
                self.emit(f"acc{j} = 0.0", base)
            self.emit(f"for i in range({width}):", base)
            self.emit(f"pcd = {pair}", base + 1)
            for j in rows:
                self.emit(f"acc{j} += {C}[{_at(j, width, 'i')}] * pcd", base + 1)
            for j in rows:
                self.emit(f"hz[({j} * {k} + c) * {k} + d] += acc{j}", base)
                self.emit("if d != c:", base)
                self.emit(f"hz[({j} * {k} + d) * {k} + c] += acc{j}", base + 1)

        def h(i):
            return w.entry(nd, i)

        if kind == "activation":
            _, a, (_, curve) = rule
            if _var(a) and curve != "0.0":
                each(lambda i: curve.format(a=w.entry(a, i), h=h(i)), a, a, False)
        elif kind == "product":
            _, a, _, b, _ = rule
            if _var(a) and _var(b):
                each(lambda i: "1.0", a, b, True)
        elif kind == "quotient":
            _, a, _, b, b_text = rule
            if _var(b):  # d2/db2 = 2 h / b^2; d2/da db = -1 / b^2
                each(lambda i: f"(2.0 * {h(i)} / ({b_text(i)} * {b_text(i)}))", b, b, False)
                if _var(a):
                    each(lambda i: f"(-1.0 / ({b_text(i)} * {b_text(i)}))", a, b, True)
        elif kind == "chain":
            self._chain_curvature(rule, g)
        elif kind == "submodule":
            idx, k = self.sub_index(nd.target), self.k
            self.emit(f"for j in range({self.n}):")
            self.emit(f"for o in range({width}):", 1)
            self.emit(f"gs = {g}[j * {width} + o]", 2)
            self.emit(f"for c in range({k}):", 2)
            self.emit(f"for d in range({k}):", 3)
            self.emit(f"hz[(j * {k} + c) * {k} + d] += gs * S{idx}h[r, o, c, d]", 4)

    def _chain_curvature(self, rule: tuple, g: str) -> None:
        """A layer chain's second-order term: ``hz_j += T_a' (sum_o G_jo H_o) T_a``, ``H
        (rows, wo, ka, ka)`` every output's Hessian in the chain's input, of the block
        (:mod:`torchslq.dynamics.network_chains`)."""
        _, c, a, wo = rule
        ta, ka, k, n = self.T[a], self.w.widths[a], self.k, self.n
        self.count += 1
        M, P = f"cm{self.count}", f"cp{self.count}"
        self.emit(f"{M} = {self.new_array(ka * ka)}")
        self.emit(f"{P} = {self.new_array(k * ka)}")
        self.emit(f"for j in range({n}):")
        self.emit(f"for q in range({ka * ka}):", 1)
        self.emit(f"{M}[q] = 0.0", 2)
        self.emit(f"for o in range({wo}):", 1)
        self.emit(f"gs = {g}[j * {wo} + o]", 2)
        self.emit(f"for i in range({ka}):", 2)
        self.emit(f"for l in range({ka}):", 3)
        self.emit(f"{M}[i * {ka} + l] += gs * HC{c}[ii, o, i, l]", 4)
        self.emit(f"for c in range({k}):", 1)  # P = T_a M
        self.emit(f"for l in range({ka}):", 2)
        self.emit("acc = 0.0", 3)
        self.emit(f"for i in range({ka}):", 3)
        self.emit(f"acc += {ta}[c * {ka} + i] * {M}[i * {ka} + l]", 4)
        self.emit(f"{P}[c * {ka} + l] = acc", 3)
        self.emit(f"for c in range({k}):", 1)  # hz_j += P T_a'
        self.emit(f"for d in range({k}):", 2)
        self.emit("acc = 0.0", 3)
        self.emit(f"for l in range({ka}):", 3)
        self.emit(f"acc += {P}[c * {ka} + l] * {ta}[d * {ka} + l]", 4)
        self.emit(f"hz[(j * {k} + c) * {k} + d] += acc", 3)


#: the rules whose derivatives are entrywise (:func:`_elementwise_terms`)
_ELEMENTWISE = ("activation", "sum", "product", "quotient", "slice", "cat")


def _elementwise_terms(w, nd: fx.Node, rule: tuple) -> list[tuple]:
    """Node ``nd``'s derivatives by its entrywise ``rule``, one tuple ``(a, span, scale,
    a_off, off)`` per argument: ``d nd[off + i] / d a[a_off + i] = scale(i)`` for ``i <
    span`` (``scale`` None: 1; a number; or ``i -> expression``). The reverse sweep
    carries sensitivities back by them, the forward tangents forward."""
    kind, width = rule[0], w.widths[nd]
    if kind == "activation":  # h = s(a): s'(a) from a and h
        _, a, (slope, _) = rule
        return [(a, width, lambda i: slope.format(a=w.entry(a, i), h=w.entry(nd, i)), 0, 0)]
    if kind == "sum":
        return [(a, width, sign, 0, 0) for a, sign in rule[1]]
    if kind == "product":  # a b: b and a
        _, a, a_text, b, b_text = rule
        return [(a, width, b_text, 0, 0), (b, width, a_text, 0, 0)]
    if kind == "quotient":  # h = a / b: 1 / b and -h / b
        _, a, _, b, b_text = rule
        return [
            (a, width, lambda i: f"(1.0 / {b_text(i)})", 0, 0),
            (b, width, lambda i: f"(-{w.entry(nd, i)} / {b_text(i)})", 0, 0),
        ]
    if kind == "slice":
        _, source, start = rule
        return [(source, width, None, start, 0)]
    terms, start = [], 0  # cat
    for piece in rule[1]:
        terms.append((piece, w.widths[piece], None, 0, start))
        start += w.widths[piece]
    return terms


def _arguments(rule: tuple) -> list:
    """The nodes and constants a rule reads."""
    kind = rule[0]
    if kind == "sum":
        return [a for a, _ in rule[1]]
    if kind in ("product", "quotient"):
        return [rule[1], rule[3]]
    if kind == "cat":
        return list(rule[1])
    if kind == "chain":
        return [rule[2]]
    return [rule[1]] if kind != "submodule" else [rule[1], rule[2]]


def _tangents_needed(program, rules: dict) -> set:
    """The nodes whose tangents a second-order term reads (a curved activation's input,
    a product's or quotient's operands) and every node those depend on."""
    seeds = []
    for nd in program.nodes:
        rule = rules.get(nd)
        if rule is None:
            continue
        if rule[0] == "activation" and rule[2][1] != "0.0":
            seeds.append(rule[1])
        elif rule[0] in ("product", "quotient"):
            seeds += [rule[1], rule[3]]
        elif rule[0] == "chain":
            seeds.append(rule[2])
    needed: set = set()
    while seeds:
        nd = seeds.pop()
        if not _var(nd) or nd in needed:
            continue
        needed.add(nd)
        if nd in rules:
            seeds += _arguments(rules[nd])
    return needed


def _factor(scale, i) -> tuple[list, str]:
    """The lines computing entry ``i``'s factor ``s`` and the text multiplying by it
    (``scale`` None: 1; a number; or ``i -> expression``)."""
    if callable(scale):
        return [(f"s = {scale(i)}", 0)], " * s"
    if scale is not None and scale != 1.0:
        return [], f" * {float(scale)!r}"
    return [], ""


def _name(j) -> str:
    return str(j)


def _at(j, width: int, i, offset=0) -> str:
    """The index of entry ``(j, offset + i)`` of a row-major ``(., width)`` array."""
    if isinstance(j, int) and isinstance(i, int):
        return str(j * width + offset + i)
    head = f"{j * width}" if isinstance(j, int) else f"{j} * {width}"
    tail = f"{i}" if not offset else f"{i} + {offset}"
    return f"{head} + {tail}"


def write_jacobians(
    w, program, root, n: int, m: int, narrow: int, new_array, weight_rows, weights=None,
    rules=None,
):  # fmt: skip
    """The lines of the generated ``jacobians`` function's sweep (to follow the step's
    forward lines in the row loop) and the Dynamics submodules whose Jacobians it takes
    as arguments (targets, in order). ``w`` is the forward writer after the step's nodes;
    ``weight_rows(target)`` the offset of a layer's weight rows in ``p``. With
    ``weights(target)`` (the offset of its transposed weight, the step's), the lines of
    the ``hessians`` function instead: also every output's Hessian into ``H[r]`` (and
    each submodule's Hessians taken as a third argument). ``rules``: the writer's rules
    with changes (a layer chain's, :func:`torchslq.dynamics.network_chains.reverse_rules`;
    None: ``w.rules``). Raises :class:`_Unsupported` for what it does not write."""
    rules = w.rules if rules is None else rules
    second = weights is not None
    sweep = _Second(w, n, m, narrow, new_array) if second else _Sweep(w, n, narrow, new_array)
    if second:
        for nd in program.nodes:
            rule = w.rules.get(nd)
            if (
                rule is not None
                and rule[0] == "submodule"
                and tuple(rule[1:]) != tuple(program.inputs)
            ):
                raise _Unsupported("a Dynamics submodule on other nodes than (x, u)")
        sweep.forward_tangents(program, tuple(program.inputs), rules, weights)
        size = n * sweep.k * sweep.k
        sweep.emit(f"hz = {new_array(size)}")
        sweep.emit(f"for q in range({size}):")
        sweep.emit("hz[q] = 0.0", 1)
    out = program.output
    g, _ = sweep.grad(out)
    for j in range(n):
        sweep.emit(f"{g}[{j * n + j}] = 1.0")
    for nd in reversed(program.nodes):
        if nd.op in ("placeholder", "output", "get_attr") or nd not in sweep.G:
            continue
        rule = rules.get(nd)
        if rule is None:
            raise _Unsupported(f"no reverse rule for {nd.op} {nd.target}")
        width = w.widths[nd]
        src = (sweep.G.pop(nd), width)
        _apply(sweep, nd, rule, src, tuple(program.inputs), weight_rows)
        if second:
            sweep.curvature(nd, rule, src)
    xin, uin = program.inputs
    for node, name, k in ((xin, "A", n), (uin, "B", m)):
        g = sweep.G.get(node)
        sweep.emit(f"for j in range({n}):")
        sweep.emit(f"for i in range({k}):", 1)
        sweep.emit(f"{name}[r, j, i] = {'0.0' if g is None else f'{g}[j * {k} + i]'}", 2)
    if second:
        k = n + m
        sweep.emit(f"for q in range({n * k * k}):")
        sweep.emit(f"H[r, q // {k * k}, (q // {k}) % {k}, q % {k}] = hz[q]", 1)
    return sweep.lines, sweep.subs


def _apply(sweep: _Sweep, nd: fx.Node, rule: tuple, src: tuple, inputs: tuple, weight_rows):
    """Node ``nd``'s sensitivity ``src`` (its array and width) carried to its arguments
    by its ``rule`` (how the forward writer computed it)."""
    w, kind = sweep.w, rule[0]
    if kind == "linear":
        _, a, target = rule
        sweep.linear(nd, a, src[0], weight_rows(target))
    elif kind in _ELEMENTWISE:
        for a, span, scale, a_off, off in _elementwise_terms(w, nd, rule):
            sweep.scaled_add(a, src, span, scale, doff=a_off, soff=off)
    elif kind == "submodule":
        _, a, b = rule
        sweep.submodule(nd, src[0], inputs, (a, b))
    elif kind == "chain":
        sweep.chain(src[0], rule)
    else:  # pragma: no cover - every rule the writer records is handled above
        raise _Unsupported(kind)
