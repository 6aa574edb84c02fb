"""Reproductions of the papers torchslq implements (tables, figures, report writers).

Not part of the installed package: run from a checkout of the repository (the
``torchslq reproduce`` command, ``examples/`` and ``tests/`` import it from here).
"""

from .sideris import (
    PAPER_HOPPER,
    PAPER_TABLE1,
    PAPER_TABLE1_NEWTON,
    drag_vehicle_problem,
    format_table,
    hopper_problem,
    plot_drag_solution,
    plot_hopper,
    plot_relative_cost,
    relative_cost_histories,
    reproduce_hopper,
    reproduce_table1,
    solve_drag_vehicle,
    solve_hopper,
)

__all__ = [
    "PAPER_HOPPER",
    "PAPER_TABLE1",
    "PAPER_TABLE1_NEWTON",
    "drag_vehicle_problem",
    "format_table",
    "hopper_problem",
    "plot_drag_solution",
    "plot_hopper",
    "plot_relative_cost",
    "relative_cost_histories",
    "reproduce_hopper",
    "reproduce_table1",
    "solve_drag_vehicle",
    "solve_hopper",
]
