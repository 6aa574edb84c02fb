"""torchslq on more than one process, on ``torch.distributed``.

* Training: the :class:`torchslq.MPC` layer is an ``nn.Module`` whose gradients reach
  ordinary parameters, so ``torch.nn.parallel.DistributedDataParallel`` wraps a model
  that contains it like any other (every rank solves its shard of the batch, the
  gradients are all-reduced); ``examples/mpc_ddp_training.py`` trains one under
  ``torchrun``.
* Batch solves: :func:`solve_sharded` splits a large batch of initial states into shards
  solved by the ranks of a job and streams each shard's :class:`~torchslq.SolverResult`
  to disk (atomically; a rerun resumes), :func:`load_sharded` assembles them, and
  ``torchslq solve <system> --out-dir DIR --shard-size S --workers N`` runs it from the
  command line.
* Processes: ``torchrun`` (:func:`init_from_env`) or local workers (:func:`launch`).

Why ``torch.distributed`` and not Ray: see :mod:`torchslq.distributed.processes`.
"""

from .processes import free_port, init_from_env, launch, rank_and_world
from .sharded import (
    ShardReport,
    iter_shards,
    load_sharded,
    shard_bounds,
    shard_path,
    solve_sharded,
)

__all__ = [
    "ShardReport",
    "free_port",
    "init_from_env",
    "iter_shards",
    "launch",
    "load_sharded",
    "rank_and_world",
    "shard_bounds",
    "shard_path",
    "solve_sharded",
]
