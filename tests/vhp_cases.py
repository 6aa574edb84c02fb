"""Shared test data: broadcast layouts of ``(x, u, s)`` leading dims for the
vector-Hessian product tests (tests/test_analytic_vhp.py, tests/test_compiled_rk4.py)."""

VHP_LAYOUTS = [
    ((3, 4), (3, 4), (3, 4)),  # s per point (DDP's costate mode)
    ((3, 4), (3, 4), (5, 1, 1)),  # extra leading weight dim (all output Hessians)
    ((1, 4), (1, 4), (3, 4)),  # one trajectory, several weights per point
    ((3, 4), (3, 1), (1, 4)),  # broadcast controls and weights
]
