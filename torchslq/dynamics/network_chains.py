"""A learned model's wide layer chains differentiated in blocks of rows.

The generated ``jacobians`` function (:mod:`torchslq.dynamics.network_reverse`) runs the
step's forward code and the reverse sweep one row at a time. For a chain of wide layers
(``Linear - tanh - Linear - tanh - Linear`` on ``cat([x, u])``, say) each row then
reloads every weight for a matrix-vector product: a 5-64-64-4 MLP ran its products at
5-7 GFMA/s, where a matrix product over rows runs at several times that. Here such a
chain is taken out of the row loop: rows are handled :data:`BLOCK_ROWS` at a time, and
for each block

1. the chain's input ``a (rows, k)`` is computed row by row (only the nodes it depends
   on), into ``CIN``;
2. the chain's forward pass and its Jacobian ``J = d out / d a (rows, wo, k)`` (``wo``
   outputs seeded with the identity, swept back: ``G <- G diag(s'(z))`` through an
   activation, ``G <- G W`` through a layer) run on the whole block, each layer's
   product one ``np.dot`` (BLAS) over the block's rows;
3. the row loop runs as before, with the chain's output read from the block and its
   reverse step ``G_a += G_out J[row]``.

A chain is a sequence of nodes, each a ``nn.Linear`` layer or an activation (a module,
function or method the step writes) of the one before, each but the last used by the
next alone, with a layer at least :data:`WIDE` wide on both sides and at most ``n``
outputs (its Jacobian then costs no more than the row sweep's ``n`` sensitivities). Its
input must not depend on another chain. The results equal the row sweep's to rounding
(the products sum in BLAS's order). Needs numba's BLAS (scipy); without it no chain is
taken.

The Hessians' function takes the chains the same way (their tangents pushed forward on
the block), and so does the step on many rows at once, ``step_rows(r0, r1, X, U, p,
OUT)`` (:func:`step_rows_lines`: steps 1 and 3 with the chain's forward pass between,
no derivatives), which the rollouts and the fused line search call once per time step
for all their rows (:func:`torchslq._backend.model_fns.register_rows`): on the cart-pole
with a 5-64-64-4 tanh residual, a step of 64 rows took about 0.6 us a row instead of
0.85 as one-row steps.
"""

from __future__ import annotations

import re
from typing import NamedTuple

from torch import fx

from .graph_jacobian import _var

#: the narrowest layer (inputs and outputs) that makes a chain worth a block
WIDE = 16
#: rows per block: the block's arrays (a few (32, 64) float64 arrays) stay in L1/L2, and
#: each product is large enough for BLAS's kernels
BLOCK_ROWS = 32


class Chain(NamedTuple):
    """A chain of layers and activations (module docstring), numbered ``index``."""

    index: int
    input: fx.Node
    output: fx.Node
    nodes: tuple[fx.Node, ...]
    #: ``("linear", k, width, weight offset (k, width), row offset (width, k), bias
    #: offset or None)`` or ``("activation", form, slope, width, curvature)``, in
    #: forward order
    ops: tuple[tuple, ...]


#: False: no chain is taken (the row sweep alone; to compare the two)
enabled = True


def _blas_available() -> bool:
    """Whether numba can compile ``np.dot`` (it calls scipy's BLAS)."""
    try:
        import scipy.linalg.cython_blas  # noqa: F401
    except ImportError:
        return False
    return True


def find_chains(program, w, n: int, weights, weight_rows) -> list[Chain]:
    """The chains of ``program`` as the forward writer ``w`` wrote it (its ``rules``,
    ``forms`` and ``widths``); ``weights(target)`` / ``weight_rows(target)``: a layer's
    offsets in the parameter array (transposed, and as it is)."""
    if not enabled:
        return []
    rules, forms = w.rules, w.forms

    def link(nd):
        """The node ``nd`` is a chain step on, or None."""
        rule = rules.get(nd)
        if rule is None or rule[0] not in ("linear", "activation") or not _var(rule[1]):
            return None
        if rule[0] == "activation" and nd not in forms:
            return None
        return rule[1]

    def only_user(nd):
        users = list(nd.users)
        return users[0] if len(users) == 1 else None

    chains: list[Chain] = []
    taken: set = set()
    for nd in program.nodes:
        prev = link(nd)
        if nd in taken or prev is None:
            continue
        if link(prev) is not None and only_user(prev) is nd:
            continue  # (inside a chain that starts earlier and was not taken)
        nodes = [nd]
        while (nxt := only_user(nodes[-1])) is not None and link(nxt) is nodes[-1]:
            nodes.append(nxt)
        taken.update(nodes)
        ops = []
        for c in nodes:
            rule = rules[c]
            if rule[0] == "linear":
                k, width = w.widths[rule[1]], w.widths[c]
                mod_bias = _bias_offset(w, rule[2])
                ops.append(("linear", k, width, weights(rule[2]), weight_rows(rule[2]), mod_bias))
            else:
                ops.append(("activation", forms[c], rule[2][0], w.widths[c], rule[2][1]))
        wide = any(op[0] == "linear" and min(op[1], op[2]) >= WIDE for op in ops)
        if not wide or w.widths[nodes[-1]] > n:
            continue
        if _depends_on(prev, [q for ch in chains for q in ch.nodes]):
            continue
        chains.append(Chain(len(chains), prev, nodes[-1], tuple(nodes), tuple(ops)))
    if chains and not _blas_available():
        return []
    return chains


def _bias_offset(w, target: str):
    """The bias's offset in the parameter array (registered by the writer), or None."""
    return w.offsets.get(("bias", target))


def _depends_on(node: fx.Node, nodes: list) -> bool:
    """Whether ``node`` is one of ``nodes`` or computed from one."""
    seen, stack, targets = set(), [node], set(nodes)
    while stack:
        q = stack.pop()
        if q in targets:
            return True
        if q in seen or not isinstance(q, fx.Node):
            continue
        seen.add(q)
        stack.extend(a for a in q.all_input_nodes)
    return False


def live_nodes(w, program, text: str) -> set:
    """The nodes whose values ``text`` (a derivative sweep's lines) reads, and those
    they are computed from: the forward code the sweep needs. (The rest is dropped from
    the derivatives' functions: a Dynamics submodule's step, say, whose value no
    derivative reads, is a call LLVM cannot remove.)"""
    words = set(re.findall(r"[A-Za-z_]\w*", text))
    read = []
    for nd, v in w.values.items():
        if not isinstance(nd, fx.Node):
            continue
        texts = [v] if isinstance(v, str) else v
        if any(t in words for e in texts for t in re.findall(r"[A-Za-z_]\w*", e)):
            read.append(nd)
    return _ancestors(read)


def _ancestors(nodes: list, stop: set = frozenset()) -> set:
    """``nodes`` and the nodes they are computed from, not looking past those in
    ``stop``."""
    seen, stack = set(), list(nodes)
    while stack:
        q = stack.pop()
        if q in seen:
            continue
        seen.add(q)
        if q not in stop:
            stack.extend(q.all_input_nodes)
    return seen


def _arrays(chain: Chain, rows: str, hessians: bool, jacobian: bool = True) -> list[str]:
    """Allocations of a chain's block arrays for ``rows`` rows: its input's and nodes';
    with ``jacobian`` the sensitivities' (with ``hessians``, the tangents' and the
    outputs' Hessians' too)."""
    c, k, wo = chain.index, _width_in(chain), _width_out(chain)
    lines = [f"CIN{c} = np.empty(({rows}, {k}))"]
    for i, op in enumerate(chain.ops):
        lines.append(f"Z{c}_{i} = np.empty(({rows}, {_width(op)}))")
    if not jacobian:
        return lines
    lines.append(f"G{c}_{len(chain.ops)} = np.empty(({rows} * {wo}, {wo}))")
    for i, op in enumerate(chain.ops):
        if op[0] == "linear":
            lines.append(f"G{c}_{i} = np.empty(({rows} * {wo}, {op[1]}))")
    if hessians:
        lines.append(f"TI{c} = np.empty(({rows} * {k}, {k}))")
        for i, op in enumerate(chain.ops):
            lines.append(f"TZ{c}_{i} = np.empty(({rows} * {k}, {_width(op)}))")
        lines.append(f"HC{c} = np.empty(({rows}, {wo}, {k}, {k}))")
        for i, op in enumerate(chain.ops):
            if op[0] == "activation":
                lines.append(f"CV{c}_{i} = np.empty(({rows} * {wo}, {op[3]}))")
    return lines


def _width(op: tuple) -> int:
    """An op's output width."""
    return op[2] if op[0] == "linear" else op[3]


def _width_in(chain: Chain) -> int:
    op = chain.ops[0]
    return op[1] if op[0] == "linear" else op[3]


def _width_out(chain: Chain) -> int:
    return _width(chain.ops[-1])


def function_lines(
    chains: list[Chain], w, program, n: int, sweep: list[str], header: str,
    hessians: bool = False,
) -> list[str]:  # fmt: skip
    """The generated ``jacobians`` function with ``chains`` taken out of the row loop
    (module docstring): its ``def`` line ``header``, the forward writer ``w`` (its lines
    and ``spans``) of a model with ``n`` states, and the reverse sweep's lines ``sweep``
    (written with the chains' rules, :func:`reverse_rules`); with ``hessians``, the
    ``hessians`` function's (the chains' outputs' Hessians too)."""
    ind = "    "
    out = _blocks_head(chains, w, program, header, n, hessians, jacobian=True)
    # 2. the chains on the block
    for ch in chains:
        out += [ind * 2 + line for line in _block(ch, hessians)]
    # 3. the rows, the chains' outputs read from the block (the nodes the sweep reads)
    out += _row_loop(ind * 2)
    live = live_nodes(w, program, "\n".join(sweep))
    out += [ind * 2 + line for line in _rows_body(chains, w, program, live)]
    out += [ind + line for line in sweep]
    return out


def step_rows_lines(chains: list[Chain], w, program, n: int, output: list[str]) -> list[str]:
    """The generated ``step_rows(r0, r1, X, U, p, OUT)``: ``OUT[r] = step(X[r], U[r])``
    for the rows ``r0 <= r < r1`` of ``X (R, n)``, ``U (R, m)``, with ``chains`` on
    blocks of rows as in the Jacobians' function, forward only (each layer one
    ``np.dot`` over the block instead of a matrix-vector product per row: a rollout's
    step on many rows). ``w``: the forward writer (its lines and ``spans``); ``output``:
    the step's lines that write its value into ``out``."""
    ind = "    "
    head = "def step_rows(r0, r1, X, U, p, OUT):"
    out = _blocks_head(chains, w, program, head, n, False, jacobian=False)
    for ch in chains:
        out += [ind * 2 + line for line in _forward_block(ch)[0]]
    out += _row_loop(ind * 2) + [f"{ind * 3}out = OUT[r]"]
    # the nodes the output needs, a chain's output read from its block: not the nodes
    # only its input needs (computed in step 1; a feature map's sin and cos, say)
    live = _ancestors([program.output], stop={ch.output for ch in chains})
    out += [ind * 2 + line for line in _rows_body(chains, w, program, live) + output]
    return out


def _blocks_head(
    chains: list[Chain], w, program, header: str, n: int, hessians: bool, jacobian: bool
) -> list[str]:
    """A blocked function's lines up to its chains' passes: ``header``, the chains'
    weights as 2-d arrays (for np.dot; transposed too, with ``jacobian``) and block
    arrays, the loop over blocks and (step 1) the chains' inputs, row by row."""
    ind = "    "
    out = [header, f"{ind}work = np.empty((8, {n}))"]
    for ch in chains:
        for i, op in enumerate(ch.ops):
            if op[0] == "linear":
                _, k, width, woff, wr, _ = op
                out.append(
                    f"{ind}W{ch.index}_{i} = np.ascontiguousarray(p[{woff}:{woff + k * width}])"
                    f".reshape(({k}, {width}))"
                )
                if jacobian:
                    out.append(
                        f"{ind}V{ch.index}_{i} = np.ascontiguousarray(p[{wr}:{wr + k * width}])"
                        f".reshape(({width}, {k}))"
                    )
        out += [ind + line for line in _arrays(ch, str(BLOCK_ROWS), hessians, jacobian)]
    out.append(f"{ind}for b0 in range(r0, r1, {BLOCK_ROWS}):")
    out.append(f"{ind * 2}rb = min({BLOCK_ROWS}, r1 - b0)")
    out.append(f"{ind * 2}if rb != {BLOCK_ROWS}:  # (the last block)")
    for ch in chains:
        out += [ind * 3 + line for line in _arrays(ch, "rb", hessians, jacobian)]
    # 1. the chains' inputs, row by row
    chained = {q for ch in chains for q in ch.nodes}
    needed = _ancestors([ch.input for ch in chains])
    out += _row_loop(ind * 2)
    lines = w.lines
    a, b = w.spans[None]
    body = list(lines[a:b])
    for nd in program.nodes:
        if nd in needed and nd in w.spans and nd not in chained:
            a, b = w.spans[nd]
            body += lines[a:b]
    for ch in chains:
        body += _store(w, ch)
    return out + [ind * 2 + line for line in body]


def _rows_body(chains: list[Chain], w, program, live: set) -> list[str]:
    """The row loop's body after the chains' passes (step 3): the ``live`` nodes' code
    in graph order, each chain's output read from its block."""
    chained = {q for ch in chains for q in ch.nodes}
    outputs = {ch.output: ch for ch in chains}
    lines = w.lines
    a, b = w.spans[None]
    body = list(lines[a:b])
    for nd in program.nodes:
        if nd not in w.spans or nd not in live:
            continue
        if nd in outputs:
            body += _read(w, outputs[nd])
        elif nd not in chained:
            a, b = w.spans[nd]
            body += lines[a:b]
    return body


def _row_loop(indent: str) -> list[str]:
    return [
        f"{indent}for ii in range(rb):",
        f"{indent}    r = b0 + ii",
        f"{indent}    x = X[r]",
        f"{indent}    u = U[r]",
    ]


def _store(w, ch: Chain) -> list[str]:
    """The chain's input at the row into ``CIN`` (function-level indent)."""
    v = w.values[ch.input]
    c, k = ch.index, w.widths[ch.input]
    if isinstance(v, list):
        return [f"    CIN{c}[ii, {q}] = {v[q]}" for q in range(k)]
    return [f"    for q in range({k}):", f"        CIN{c}[ii, q] = {v}[q]"]


def _read(w, ch: Chain) -> list[str]:
    """The chain's output at the row, under the names the following nodes read."""
    v = w.values[ch.output]
    out = f"Z{ch.index}_{len(ch.ops) - 1}"
    if isinstance(v, list):
        return [f"    {name} = {out}[ii, {q}]" for q, name in enumerate(v)]
    return [f"    {v} = {out}[ii]"]


def _forward_block(ch: Chain) -> tuple[list[str], dict]:
    """The chain's forward pass on the block (``rb`` rows of ``CIN``, each layer one
    ``np.dot``, its bias and a following activation in one pass over the block):
    ``(lines, acts)``, ``acts`` the arrays before and after each activation (by op
    index)."""
    c = ch.index
    lines = []
    prev = f"CIN{c}"
    acts = {}  # op index -> (pre-activation array, activation array)
    for i, op in enumerate(ch.ops):
        z = f"Z{c}_{i}"
        if op[0] == "linear":
            _, _, width, _, _, boff = op
            lines.append(f"np.dot({prev}, W{c}_{i}, {z})")
            nxt = ch.ops[i + 1] if i + 1 < len(ch.ops) else None
            if boff is None and (nxt is None or nxt[0] != "activation"):
                prev = z
                continue
            # the bias and a following activation in one pass over the block
            lines += ["for ii in range(rb):", f"    for o in range({width}):"]
            if boff is not None:
                lines.append(f"        {z}[ii, o] += p[{boff} + o]")
            if nxt is not None and nxt[0] == "activation":
                h = f"Z{c}_{i + 1}"
                lines.append(f"        {h}[ii, o] = {nxt[1].format(f'{z}[ii, o]')}")
        elif i == 0 or ch.ops[i - 1][0] != "linear":  # (else written with its layer)
            _, form, _, width, _ = op
            lines += [
                "for ii in range(rb):",
                f"    for o in range({width}):",
                f"        {z}[ii, o] = {form.format(f'{prev}[ii, o]')}",
            ]
        if op[0] == "activation":
            acts[i] = (prev, z)
        prev = z
    return lines, acts


def _block(ch: Chain, hessians: bool) -> list[str]:
    """The chain's forward pass and Jacobian on the block (``rb`` rows of ``CIN``); with
    ``hessians`` also every output's Hessian ``HC (rb, wo, k, k)``: the tangents ``T =
    d node / d CIN`` pushed forward, and each activation adding ``T_z' diag(G s''(z))
    T_z`` in the sweep back (``G`` the outputs' sensitivities to its value)."""
    c, wo, k = ch.index, _width_out(ch), _width_in(ch)
    lines, acts = _forward_block(ch)
    tangents = {}  # activation index -> the tangent array of its input
    if hessians:
        t = f"TI{c}"
        lines += [
            "for ii in range(rb):",
            f"    for c in range({k}):",
            f"        for q in range({k}):",
            f"            {t}[ii * {k} + c, q] = 1.0 if c == q else 0.0",
        ]
        for i, op in enumerate(ch.ops):
            tz = f"TZ{c}_{i}"
            if op[0] == "linear":
                lines.append(f"np.dot({t}, W{c}_{i}, {tz})")
            else:
                a, h = acts[i]
                slope = op[2].format(a=f"{a}[ii, q]", h=f"{h}[ii, q]")
                lines += [
                    "for ii in range(rb):",
                    f"    for c in range({k}):",
                    f"        for q in range({op[3]}):",
                    f"            {tz}[ii * {k} + c, q] = {t}[ii * {k} + c, q] * {slope}",
                ]
                tangents[i] = t
            t = tz
        lines += [
            "for ii in range(rb):",
            f"    for o in range({wo}):",
            f"        for c in range({k}):",
            f"            for d in range({k}):",
            f"                HC{c}[ii, o, c, d] = 0.0",
        ]
    # J = d out / d CIN: the identity swept back
    g = f"G{c}_{len(ch.ops)}"
    lines += [
        "for ii in range(rb):",
        f"    for o in range({wo}):",
        f"        for q in range({wo}):",
        f"            {g}[ii * {wo} + o, q] = 1.0 if o == q else 0.0",
    ]
    for i in range(len(ch.ops) - 1, -1, -1):
        op = ch.ops[i]
        if op[0] == "linear":
            nxt = f"G{c}_{i}"
            lines.append(f"np.dot({g}, V{c}_{i}, {nxt})")
            g = nxt
        else:
            _, _, slope, width, curve = op
            a, h = acts[i]
            if hessians and curve != "0.0":  # (G: the sensitivities to the activation)
                cv = f"CV{c}_{i}"
                term = curve.format(a=f"{a}[ii, q]", h=f"{h}[ii, q]")
                lines += [
                    "for ii in range(rb):",
                    f"    for o in range({wo}):",
                    f"        for q in range({width}):",
                    f"            {cv}[ii * {wo} + o, q] = {g}[ii * {wo} + o, q] * {term}",
                    f"_chain_curvature(rb, {k}, {wo}, {cv}, {tangents[i]}, HC{c})",
                ]
            s = slope.format(a=f"{a}[ii, q]", h=f"{h}[ii, q]")
            lines += [  # (the slope again for each output: a contiguous inner loop)
                "for ii in range(rb):",
                f"    for o in range({wo}):",
                f"        for q in range({width}):",
                f"            {g}[ii * {wo} + o, q] *= {s}",
            ]
    lines.append(f"JC{c} = {g}.reshape((rb, {wo}, {_width_in(ch)}))")
    return lines


def reverse_rules(w, chains: list[Chain]) -> dict:
    """The writer's rules with each chain's output stepping straight to its input
    (``("chain", index, input, outputs)``)."""
    rules = dict(w.rules)
    for ch in chains:
        for nd in ch.nodes:  # (their values are not computed in the rows)
            rules.pop(nd, None)
        rules[ch.output] = ("chain", ch.index, ch.input, _width_out(ch))
    return rules
