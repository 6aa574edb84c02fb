"""Compiled functions generated from a user's own torch model.

A :class:`~torchslq.ContinuousDynamics` written in plain torch ops is called a dozen
tiny ops at a time: a rollout of ``T`` RK4 steps is ``4 T`` calls of its ``forward``,
each ~50 us of dispatch for a few flops, and its Jacobians come from ``torch.func``
passes of the same kind. The library's CPU kernels (:mod:`torchslq.dynamics.compiled_rk4`,
the compiled rollouts) need the model's right-hand side and derivatives as numba
functions (:meth:`~torchslq.ContinuousDynamics.compiled_rhs`,
:meth:`~torchslq.ContinuousDynamics.compiled_derivatives`). This module derives them
from the model's own ``forward``, so a user's model runs on the same kernels as a model
with hand-written compiled code:

1. **trace** ``forward`` on two rows into a ``torch.fx`` graph of aten ops
   (:mod:`torchslq.dynamics._trace`: functionalized, so in-place writes and views
   become plain ops; Python control flow that depends on the values cannot be traced
   and the model is left on the torch path);
2. **evaluate** the traced aten graph on numpy arrays of ``sympy`` expressions in the
   row's entries ``x_i``, ``u_j`` and the model's parameters ``p_k`` (its parameters and
   buffers, flattened), and check the rows are independent and alike (a model that
   mixes rows, or a per-element parameter, is left on the torch path);
3. **differentiate** symbolically: the Jacobian ``[f_x | f_u]`` and every output's
   Hessian in ``z = (x, u)``, whose nonzero pattern is the model's curvature pattern
   (:class:`~torchslq.dynamics.CompiledDerivatives`);
4. **print** the expressions after common-subexpression elimination as numba functions
   in a module file under the cache directory (``$TORCHSLQ_CACHE_DIR``, default
   ``~/.cache/torchslq``), keyed on a hash of the traced graph, so a later process
   imports them (numba's disk cache) without running steps 2-4 again;
5. **check** the compiled functions against the model's ``forward`` and its
   autograd derivatives at random points; a mismatch leaves the model on the torch
   path with a warning.

None of these steps imports torch's compiler stack (``torch._dynamo``,
``torch._inductor``: over a second in a fresh process, which ``make_fx``, fake tensors
and ``torch.func``'s reverse mode pay). A later process skips step 1 as well when it
can. A *source index* maps a key of what the traced graph depends on and is known
without tracing (the source files of the model's classes, its structure, the
generator's and torch's versions) to the module; a module found that way is used when
its step equals the model's ``forward`` at random points (a function the model calls
from another file may have changed), else the model is traced as above.

A discrete :class:`~torchslq.Dynamics` is generated the same way: its step, its
Jacobians and its Hessian blocks (:meth:`~torchslq.Dynamics.compiled_step`,
``compiled_jacobians``, ``compiled_vhp``). The library's kernels that run these
functions (the RK4 derivative passes, the rollouts) take them as first-class function
values (:mod:`torchslq._backend.model_fns`): those kernels are compiled once per machine
for every model, so a new model costs the compilation of its own two functions. The
module also holds the same kernels rewritten to call its functions directly
(:mod:`torchslq.dynamics._specialize`), where numba inlines them; large passes use
those (:mod:`torchslq._backend.bound`), compiled on first use and cached with the module.

The parameters travel as numbers (``params``), read from the module at each call: its
tensors, and its float attributes (a mass, a time step; one that steers Python control
flow is traced as a constant instead), so a model whose parameters change (training, a
sweep) uses the same compiled code. Models this cannot take (unsupported ops,
per-element parameters, networks, too large, value-dependent control flow) keep the
torch path; :func:`explain` says why.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import threading
import time
import warnings
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from .._backend.source_modules import cache_root, import_source, write_atomic
from .._pinned import _PINNED, solve_scope
from ._symbolic import Unsupported as _Unsupported
from ._symbolic import as_array, evaluate, symbols

__all__ = ["GeneratedHooks", "explain", "generated_hooks"]

#: bumped when the generated code changes meaning (part of the cache key)
CODEGEN_VERSION = 3
#: models larger than this keep the torch path (a network is faster as matrix ops)
MAX_GRAPH_NODES = 600
MAX_PARAMETERS = 256
MAX_EXPRESSION_OPS = 4000
#: larger models keep the torch path: their second derivatives (n (n+m)^2 / 2 entries)
#: take long to differentiate symbolically and to compile as straight-line code
MAX_STATE_PLUS_CONTROL = 20
MAX_GENERATED_LINES = 2500
#: seconds of symbolic differentiation before a model is left on the torch path (the
#: verdict is kept on disk beside the cache, so no later process with this budget or a
#: smaller one tries again)
DEFAULT_BUDGET_S = 20.0


class GeneratedHooks(NamedTuple):
    """What :func:`generated_hooks` derives from a model: ``rhs(x, u, p, out)`` and
    ``derivatives`` (a :class:`~torchslq.dynamics.CompiledDerivatives`, or a plain
    function for a model without curvature) as numba functions, and the names of the
    module tensors (parameters and buffers) whose flattened values make ``p``."""

    rhs: Callable
    derivatives: object
    tensor_names: tuple[str, ...]
    source_path: str | None
    #: ``step(x, u, p, out, work)`` of a discrete model (its ``rhs``); None for a
    #: continuous one (:func:`torchslq.discretize` makes its step)
    step: Callable | None = None

    def params(self, model: nn.Module) -> np.ndarray:
        """The current values of the model's tensors and float attributes (named
        ``@path.attr``), flattened into one float64 array (the ``p`` the generated
        functions read)."""
        # numpy pieces, not tensors: this runs on every rollout and linearisation
        tensors = dict(_named_tensors(model))
        parts = [
            np.array([_get_attr(model, k[1:])], dtype=np.float64)
            if k.startswith("@")
            else tensors[k].detach().to("cpu", torch.float64).reshape(-1).numpy()
            for k in self.tensor_names
        ]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.float64)


def _get_attr(model: nn.Module, path: str):
    mod, _, name = path.rpartition(".")
    return getattr(model.get_submodule(mod) if mod else model, name)


def _float_attrs(model: nn.Module) -> list[str]:
    """``path.attr`` of every module's public float attributes (a mass, a time step):
    traced as inputs, so the code reads their current values and a change or a sweep
    does not generate new code."""
    out = []
    for name, mod in model.named_modules():
        for k, v in vars(mod).items():
            if type(v) is float and not k.startswith("_"):
                out.append(f"{name}.{k}" if name else k)
    return out


_LOCK = threading.RLock()  # reentrant: a model whose forward calls another (a wrapped
# discretised model) builds the inner model's code while its own is being checked
# per model instance (weakly: a dropped model takes its entry with it, and the entry is
# not copied or pickled with the model): (structure key, hooks or None, reason)
_BUILT: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _enabled() -> bool:
    return os.environ.get("TORCHSLQ_CODEGEN", "1") not in ("0", "false", "off", "no")


def generated_hooks(model: nn.Module) -> GeneratedHooks | None:
    """The generated compiled functions of ``model`` (a :class:`~torchslq.ContinuousDynamics`
    called without ``t``, or a discrete :class:`~torchslq.Dynamics`: ``rhs`` is then the
    step), or None when it cannot be compiled (see
    :func:`explain`) or code generation is off (``TORCHSLQ_CODEGEN=0``, or the model's
    class sets ``generate_compiled_code = False``). Computed once per model instance
    and structure (parameter shapes, non-tensor attributes)."""
    if not _enabled() or not getattr(model, "generate_compiled_code", True):
        return None
    pinned = _PINNED.get()
    if pinned is not None:
        hit = pinned.get(id(model))
        if hit is not None and hit[0] is model:
            return hit[1]
        hooks = _generated_hooks(model)
        pinned[id(model)] = (model, hooks)
        return hooks
    return _generated_hooks(model)


def _generated_hooks(model: nn.Module) -> GeneratedHooks | None:
    """:func:`generated_hooks` without the pin of :func:`hooks_pinned`."""
    key = _structure_key(model)
    cached = _BUILT.get(model)
    if cached is not None and cached[0] == key:
        baked = cached[3]  # float attributes traced as constants: their values matter
        if baked is None or baked == tuple(_get_attr(model, a) for a in _float_attrs(model)):
            return cached[1]
    with _LOCK:
        baked = None
        try:
            try:
                hooks, reason = _build(model, lift_floats=True), ""
            except _Unsupported:  # e.g. a float attribute in an `if`: trace it as a constant
                hooks, reason = _build(model, lift_floats=False), ""
                baked = tuple(_get_attr(model, a) for a in _float_attrs(model))
        except _Unsupported as e:
            hooks, reason = None, str(e)
        except Exception as e:  # a model the tracer does not understand: torch path
            hooks, reason = None, f"{type(e).__name__}: {e}"
        _BUILT[model] = (key, hooks, reason, baked)
    return hooks


@contextlib.contextmanager
def hooks_pinned():
    """Within this block :func:`generated_hooks` answers for a model it has already
    answered for in the block without looking at the model again, and
    :func:`torchslq._pinned.pinned` keeps what a solve derives from its model and cost. A
    solver's loop runs inside it: checking the model's structure (its parameters' names
    and shapes, every module's plain attributes) took about 30 us, three times per
    iteration, a tenth of an iLQR iteration at B = 1; a model does not change its
    structure or values during a solve. Nested blocks share the outermost one's
    answers."""
    with solve_scope():
        yield


def explain(model: nn.Module) -> str:
    """Why ``model`` runs on generated compiled code or not: ``"compiled"`` or the reason
    it keeps the torch path."""
    if not _enabled():
        return "code generation is off (TORCHSLQ_CODEGEN=0)"
    if not getattr(model, "generate_compiled_code", True):
        return f"{type(model).__name__}.generate_compiled_code is False"
    hooks = generated_hooks(model)
    if hooks is not None:
        return "compiled"
    return _BUILT[model][2]


# ------------------------------------------------------------------------- structure
def _named_tensors(model: nn.Module) -> list[tuple[str, Tensor]]:
    return [*model.named_parameters(), *model.named_buffers()]


def _simple(v) -> bool:
    if isinstance(v, (bool, int, float, str, type(None))):
        return True
    return isinstance(v, (tuple, list)) and len(v) <= 64 and all(_simple(e) for e in v)


def _structure_key(model: nn.Module) -> tuple:
    """What the traced graph may depend on besides the tensors' values: their names and
    shapes, and every module's plain attributes (numbers a model's ``forward`` reads)."""
    tensors = tuple((k, tuple(t.shape)) for k, t in _named_tensors(model))
    attrs = []
    for name, mod in model.named_modules():
        for k, v in vars(mod).items():
            if type(v) is float and not k.startswith("_"):
                attrs.append((name, k, "float"))  # its value: see generated_hooks
            elif not k.startswith("_") and _simple(v):
                attrs.append((name, k, repr(v)))
            elif torch.is_tensor(v) and not k.startswith("_") and v.numel() <= MAX_PARAMETERS:
                # a plain tensor attribute is traced as a constant: key on its value
                attrs.append((name, k, tuple(v.detach().cpu().reshape(-1).tolist())))
    return (type(model), tensors, tuple(attrs))


# ------------------------------------------------------------------------- build
def _build(model: nn.Module, lift_floats: bool) -> GeneratedHooks:
    from .base import state_control_dims

    n, m = state_control_dims(model)
    if n + m > MAX_STATE_PLUS_CONTROL:
        raise _Unsupported(
            f"state_dim + control_dim = {n + m} (more than {MAX_STATE_PLUS_CONTROL}): its "
            "second derivatives are too many to generate as straight-line code"
        )
    named = _named_tensors(model)
    if lift_floats:
        named += [
            ("@" + a, torch.tensor(_get_attr(model, a), dtype=torch.float64))
            for a in _float_attrs(model)
        ]
    count = sum(t.numel() for _, t in named)
    if count > MAX_PARAMETERS:
        raise _Unsupported(
            f"{count} parameter entries (more than {MAX_PARAMETERS}): a network runs faster "
            "as batched matrix ops"
        )
    from .base import ContinuousDynamics

    kind = "continuous" if isinstance(model, ContinuousDynamics) else "discrete"
    skey = _source_key(model, kind, n, m, named, lift_floats)
    hooks = _from_source_index(model, skey, n, m, named)
    if hooks is not None:
        return hooks
    gm = _trace(model, n, m, named)
    consts = [getattr(gm, node.target) for node in gm.graph.nodes if node.op == "get_attr"]
    h = hashlib.sha256()
    h.update(
        f"v{CODEGEN_VERSION};{kind};{n};{m};{[(k, tuple(t.shape)) for k, t in named]}".encode()
    )
    h.update(gm.code.encode())
    h.update(_kernel_sources_digest())
    for c in consts:
        h.update(c.detach().cpu().to(torch.float64).contiguous().numpy().tobytes())
    digest = h.hexdigest()[:24]
    path = _cache_dir() / f"m_{digest}.py" if _cache_dir() is not None else None
    module = None
    if path is not None and path.exists():
        try:
            module = _import(path, digest)
        except Exception:  # a damaged file: generate it again
            module = None
    if module is None:
        refused = None if path is None else path.with_suffix(".unsupported")
        if refused is not None and refused.exists():
            reason = refused.read_text()
            # a time-out holds for budgets up to the one it ran out of: a larger budget
            # (TORCHSLQ_CODEGEN_BUDGET) tries again
            ran_out = _budget_of(reason)
            if ran_out is None or _budget() <= ran_out:
                raise _Unsupported(reason)
        try:
            source = _generate(gm, n, m, named, type(model).__name__, kind)
        except _Unsupported as e:
            if refused is not None:
                with contextlib.suppress(OSError):
                    refused.write_text(str(e))
            raise
        module = _write_and_import(path, digest, source)
    hooks = _hooks_of(module, named)
    # the code is a function of the traced graph: checked once, when first generated
    # (a module that failed its check has no marker and is checked again: same verdict)
    checked = None if path is None else path.with_suffix(".checked")
    if checked is None or not checked.exists():
        _check(model, hooks, n, m)
        if checked is not None:
            with contextlib.suppress(OSError):
                checked.touch()
    if skey is not None and path is not None:
        with contextlib.suppress(OSError):
            write_atomic(_cache_dir() / f"s_{skey}.txt", digest)
    return hooks


def _hooks_of(module, named: list[tuple[str, Tensor]]) -> GeneratedHooks:
    derivatives = module.derivatives
    if module.CURVED_OUTPUTS:
        from .base import CompiledDerivatives

        derivatives = CompiledDerivatives(
            module.derivatives, module.CURVED_OUTPUTS, module.CURVED_ENTRIES
        )
    from .._backend._numba_kernels import STEP_DISCRETE
    from .._backend.bound import register
    from .._backend.model_fns import register_step

    register(module)  # its kernels, for large passes
    step = None
    if module.ROLLOUT_MODE == STEP_DISCRETE:  # a discrete model: rhs is its step
        step = module.step
        register_step(step, module.rhs, STEP_DISCRETE)
    names = tuple(k for k, _ in named)
    return GeneratedHooks(module.rhs, derivatives, names, module.__file__, step)


# ------------------------------------------------------------------------- source index
def _source_key(model: nn.Module, kind: str, n: int, m: int, named, lift_floats: bool):
    """A key of what the traced graph depends on that is known without tracing (which
    runs the forward op by op and hashes its graph): the source files of the classes of
    the model's modules, its structure (tensor names and shapes, plain attributes; the
    floats' values where they are traced as constants), the generator and torch's
    version. None without a cache or when a class has no source file. A model's
    ``forward`` may still call code elsewhere: a hit is checked against it numerically
    (:func:`_from_source_index`)."""
    if _cache_dir() is None:
        return None
    import inspect

    h = hashlib.sha256()
    h.update(f"v{CODEGEN_VERSION};{kind};{n};{m};{torch.__version__};{lift_floats}".encode())
    h.update(repr([(k, tuple(t.shape)) for k, t in named]).encode())
    h.update(repr(_structure_key(model)[1:]).encode())
    if not lift_floats:
        h.update(repr([_get_attr(model, a) for a in _float_attrs(model)]).encode())
    h.update(_kernel_sources_digest())
    seen: set = set()
    for mod in model.modules():
        for cls in type(mod).__mro__:
            if cls in seen or cls.__module__.split(".")[0] in ("torch", "builtins", "abc"):
                continue
            seen.add(cls)
            try:
                text = Path(inspect.getsourcefile(cls)).read_bytes()
            except (TypeError, OSError):
                return None
            h.update(f"{cls.__module__}.{cls.__qualname__}".encode())
            h.update(hashlib.sha256(text).digest())
    return h.hexdigest()[:24]


def _from_source_index(model: nn.Module, skey: str | None, n: int, m: int, named):
    """The hooks of the module recorded for ``skey`` when it was generated and checked,
    and its step still equals the model's ``forward`` at a few random points; else None
    (the caller traces)."""
    if skey is None:
        return None
    index = _cache_dir() / f"s_{skey}.txt"
    try:
        digest = index.read_text().strip()
        path = _cache_dir() / f"m_{digest}.py"
        if not path.with_suffix(".checked").exists():
            return None
        module = _import(path, digest)
    except Exception:  # no index, or a damaged file: trace
        return None
    hooks = _hooks_of(module, named)
    if not _same_step(model, hooks, n, m):
        return None
    return hooks


def _same_step(model: nn.Module, hooks: GeneratedHooks, n: int, m: int) -> bool:
    """Whether ``hooks.rhs`` equals the model's ``forward`` (float64) at 3 random points
    (to 1e-12 relative; NaN where the forward is NaN)."""
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(3, n, generator=gen, dtype=torch.float64)
    u = torch.randn(3, m, generator=gen, dtype=torch.float64)
    state = {k: t.detach().to("cpu", torch.float64) for k, t in _named_tensors(model)}
    p = hooks.params(model)
    with torch.no_grad():
        ref = torch.func.functional_call(model, state, (x, u)).numpy()
    out = np.zeros(n)
    for r in range(3):
        hooks.rhs(x[r].numpy(), u[r].numpy(), p, out)
        scale = 1.0 + np.abs(np.nan_to_num(ref[r])).max()
        if not np.allclose(out, ref[r], rtol=1e-12, atol=1e-12 * scale, equal_nan=True):
            return False
    return True


def _trace(model: nn.Module, n: int, m: int, named: list[tuple[str, Tensor]]):
    """The aten graph (a ``torch.fx.GraphModule``) of ``model``'s ``forward`` on two
    rows: placeholders ``x`` ``(2, n)``, ``u`` ``(2, m)`` and one per ``named`` tensor
    (its shape; a float attribute's, named ``@path.attr``, is 0-d and set on the module
    for the trace), constants as ``get_attr`` nodes. Raises :class:`_Unsupported`
    where the forward cannot be traced (:func:`_make_graph`)."""
    from torch.func import functional_call

    names = [k for k, _ in named]

    def fn(x, u, *ps):
        tensors = {}
        for k, p in zip(names, ps, strict=True):
            if k.startswith("@"):  # a float attribute, traced as an input
                mod, _, attr = k[1:].rpartition(".")
                vars(model.get_submodule(mod) if mod else model)[attr] = p
            else:
                tensors[k] = p
        return functional_call(model, tensors, (x, u))

    # real tensors: the trace runs the forward once on them (two rows of zeros, copies
    # of the parameters, so nothing the forward does reaches the model's own tensors)
    x = torch.zeros(2, n, dtype=torch.float64)
    u = torch.zeros(2, m, dtype=torch.float64)
    ps = [t.detach().to("cpu", torch.float64, copy=True) for _, t in named]
    with _state_restored(model):  # a forward that caches tensors must not keep traced ones
        return _make_graph(fn, x, u, ps)


@contextlib.contextmanager
def _state_restored(model: nn.Module):
    """Every module's attributes (and the contents of dict / list attributes, e.g. a
    cache of constant matrices a ``forward`` fills on first use) as they were before."""
    saved = []
    for mod in model.modules():
        attrs = dict(vars(mod))
        inner = {k: (dict(v) if isinstance(v, dict) else list(v)) for k, v in attrs.items()
                 if isinstance(v, (dict, list)) and not k.startswith("_modules")}  # fmt: skip
        saved.append((mod, attrs, inner))
    try:
        yield
    finally:
        for mod, attrs, inner in saved:
            d = vars(mod)
            for k in [k for k in d if k not in attrs]:
                del d[k]
            d.update(attrs)
            for k, v in inner.items():
                d[k].clear()
                if isinstance(v, dict):
                    d[k].update(v)
                else:
                    d[k].extend(v)


def _make_graph(fn, x, u, ps):
    """:func:`torchslq.dynamics._trace.trace` of ``fn(x, u, *ps)``; any error it raises
    (an op on tensors of mismatched shapes, a value read back into Python) and a graph
    of more than ``MAX_GRAPH_NODES`` ops as :class:`_Unsupported`."""
    from ._trace import trace

    try:
        gm = trace(fn, x, u, *ps)
    except Exception as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise _Unsupported(f"forward could not be traced ({type(e).__name__}: {first})") from e
    calls = sum(1 for node in gm.graph.nodes if node.op == "call_function")
    if calls > MAX_GRAPH_NODES:
        raise _Unsupported(f"forward is {calls} ops (more than {MAX_GRAPH_NODES})")
    return gm


def _cache_dir() -> Path | None:
    d = cache_root() / f"generated_v{CODEGEN_VERSION}"
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    return d if os.access(d, os.W_OK) else None


def _import(path: Path, digest: str):
    def check(module) -> None:
        missing = [k for k in _MODULE_NAMES if not hasattr(module, k)]
        if missing:
            raise ImportError(f"{path} defines no {', '.join(missing)}")

    return import_source(path, f"torchslq_generated_{digest}", check)


def _write_and_import(path: Path | None, digest: str, source: str):
    if path is not None:
        try:
            write_atomic(path, source)
            return _import(path, digest)
        except OSError:
            pass
    # no writable cache: compile in memory (numba then compiles in every process)
    scope: dict = {"__name__": f"torchslq_generated_{digest}"}
    exec(
        compile(source.replace("cache=True", "cache=False"), f"<generated {digest}>", "exec"), scope
    )

    class _Module:
        pass

    module = _Module()
    module.__dict__.update(scope)
    module.__file__ = None
    return module


# ------------------------------------------------------------------------- generate
def _row_expressions(gm, n: int, m: int, named) -> tuple[list, list, list, list]:
    """``(f, xs, us, ps)``: the output expressions of row 0 and the symbols."""
    import sympy

    x = symbols("x", (2, n))
    u = symbols("u", (2, m))
    ps, flat = [], []
    k = 0
    for _, t in named:
        arr = np.empty(tuple(t.shape), dtype=object)
        for idx in np.ndindex(*t.shape):
            arr[idx] = sympy.Symbol(f"p{k}", real=True)
            flat.append(arr[idx])
            k += 1
        ps.append(arr)
    out = evaluate(gm, [x, u, *ps])
    out = as_array(out) if not isinstance(out, (list, tuple)) else None
    if out is None or out.shape != (2, n):
        raise _Unsupported(
            f"forward returned shape {None if out is None else out.shape} for 2 rows of "
            f"states (expected (2, {n}))"
        )
    rows = [[sympy.sympify(e) for e in out[r]] for r in range(2)]
    own = [set(x[0]) | set(u[0]), set(x[1]) | set(u[1])]
    swap = {**dict(zip(x[1], x[0], strict=True)), **dict(zip(u[1], u[0], strict=True))}
    for i in range(n):
        f0, f1 = rows[0][i], rows[1][i]
        free0 = f0.free_symbols - set(flat)
        if not free0 <= own[0] or f1.xreplace(swap) != f0:
            raise _Unsupported(
                "output rows are not independent and alike (a model mixing rows, or a "
                "parameter with a batch dim)"
            )
    ops = sum(sympy.count_ops(e) for e in rows[0])
    if ops > MAX_EXPRESSION_OPS:
        raise _Unsupported(f"forward is {ops} scalar ops per row (more than {MAX_EXPRESSION_OPS})")
    return rows[0], list(x[0]), list(u[0]), flat


def _printer():
    import sympy
    from sympy.printing.pycode import PythonCodePrinter

    class Printer(PythonCodePrinter):
        def _print_Float(self, expr):
            return repr(float(expr))

        def _print_Rational(self, expr):
            return repr(float(expr))

        def _print_Integer(self, expr):
            return repr(float(expr))

        def _print_DiracDelta(self, expr):
            # d sign / dx: zero away from 0, and what torch's autograd gives at 0 too
            return "0.0"

        def _print_Pow(self, expr, rational=False):
            base, e = expr.args
            if e.is_Float and float(2 * e).is_integer():  # torch's x ** 1.5
                e = sympy.Rational(int(2 * e), 2)
            if e.is_Integer and 1 < int(e) <= 4:  # x*x...: what the forward computed
                b = self.parenthesize(base, 100)
                return "(" + "*".join([b] * int(e)) + ")"
            if e.is_Integer and -4 <= int(e) <= -1:
                # products, not a call of pow (10x slower in numba); a reciprocal the
                # function already holds is reused (a division is the slow operation)
                inv = self.reciprocals.get(base)
                if inv is not None:
                    return inv if int(e) == -1 else "(" + "*".join([inv] * -int(e)) + ")"
                b = self.parenthesize(base, 100)
                return "(1.0/" + ("(" + "*".join([b] * -int(e)) + ")" if int(e) < -1 else b) + ")"
            if e.is_Rational and e.q == 2 and abs(e.p) <= 9:  # b^(k/2): sqrt and products
                b = self.parenthesize(base, 100)
                root = "*".join([f"math.sqrt({self._print(base)})"] + [b] * ((abs(e.p) - 1) // 2))
                return f"({root})" if e.p > 0 else f"(1.0/({root}))"
            return super()._print_Pow(expr, rational=rational)

        def assignment(self, symbol, expr) -> str:
            """``symbol = expr`` as a line of the function, and ``symbol`` noted as the
            reciprocal of ``b`` when ``expr`` is ``1/b`` (printed before its uses:
            the common subexpressions are in dependency order)."""
            line = f"    {symbol.name} = {self.doprint(expr)}"
            if expr.is_Pow and expr.args[1] == -1:
                self.reciprocals[expr.args[0]] = symbol.name
            return line

    printer = Printer({"fully_qualified_modules": True, "standard": "python3"})
    printer.reciprocals = {}
    return printer


_BUDGET_REASON = "its symbolic second derivatives took over {:g} s (TORCHSLQ_CODEGEN_BUDGET)"


def _budget() -> float:
    """Seconds of symbolic differentiation allowed (``TORCHSLQ_CODEGEN_BUDGET``)."""
    return float(os.environ.get("TORCHSLQ_CODEGEN_BUDGET", DEFAULT_BUDGET_S))


def _budget_of(reason: str) -> float | None:
    """The budget a kept verdict ran out of, or None where it is another reason."""
    head, _, tail = _BUDGET_REASON.partition("{:g}")
    if reason.startswith(head) and reason.endswith(tail):
        with contextlib.suppress(ValueError):
            return float(reason[len(head) : len(reason) - len(tail)])
    return None


def _generate(gm, n: int, m: int, named, model_name: str, kind: str) -> str:
    import sympy

    f, xs, us, ps = _row_expressions(gm, n, m, named)
    z = xs + us
    nz = n + m
    J = [[sympy.diff(fi, zc) for zc in z] for fi in f]
    H = {}
    budget = _budget()
    start = time.perf_counter()
    for i in range(n):
        if time.perf_counter() - start > budget:
            raise _Unsupported(_BUDGET_REASON.format(budget))
        for a in range(nz):
            for b in range(a, nz):
                h = sympy.diff(J[i][a], z[b])
                if h != 0:
                    H[(i, a, b)] = h
    outs = tuple(sorted({i for i, _, _ in H}))
    ents = tuple(sorted({a for _, a, _ in H} | {b for _, _, b in H}))

    def reads(exprs) -> list[str]:
        used = set().union(*(sympy.sympify(e).free_symbols for e in exprs)) if exprs else set()
        lines = []
        for name, syms in (("x", xs), ("u", us), ("p", ps)):
            for i, s in enumerate(syms):
                if s in used:
                    lines.append(f"    {s.name} = {name}[{i}]")
        return lines

    rhs_printer = _printer()  # one per function: its reciprocals
    subs, reduced = sympy.cse(f, symbols=sympy.numbered_symbols("r"), order="none")
    rhs_assign = [rhs_printer.assignment(s, e) for s, e in subs]
    rhs_vals = [rhs_printer.doprint(v) for v in reduced]
    rhs_body = rhs_assign + [f"    out[{i}] = {v}" for i, v in enumerate(rhs_vals)]
    jac = [J[i][c] for i in range(n) for c in range(nz)]
    hes = list(H.values())
    # one elimination over the Jacobian and the Hessians (they share most terms): the
    # subexpressions the Jacobian reads before the return of a Jacobian-only call (an
    # empty H), the rest after it; fewer ops compile faster (numba's typing and lowering
    # take about a millisecond per op) and the Hessian pass reuses the Jacobian's terms
    printer = _printer()
    subs, reduced = sympy.cse(jac + hes, symbols=sympy.numbered_symbols("j"), order="none")
    need = set().union(*(e.free_symbols for e in reduced[: len(jac)]))
    for sym, e in reversed(subs):  # subs are in dependency order
        if sym in need:
            need |= e.free_symbols
    jac_assign = [printer.assignment(sym, e) for sym, e in subs if sym in need]
    vals = [printer.doprint(e) for e in reduced[: len(jac)]]
    # the Jacobian's entries that are numbers (constant zeros and ones of the model)
    jac_numbers = [e.is_Number for e in reduced[: len(jac)]]
    deriv_body = jac_assign + [
        f"    fz[{i}, {c}] = {vals[i * nz + c]}" for i in range(n) for c in range(nz)
    ]
    deriv_body += ["    if H.shape[0] == 0:", "        return"]
    if hes:
        deriv_body += [printer.assignment(sym, e) for sym, e in subs if sym not in need]
        val = {}
        for k, (key, e) in enumerate(zip(H, reduced[len(jac) :], strict=True)):
            val[key] = printer.doprint(e)
            if key[1] != key[2] and not (e.is_Symbol or e.is_Number):
                deriv_body.append(f"    h{k} = {val[key]}")  # written to H[j, a, b] and H[j, b, a]
                val[key] = f"h{k}"
        for j in outs:
            for a in ents:
                for b in ents:
                    key = (j, min(a, b), max(a, b))
                    deriv_body.append(f"    H[{j}, {a}, {b}] = {val.get(key, '0.0')}")
    else:  # no curvature: the whole H is zero
        deriv_body += [
            f"    for j in range({n}):",
            f"        for a in range({nz}):",
            f"            for b in range({nz}):",
            "                H[j, a, b] = 0.0",
        ]
    src = [
        f"# generated by torchslq.dynamics.codegen (version {CODEGEN_VERSION}) from {model_name}.forward",
        f"# state dim {n}, control dim {m}, parameters {len(ps)}; do not edit",
        "import math",
        "import numba",
        "",
        f"CURVED_OUTPUTS = {outs!r}",
        f"CURVED_ENTRIES = {ents!r}",
        "",
        "",
        "@numba.njit(nogil=True, cache=True)",
        "def rhs(x, u, p, out):",
        *reads(f),
        *rhs_body,
        "",
        "",
        "@numba.njit(nogil=True, cache=True)",
        "def derivatives(x, u, p, fz, H):",
        *reads(jac + hes),
        *deriv_body,
    ]
    if len(src) > MAX_GENERATED_LINES:  # (what a first solve compiles: rhs, derivatives)
        raise _Unsupported(
            f"{len(src)} lines of generated code (more than {MAX_GENERATED_LINES}): too "
            "long to compile quickly"
        )
    if kind == "continuous":
        # both bodies in one function (the RK4 stages need both at each point): the
        # same statements, so the same bits, with the terms they share (its sines,
        # denominators) computed once by LLVM; the names do not clash (r*, j*, h*)
        src += [
            "",
            "",
            "@numba.njit(nogil=True, cache=True)",
            "def rhs_derivatives(x, u, p, out, fz, H):",
            *reads(f + jac + hes),
            *rhs_body,
            *deriv_body,
        ]
    src += _kernel_source(kind)
    if kind == "continuous":
        rhs_parts = (rhs_assign, rhs_vals)
        jac_parts = (jac_assign, vals, jac_numbers)
        src += _jacobian_rows_source(xs, us, reads(f + jac), rhs_parts, jac_parts, n, m)
        src += _rk4_step_source(xs, us, reads(f), rhs_parts, n)
    refused = rhs_printer._not_supported | printer._not_supported
    if refused:
        raise _Unsupported(f"cannot print {sorted(map(str, refused))[:3]}")
    return "\n".join(src) + "\n"


_KERNELS: dict[str, list[str]] = {}


def _kernel_source(kind: str) -> list[str]:
    """The library's kernels that take a model's functions as arguments, rewritten to
    call this module's ``rhs`` / ``derivatives`` / ``step`` directly
    (:mod:`torchslq.dynamics._specialize`), plus the names :mod:`torchslq._backend.bound`
    reads. numba compiles each on its first call (a large pass) and caches it with the
    module."""
    if kind not in _KERNELS:
        from .._backend import _numba_kernels, _numba_search
        from . import _numba_rk4, _numba_step
        from ._specialize import specialised_source

        if kind == "continuous":  # the RK4 step of rhs and its derivatives
            derivs, helpers = specialised_source(
                _numba_rk4, {"rhs", "derivs"}, ["rk4_lanes_kernel", "rk4_second_derivatives_kernel"]
            )
            source = "torchslq.dynamics._numba_rk4"
            names = ["jacobians_kernel = rk4_lanes_kernel"]
            names += ["hessians_kernel = rk4_second_derivatives_kernel"]
            # (step: the module's rk4_step_locals, written after these kernels)
            names += ["ROLLOUT_MODE = STEP_RK4"]
        else:  # rhs is the step
            derivs, helpers = specialised_source(
                _numba_step, {"rhs", "derivs"}, ["step_derivatives_kernel"]
            )
            source = "torchslq.dynamics._numba_step"
            names = ["jacobians_kernel = step_derivatives_kernel"]
            names += ["hessians_kernel = step_derivatives_kernel", "ROLLOUT_MODE = STEP_DISCRETE"]
            names += [
                "",
                "",
                "@numba.njit(nogil=True, cache=True)",
                "def step(x, u, p, out, work):",
            ]
            names += ["    rhs(x, u, p, out)"]
        roll, roll_helpers = specialised_source(
            _numba_kernels, {"step", "rhs"}, ["closed_loop_rollout_kernel", "step_rows_kernel"]
        )
        # this module's step is known: the bound rollouts call it without the mode test
        # (with the three branches inlined, numba's rollout ran ~25% slower)
        # (and the library's RK4 step, which only _model_step called)
        roll = _without_function(_without_function(roll, "_model_step"), "rk4_step_with")
        roll += (
            "\n\n\n@numba.njit(nogil=True, inline='always')\n"
            "def _model_step(mode, x, u, p, out, work):\n"
            "    step(x, u, p, out, work)\n"
        )
        roll_helpers = sorted(set(roll_helpers) | {"STEP_RK4", "STEP_DISCRETE"})
        # the fused line search's trials run the rollout's row loop rewritten above
        search, search_helpers = specialised_source(
            _numba_search,
            {"step", "rhs"},
            ["armijo_rollout_kernel"],
            frozenset({"_closed_loop_rows"}),
        )
        roll += "\n\n\n" + search
        lines = ["", "", "# the library's kernels with this module's functions bound in", ""]
        lines += ["import numpy as np", ""]
        for mod, used in (
            (source, helpers),
            ("torchslq._backend._numba_kernels", roll_helpers),
            ("torchslq._backend._numba_search", search_helpers),
        ):
            lines += [f"from {mod} import {name}" for name in used]
        lines += ["", "derivs = derivatives"]
        if kind == "continuous":  # the stages call one function for both (same bits)
            derivs = _without_function(derivs, "_rhs_and_derivs")
            lines += ["_rhs_and_derivs = rhs_derivatives"]
        lines += ["", "", derivs, "", "", roll, "", "", *names]
        _KERNELS[kind] = lines
    return _KERNELS[kind]


def _jacobian_rows_source(xs, us, reads, rhs_parts, jac_parts, n, m) -> list[str]:
    """``jacobians_only_kernel``: the RK4 step's Jacobians ``A``, ``B`` (what
    :func:`torchslq.dynamics._numba_rk4.rk4_lanes_kernel` computes without weights) as
    straight-line code per row: every stage's ``f``, ``f_z`` and ``dk_i/dz`` in local
    variables instead of lane arrays, the model's entries that are the constant 0 left
    out of the chain rule (with those of ``dk_i/dz`` they make zero) and those that are
    1 not multiplied. The same operations in the same order otherwise (no FMA
    contraction here or there), so for finite inputs the same bits (a dropped product
    ``0 * v`` only matters where ``v`` is not finite, and such a row has non-finite
    entries either way); the argument list is ``rk4_lanes_kernel``'s less ``rhs``,
    ``derivs``, its weights and Hessians unread. ``rhs_parts``: the right-hand side's
    assignment lines and printed outputs; ``jac_parts``: the Jacobian's assignment
    lines, its printed entries (row-major ``(n, n + m)``) and which are numbers."""
    nz = n + m
    rhs_assign, rhs_vals = rhs_parts
    jac_assign, jac_vals, jac_numbers = jac_parts
    F = {(j, c): jac_vals[j * nz + c] for j in range(n) for c in range(nz)}
    const = {(j, c): F[j, c] for j in range(n) for c in range(nz) if jac_numbers[j * nz + c]}

    def fval(j, c):
        return const.get((j, c), f"F{j}_{c}")

    ind = " " * 8
    lines = [
        "",
        "",
        "@numba.njit(nogil=True, cache=True, _nrt=False)",
        "def jacobians_only_kernel(r0, r1, p, dt, curved_outputs, curved_entries, x, u, S, Hz, A, B):",
        *[ln for ln in reads if "= p[" in ln],
        "    c6 = dt / 6.0",
        "    for row in range(r0, r1):",
        f"{ind}xr = x[row]",
        f"{ind}ur = u[row]",
        *[f"{ind}{s.name} = ur[{i}]" for i, s in enumerate(us)],
    ]
    zeros: list[dict] = []  # per stage: the entries of dk_i/dz that are exactly zero
    for i in range(4):
        if i == 0:
            lines += [f"{ind}{s.name} = xr[{k}]" for k, s in enumerate(xs)]
        else:
            lines.append(f"{ind}a_dt = {0.5 if i < 3 else 1.0!r} * dt")
            lines += [f"{ind}{s.name} = xr[{k}] + a_dt * k{i - 1}_{k}" for k, s in enumerate(xs)]
        if i < 3:  # the stage's f (the last stage's is not needed)
            lines += [ind + ln.strip() for ln in rhs_assign]
            lines += [f"{ind}k{i}_{j} = {rhs_vals[j]}" for j in range(n)]
        lines += [ind + ln.strip() for ln in jac_assign]
        lines += [f"{ind}F{j}_{c} = {v}" for (j, c), v in F.items() if (j, c) not in const]
        zero = {}
        for j in range(n):
            for c in range(nz):
                if i == 0:
                    zero[j, c] = fval(j, c) == "0.0"
                    if not zero[j, c]:
                        lines.append(f"{ind}d0_{j}_{c} = {fval(j, c)}")
                    continue
                terms = []
                for q in range(n):
                    fq = fval(j, q)
                    if fq == "0.0" or zeros[i - 1][q, c]:
                        continue
                    terms.append(f"d{i - 1}_{q}_{c}" if fq == "1.0" else f"{fq} * d{i - 1}_{q}_{c}")
                zero[j, c] = fval(j, c) == "0.0" and not terms
                if zero[j, c]:
                    continue
                lines.append(f"{ind}s = 0.0")
                lines += [f"{ind}s = s + {t}" for t in terms]
                lines.append(f"{ind}d{i}_{j}_{c} = {fval(j, c)} + a_dt * s")
        zeros.append(zero)
    for j in range(n):
        for c in range(nz):
            d = ["0.0" if zeros[i][j, c] else f"d{i}_{j}_{c}" for i in range(4)]
            if c < n:  # A = I + c6 sk, B = c6 sk
                target, eye = f"A[row, {j}, {c}]", ("1.0" if c == j else "0.0") + " + "
            else:
                target, eye = f"B[row, {j}, {c - n}]", ""
            if all(zeros[i][j, c] for i in range(4)):
                lines.append(f"{ind}{target} = {(eye[:3] if eye else '0.0')}")
                continue
            lines.append(f"{ind}sk = {d[0]} + 2.0 * {d[1]}")
            lines.append(f"{ind}sk = sk + 2.0 * {d[2]} + {d[3]}")
            lines.append(f"{ind}{target} = {eye}c6 * sk")
    return lines


def _rk4_step_source(xs, us, reads, rhs_parts, n) -> list[str]:
    """``rk4_step_locals(x, u, p, out, work)``, the module's ``step`` (``p[0] = dt``, the
    model's parameters after it): :func:`torchslq._backend._numba_kernels.rk4_step_with`
    as straight-line code, the stages' arguments and ``k_i`` in local variables instead
    of ``work``'s rows; the same operations in the same order, so the same bits.
    ``rhs_parts``: as for :func:`_jacobian_rows_source`."""
    import re

    assign, vals = rhs_parts
    params = []
    for ln in reads:
        mt = re.match(r"^    (\w+) = p\[(\d+)\]$", ln)
        if mt:  # the model's parameters follow dt
            params.append(f"    {mt.group(1)} = p[{int(mt.group(2)) + 1}]")
    lines = [
        "",
        "",
        "@numba.njit(nogil=True, _nrt=False, cache=True)",
        "def rk4_step_locals(x, u, p, out, work):",
        "    dt = p[0]",
        *params,
        *[f"    {s.name} = u[{i}]" for i, s in enumerate(us)],
        *[f"    xo{i} = x[{i}]" for i in range(n)],
        *[f"    {s.name} = xo{i}" for i, s in enumerate(xs)],
    ]
    for stage, k in enumerate(("ka", "kb", "kc", "kd")):
        lines += assign
        lines += [f"    {k}{j} = {vals[j]}" for j in range(n)]
        for i, sym in enumerate(xs):
            if stage == 0:
                lines.append(f"    a{i} = ka{i}")
                lines.append(f"    {sym.name} = xo{i} + (0.5 * dt) * ka{i}")
            elif stage == 1:
                lines.append(f"    a{i} = a{i} + 2.0 * kb{i}")
                lines.append(f"    {sym.name} = xo{i} + (0.5 * dt) * kb{i}")
            elif stage == 2:
                lines.append(f"    {sym.name} = xo{i} + dt * kc{i}")
            else:
                lines.append(f"    out[{i}] = xo{i} + (dt / 6.0) * (a{i} + (kd{i} + 2.0 * kc{i}))")
    return [*lines, "", "", "step = rk4_step_locals"]


def _without_function(source: str, name: str) -> str:
    """``source`` without the top-level function ``name``."""
    import ast

    tree = ast.parse(source)
    tree.body = [n for n in tree.body if not (isinstance(n, ast.FunctionDef) and n.name == name)]
    return ast.unparse(tree)


_SOURCES_DIGEST: list[bytes] = []


def _kernel_sources_digest() -> bytes:
    """A hash of every source the generated module depends on: the kernels written into
    it and the generator itself (this module, the interpreter, the rewrite), plus the
    versions of sympy and numba. A cache directory shared by several versions of the
    library (a CI machine, a user's environments) then never serves one version's
    module to another (a module without a kernel the other's launchers call)."""
    if not _SOURCES_DIGEST:
        from importlib.metadata import version

        # versions and files, not imports: sympy alone takes a third of a second to import
        h = hashlib.sha256(f"sympy {version('sympy')}; numba {version('numba')}".encode())
        here = Path(__file__).resolve().parent
        files = (
            here.parent / "_backend" / "_numba_kernels.py",
            here.parent / "_backend" / "_numba_search.py",
            here.parent / "_backend" / "_numba_cost.py",
            *(here / f"{name}.py" for name in ("_numba_rk4", "_numba_step", "_specialize")),
            here / "_symbolic.py",
            Path(__file__),
        )
        for path in files:
            h.update(path.read_bytes())
        _SOURCES_DIGEST.append(h.digest())
    return _SOURCES_DIGEST[0]


#: what the launchers read from a generated module (a file without one is regenerated)
_MODULE_NAMES = (
    "CURVED_OUTPUTS",
    "CURVED_ENTRIES",
    "rhs",
    "derivatives",
    "step",
    "closed_loop_rollout_kernel",
    "step_rows_kernel",
    "jacobians_kernel",
    "hessians_kernel",
    "ROLLOUT_MODE",
)


# ------------------------------------------------------------------------- check
def _reference_derivatives(model: nn.Module, state: dict, x: Tensor, u: Tensor):
    """``(J, H)``: the Jacobian ``[f_x | f_u]`` ``(n, n + m)`` and the per-output
    Hessians ``(n, n + m, n + m)`` in ``z = (x, u)`` of the model's ``forward`` at one
    row ``x`` ``(n,)``, ``u`` ``(m,)`` (float64), by ``torch.autograd.grad``.

    The forward runs on ``n`` copies of the row and output ``i`` is read from copy
    ``i`` (rows are independent: the generated code is per row), so the Jacobian is one
    reverse pass and the Hessians ``n + m`` more. ``torch.func.jacrev`` would give the
    same numbers but imports ``torch._dynamo`` (over a second in a fresh process)."""
    n, m = x.shape[-1], u.shape[-1]
    # autograd records nothing in inference mode, and its tensors cannot be saved for
    # backward: clones made outside it
    with torch.inference_mode(False), torch.enable_grad():
        z = torch.cat([x, u]).expand(n, n + m).clone().requires_grad_(True)
        state = {k: t.clone() for k, t in state.items()}
        y = torch.func.functional_call(model, state, (z[:, :n], z[:, n:]))
        if not y.requires_grad:  # an output of constants
            return torch.zeros(n, n + m, dtype=z.dtype), torch.zeros(n, n + m, n + m, dtype=z.dtype)
        (J,) = torch.autograd.grad(
            y.diagonal().sum(), z, create_graph=True, allow_unused=True, materialize_grads=True
        )
        H = torch.zeros(n, n + m, n + m, dtype=z.dtype)
        if J.requires_grad:  # else the forward is linear in z
            for a in range(n + m):
                (H[:, a],) = torch.autograd.grad(
                    J[:, a].sum(), z, retain_graph=True, allow_unused=True, materialize_grads=True
                )
    return J.detach(), H


def _check(model: nn.Module, hooks: GeneratedHooks, n: int, m: int) -> None:
    """The compiled functions against the model's ``forward`` and its autograd
    derivatives (:func:`_reference_derivatives`) at a few random points (float64);
    raises :class:`_Unsupported` on a mismatch (which a tracing error would give) with a
    warning."""
    from .base import CompiledDerivatives

    gen = torch.Generator().manual_seed(0)
    rows = 4
    x = torch.randn(rows, n, generator=gen, dtype=torch.float64)
    u = torch.randn(rows, m, generator=gen, dtype=torch.float64)
    p = hooks.params(model)
    state = {k: t.detach().to("cpu", torch.float64) for k, t in _named_tensors(model)}

    def f(xr, ur):
        return torch.func.functional_call(model, state, (xr[None], ur[None]))[0]

    derivs = hooks.derivatives
    if isinstance(derivs, CompiledDerivatives):
        fn, outs, ents = derivs
    else:
        fn, outs, ents = derivs, range(n), range(n + m)
    checked = 0
    for r in range(rows):
        with torch.no_grad():
            ref = f(x[r], u[r])
        if not bool(torch.isfinite(ref).all()):
            continue
        Jref, Href = _reference_derivatives(model, state, x[r], u[r])
        out = np.zeros(n)
        fz = np.zeros((n, n + m))
        Hc = np.zeros((n, n + m, n + m))
        hooks.rhs(x[r].numpy(), u[r].numpy(), p, out)
        fn(x[r].numpy(), u[r].numpy(), p, fz, Hc)
        Hmask = np.zeros_like(Hc, dtype=bool)
        Hmask[np.ix_(list(outs), list(ents), list(ents))] = True
        Hc = np.where(Hmask, Hc, 0.0)
        for what, got, want in (
            ("forward", out, ref.numpy()),
            ("Jacobian", fz, Jref.detach().numpy()),
            ("Hessians", Hc, Href.detach().numpy()),
        ):
            scale = 1.0 + np.abs(want).max()
            if not np.allclose(got, want, rtol=1e-9, atol=1e-9 * scale):
                msg = (
                    f"torchslq: the compiled code generated for {type(model).__name__} "
                    f"differs from its forward ({what}, max error "
                    f"{np.abs(got - want).max():.2e}); it keeps the torch path"
                )
                warnings.warn(msg, RuntimeWarning, stacklevel=4)
                raise _Unsupported(msg)
        checked += 1
    if checked == 0:
        raise _Unsupported("forward is not finite at the check points")
