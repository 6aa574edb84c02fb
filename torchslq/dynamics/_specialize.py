"""The library's generic numba kernels rewritten for one model: the source of the
kernels that take a model's functions as arguments (``rhs``, ``derivs``, ``step``),
with those arguments removed so the functions are read as module globals instead.

numba cannot cache a function that passes a compiled function as an argument (the
callee's address is a dynamic global), so the generic kernels are compiled in every
process for every model (seconds each). Written into a model's generated module
(:mod:`torchslq.dynamics.codegen`), where ``rhs`` and ``derivatives`` are defined, the
rewritten kernels are plain functions of that module and are cached on disk with it.
The rewrite is mechanical (the same statements, fewer parameters), so the kernels keep
one source: the generic modules.
"""

from __future__ import annotations

import ast
from pathlib import Path
from types import ModuleType

__all__ = ["specialised_source"]


def _jitted(f: ast.FunctionDef) -> bool:
    return any(
        isinstance(d, ast.Call) and isinstance(d.func, ast.Attribute) and d.func.attr == "njit"
        for d in f.decorator_list
    )


def _calls(f: ast.FunctionDef) -> set[str]:
    return {
        n.func.id for n in ast.walk(f) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
    }


def specialised_source(
    module: ModuleType,
    function_args: set[str],
    roots: list[str],
    rewritten_elsewhere: frozenset[str] = frozenset(),
) -> tuple[str, list[str]]:
    """The rewritten source of ``roots`` in ``module`` and of the jitted functions they
    call that take one of ``function_args``, and the names of the module's other
    functions, constants and imports they use (to import from it).

    Each rewritten function loses the parameters named in ``function_args`` (calls
    between rewritten functions lose those arguments, and so do calls of the functions
    in ``rewritten_elsewhere``: imported from another module whose rewrite is written
    beside this one), its docstring, and is decorated as before plus ``cache=True``."""
    tree = ast.parse(Path(module.__file__).read_text())
    funcs = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef)}
    takes = {
        name
        for name, f in funcs.items()
        if _jitted(f) and any(a.arg in function_args for a in f.args.args)
    }
    rewrite: list[str] = []
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name in rewrite:
            continue
        if name not in takes:
            raise ValueError(f"{module.__name__}.{name} takes none of {sorted(function_args)}")
        rewrite.append(name)
        todo += [c for c in _calls(funcs[name]) if c in takes]
    top = set(funcs)
    for n in tree.body:  # module-level constants the kernels read (e.g. a block size)
        if isinstance(n, (ast.Assign, ast.AnnAssign)):
            targets = n.targets if isinstance(n, ast.Assign) else [n.target]
            top |= {t.id for t in targets if isinstance(t, ast.Name)}
        elif isinstance(n, ast.ImportFrom):  # helpers from the library's other kernels
            top |= {a.asname or a.name for a in n.names}
    top -= rewritten_elsewhere
    helpers: set[str] = set()
    out = []
    for name in sorted(rewrite, key=lambda k: funcs[k].lineno):
        f = funcs[name]
        f.args.args = [a for a in f.args.args if a.arg not in function_args]
        body = f.body
        if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
            f.body = body[1:] or [ast.Pass()]
        for node in ast.walk(f):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
                if node.func.id in rewrite or node.func.id in rewritten_elsewhere:
                    node.args = [
                        a
                        for a in node.args
                        if not (isinstance(a, ast.Name) and a.id in function_args)
                    ]

        for node in ast.walk(f):
            if isinstance(node, ast.Name) and node.id in top and node.id not in rewrite:
                helpers.add(node.id)
        for d in f.decorator_list:
            if isinstance(d, ast.Call) and not any(k.arg == "cache" for k in d.keywords):
                d.keywords.append(ast.keyword(arg="cache", value=ast.Constant(True)))
        out.append(ast.unparse(ast.fix_missing_locations(f)))
    return "\n\n\n".join(out), sorted(helpers)
