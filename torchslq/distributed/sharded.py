"""Sharded batch solves: many initial states, several processes, results streamed to disk.

A data-generation job (optimal trajectories for policy distillation, say) splits its
initial states ``x0 (N, n)`` into shards of ``shard_size`` rows; every process of the
job (``torch.distributed`` ranks, :func:`torchslq.distributed.launch`) solves its shards
one after the other and writes each result as one file as soon as it is done.

On-disk format (``out_dir``)::

    manifest.json           what the job solves: N, shard size, shard count, state
                            dim, dtype, a SHA-256 of x0 (and of u_init), the solver
    shard_000000.pt         rows [0, shard_size) : SolverResult.save of that shard
    shard_000001.pt         rows [shard_size, 2 shard_size) ...

Each shard file is what :meth:`torchslq.SolverResult.save` writes (``torch.save`` of a
dict of tensors, loadable with ``weights_only=True``), so ``SolverResult.load(path)``
reads one shard and :func:`load_sharded` assembles all of them in row order.

Writes are atomic: a shard is written to a temporary file in ``out_dir``, flushed and
``fsync``-ed, then renamed over its final name (``os.replace``). A worker killed
mid-shard leaves at most a temporary file, never a partial shard; running the same job
again skips the shards on disk and solves only the missing ones (a rerun after a crash,
or ``torchrun --max-restarts``). With a process group, rank 0 lists the missing shards
and broadcasts the list, which is then dealt round-robin over the ranks (a resumed job is
balanced); without one, each process takes the shards ``i`` with ``i % world_size ==
rank``. A manifest that does not match the job (other ``x0``, shard size, ...) is an
error, not a silent mix of two data sets.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor

from ..solvers.result import SolverResult

__all__ = [
    "ShardReport",
    "iter_shards",
    "load_sharded",
    "shard_bounds",
    "shard_path",
    "solve_sharded",
]

FORMAT = "torchslq.sharded/1"
MANIFEST = "manifest.json"


@dataclass
class ShardReport:
    """What :func:`solve_sharded` did in this process.

    Attributes:
        out_dir: the output folder.
        num_shards: shards of the whole job.
        computed: indices of the shards this process solved and wrote in this call.
        skipped: indices of the shards already on disk when the call started.
        rank, world_size: this process's place in the job.
    """

    out_dir: Path
    num_shards: int
    computed: list[int]
    skipped: list[int]
    rank: int
    world_size: int


def shard_bounds(batch: int, shard_size: int) -> list[tuple[int, int]]:
    """Row ranges ``[(start, stop), ...]`` of the shards of a batch of ``batch`` rows; the
    last shard may be shorter. An empty batch has one empty shard ``[(0, 0)]`` (its file
    holds the empty result, so that the job can be loaded like any other)."""
    if not isinstance(shard_size, int) or isinstance(shard_size, bool) or shard_size < 1:
        raise ValueError(f"shard_size must be a positive int, got {shard_size!r}")
    if batch == 0:
        return [(0, 0)]
    return [(s, min(s + shard_size, batch)) for s in range(0, batch, shard_size)]


def shard_path(out_dir: str | Path, index: int) -> Path:
    """The file of shard ``index``."""
    return Path(out_dir) / f"shard_{index:06d}.pt"


def _digest(t: Tensor | None) -> str | None:
    if t is None:
        return None
    data = t.detach().to("cpu").contiguous()
    h = hashlib.sha256(str((tuple(data.shape), str(data.dtype))).encode())
    h.update(data.view(torch.uint8).numpy().tobytes() if data.numel() else b"")
    return h.hexdigest()


def _write_atomic(out_dir: Path, final: Path, write) -> None:
    """``write(file)`` into a temporary file of ``out_dir``, fsync, rename to ``final``."""
    fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".tmp", dir=out_dir)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, final)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _manifest(x0: Tensor, u_init: Tensor | None, shard_size: int, solver, problem) -> dict:
    return {
        "format": FORMAT,
        "batch": int(x0.shape[0]),
        "shard_size": shard_size,
        "num_shards": len(shard_bounds(int(x0.shape[0]), shard_size)),
        "state_dim": int(x0.shape[1]),
        "dtype": str(x0.dtype),
        "horizon": int(getattr(problem, "horizon", -1)),
        "x0_sha256": _digest(x0),
        "u_init_sha256": _digest(u_init),
        "solver": type(solver).__name__,
    }


def _check_or_write_manifest(out_dir: Path, want: dict) -> None:
    path = out_dir / MANIFEST
    if path.exists():
        have = json.loads(path.read_text())
        diff = sorted(k for k in want if have.get(k) != want[k])
        if diff:
            raise ValueError(
                f"out_dir {str(out_dir)!r} holds the shards of another job (manifest.json "
                f"differs in {', '.join(diff)}); use a new out_dir or delete it"
            )
        return
    text = json.dumps(want, indent=1).encode()
    _write_atomic(out_dir, path, lambda f: f.write(text))


def _missing(out_dir: Path, num_shards: int) -> list[int]:
    return [i for i in range(num_shards) if not shard_path(out_dir, i).exists()]


def _remove_stale_temporaries(out_dir: Path) -> None:
    for p in out_dir.glob(".*.tmp"):
        p.unlink(missing_ok=True)


def solve_sharded(
    solver: Any,
    problem: Any,
    x0: Tensor,
    out_dir: str | Path,
    shard_size: int = 1024,
    *,
    u_init: Tensor | None = None,
    rank: int | None = None,
    world_size: int | None = None,
) -> ShardReport:
    """Solve ``problem`` from every row of ``x0`` in shards, each shard's result written
    to ``out_dir`` as it finishes (module docstring: format, atomic writes, resuming).

    Args:
        solver: any torchslq solver (``solve(problem, x0, u_init)`` returning a
            :class:`~torchslq.SolverResult`).
        problem: a :class:`~torchslq.Problem`; per-element data (tensors leading with
            ``N``, e.g. a goal per row; :mod:`torchslq.per_element`) are cut into
            shards like ``x0``.
        x0: ``(N, n)`` initial states, the same on every process.
        out_dir: output folder (created).
        shard_size: rows per shard (the batch of one solve).
        u_init: optional ``(N, T, m)`` initial controls, sharded like ``x0``.
        rank, world_size: this process's rank and the number of processes; default: the
            default ``torch.distributed`` process group's, or ``(0, 1)`` without one.

    Returns:
        :class:`ShardReport` of this process. With a process group every rank returns
        after all ranks finished (a barrier).
    """
    if isinstance(solver, type) or not callable(getattr(solver, "solve", None)):
        raise TypeError(
            f"solver must be a solver object with solve(problem, x0, u_init) (e.g. "
            f"torchslq.ILQR()), got {solver!r}"
        )
    if not torch.is_tensor(x0) or x0.ndim != 2 or not x0.is_floating_point():
        raise ValueError(
            f"x0 must be a floating-point tensor (N, n), got {getattr(x0, 'shape', x0)}"
        )
    if u_init is not None and (not torch.is_tensor(u_init) or u_init.shape[:1] != x0.shape[:1]):
        raise ValueError(
            f"u_init must be a tensor (N, T, m) with N = {x0.shape[0]} rows like x0, "
            f"got {getattr(u_init, 'shape', u_init)}"
        )
    bounds = shard_bounds(int(x0.shape[0]), shard_size)
    N = int(x0.shape[0])
    group = dist.is_available() and dist.is_initialized()
    g_rank, g_world = (dist.get_rank(), dist.get_world_size()) if group else (0, 1)
    rank = g_rank if rank is None else rank
    world_size = g_world if world_size is None else world_size
    ints = all(isinstance(v, int) and not isinstance(v, bool) for v in (rank, world_size))
    if not (ints and world_size >= 1 and 0 <= rank < world_size):
        raise ValueError(f"need 0 <= rank < world_size, got rank={rank}, world_size={world_size}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    want = _manifest(x0, u_init, shard_size, solver, problem)
    num = len(bounds)
    if group:
        # rank 0 checks the manifest, clears a killed run's temporaries (no rank is
        # writing yet) and lists the missing shards; the list goes to every rank
        payload: list[Any] = [None]
        if rank == 0:
            try:
                _check_or_write_manifest(out, want)
                _remove_stale_temporaries(out)
                payload = [_missing(out, num)]
            except ValueError as err:
                payload = [str(err)]
        dist.broadcast_object_list(payload, src=0)
        if isinstance(payload[0], str):
            raise ValueError(payload[0])
        missing = payload[0]
        mine = missing[rank::world_size]
    else:
        _check_or_write_manifest(out, want)
        if world_size == 1:
            _remove_stale_temporaries(out)
        missing = _missing(out, num)
        mine = [i for i in missing if i % world_size == rank]
    skipped = sorted(set(range(num)) - set(missing))
    for i in mine:
        start, stop = bounds[i]
        u = None if u_init is None else u_init[start:stop]
        rows = torch.arange(start, stop, device=x0.device)
        # per-element problem data (a goal per row) are cut like x0
        shard_problem = problem.take(rows, N) if hasattr(problem, "take") else problem
        result = solver.solve(shard_problem, x0[start:stop], u)
        _write_atomic(out, shard_path(out, i), result.save)
    if group:
        dist.barrier()
    return ShardReport(out, num, list(mine), skipped, rank, world_size)


def _read_manifest(out_dir: Path) -> dict:
    path = out_dir / MANIFEST
    if not path.exists():
        raise FileNotFoundError(f"{str(out_dir)!r} has no {MANIFEST}: not a solve_sharded folder")
    meta = json.loads(path.read_text())
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path!s}: unknown format {meta.get('format')!r}")
    return meta


def iter_shards(out_dir: str | Path, map_location: str | torch.device | None = "cpu"):
    """Yield ``(start, stop, result)`` for every shard in row order (one shard in memory at
    a time: for data sets larger than memory). Raises :class:`FileNotFoundError` naming
    the missing shards before yielding anything if the job is incomplete."""
    out = Path(out_dir)
    meta = _read_manifest(out)
    missing = _missing(out, meta["num_shards"])
    if missing:
        raise FileNotFoundError(
            f"{len(missing)} of {meta['num_shards']} shards missing in {str(out)!r} "
            f"(first: {shard_path(out, missing[0]).name}); run the job again to finish them"
        )
    for i, (start, stop) in enumerate(shard_bounds(meta["batch"], meta["shard_size"])):
        result = SolverResult.load(shard_path(out, i), map_location=map_location)
        if result.x.shape[0] != stop - start:
            raise ValueError(f"shard {i} has {result.x.shape[0]} rows, expected {stop - start}")
        yield start, stop, result


def _cat(values: list, rows: list[int]) -> Any:
    """Concatenate one field of the shards' results along the batch dim (tensors with the
    shard's rows first; dicts key by key; per-iteration histories padded with NaN to the
    longest); anything else (options, shared values) is the first shard's."""
    first = values[0]
    if first is None:
        return None
    if isinstance(first, dict):
        keys = [k for k in first if all(isinstance(v, dict) and k in v for v in values)]
        out = {k: _cat([v[k] for v in values], rows) for k in keys}
        return {k: v for k, v in out.items() if v is not None}
    if torch.is_tensor(first) and all(
        torch.is_tensor(v) and v.ndim >= 1 and v.shape[0] == r
        for v, r in zip(values, rows, strict=True)
    ):
        if first.ndim >= 2 and len({v.shape[1:] for v in values}) > 1:  # histories
            width = max(v.shape[1] for v in values)
            padded = []
            for v in values:
                shape = (v.shape[0], width - v.shape[1], *v.shape[2:])
                fill = float("nan") if v.is_floating_point() else 0
                padded.append(torch.cat([v, v.new_full(shape, fill)], 1))
            values = padded
        return torch.cat(values, 0)
    if torch.is_tensor(first):
        return None  # not per-element (e.g. the history's time axis): dropped
    return first


def load_sharded(
    out_dir: str | Path, map_location: str | torch.device | None = "cpu"
) -> SolverResult:
    """The whole job's :class:`~torchslq.SolverResult`, shards concatenated in row order.

    Per-element fields are concatenated; per-iteration ``history`` entries ``(B, iters+1)``
    are padded with NaN to the longest shard (shards stop after different iteration
    counts); the history's ``"time"`` axis (per shard) is dropped; ``options`` are the first
    shard's. Raises :class:`FileNotFoundError` naming the missing shards if the job is
    incomplete.
    """
    parts = list(iter_shards(out_dir, map_location))
    results = [r for _, _, r in parts]
    rows = [stop - start for start, stop, _ in parts]
    cls = type(results[0])
    merged = {f.name: _cat([getattr(r, f.name) for r in results], rows) for f in fields(cls)}
    if merged.get("history") is None:
        merged["history"] = {}
    return cls(**merged)
