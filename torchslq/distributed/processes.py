"""Process groups for torchslq jobs on ``torch.distributed``.

Two ways to get ``world_size`` processes with a process group:

* ``torchrun --nproc_per_node N script.py`` (one machine or several): every process
  calls :func:`init_from_env`, which reads ``RANK``, ``WORLD_SIZE``, ``MASTER_ADDR``,
  ``MASTER_PORT`` set by ``torchrun`` and joins the group (gloo on the CPU, NCCL for CUDA);
* :func:`launch` from a plain Python process: ``nprocs`` local workers
  (``torch.multiprocessing``) on a free TCP port of this machine, gloo by default, with a
  wall-clock timeout so that a hung worker fails the call instead of blocking it.

Why ``torch.distributed`` (and not Ray): it ships with torch, ``torchrun`` is the launcher
PyTorch users already run for ``DistributedDataParallel`` training, gloo works on every
CPU and NCCL on GPUs, and a sharded batch solve only needs ranks, a broadcast and a
barrier (the shards' results go to disk, not through the engine). Ray is not a
dependency of torchslq.
"""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from datetime import timedelta
from typing import Any

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

__all__ = ["free_port", "init_from_env", "launch", "rank_and_world"]


def free_port() -> int:
    """A TCP port of 127.0.0.1 that was free a moment ago (for a local rendezvous)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rank_and_world() -> tuple[int, int]:
    """``(rank, world_size)`` of the default process group, or ``(0, 1)`` without one."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def init_from_env(backend: str | None = None, timeout_s: float = 600.0) -> tuple[int, int]:
    """Join the default process group from ``torchrun``'s environment variables.

    Args:
        backend: ``"gloo"``, ``"nccl"``, or None: NCCL when CUDA is available, else gloo.
        timeout_s: collective timeout in seconds.

    Returns ``(rank, world_size)``; ``(0, 1)`` without a process group when
    ``WORLD_SIZE`` is unset (a plain ``python script.py`` run). An existing group is
    kept.
    """
    if dist.is_initialized():
        return rank_and_world()
    if "WORLD_SIZE" not in os.environ:
        return 0, 1
    if backend is None:
        backend = "nccl" if torch.cuda.is_available() else "gloo"
    if backend == "nccl":
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    dist.init_process_group(backend, timeout=timedelta(seconds=timeout_s))
    return rank_and_world()


def _worker(
    index: int,
    fn: Callable[..., Any],
    args: tuple,
    nprocs: int,
    port: int,
    backend: str,
    timeout_s: float,
    threads: int | None,
) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(index),
        WORLD_SIZE=str(nprocs),
        LOCAL_RANK=str(index),
    )
    if threads is not None:
        torch.set_num_threads(threads)
    dist.init_process_group(
        backend,
        init_method=f"tcp://127.0.0.1:{port}",
        rank=index,
        world_size=nprocs,
        timeout=timedelta(seconds=timeout_s),
    )
    try:
        fn(index, nprocs, *args)
    finally:
        dist.destroy_process_group()


def launch(
    fn: Callable[..., Any],
    nprocs: int,
    args: tuple = (),
    *,
    backend: str = "gloo",
    timeout_s: float = 600.0,
    start_method: str = "spawn",
    threads: int | None = 1,
) -> None:
    """Run ``fn(rank, world_size, *args)`` in ``nprocs`` local processes, each a member
    of a fresh default process group, and wait for all of them.

    Args:
        fn: a picklable (module-level) function.
        nprocs: number of worker processes (>= 1).
        args: extra arguments of ``fn`` (picklable).
        backend: ``"gloo"`` (CPU) or ``"nccl"`` (one GPU per process).
        timeout_s: wall-clock limit of the whole run and the collectives' timeout: past
            it the workers are terminated and :class:`TimeoutError` is raised.
        start_method: ``"spawn"`` (default, safe with threads and CUDA) or ``"fork"``
            (faster start on Linux, CPU only).
        threads: ``torch.set_num_threads`` in each worker (default 1: the workers share
            the machine's cores); None leaves torch's default.

    Raises:
        torch.multiprocessing.ProcessRaisedException / ProcessExitedException: a worker
            raised or died (the others are terminated).
        TimeoutError: the run took longer than ``timeout_s``.

    The workers are terminated whenever this call ends early: a worker's failure, the
    timeout, an exception here, or SIGTERM to the calling process (handled while the
    call waits, from the main thread).
    """
    if not isinstance(nprocs, int) or nprocs < 1:
        raise ValueError(f"nprocs must be a positive int, got {nprocs!r}")
    port = free_port()
    ctx = mp.start_processes(
        _worker,
        args=(fn, tuple(args), nprocs, port, backend, timeout_s, threads),
        nprocs=nprocs,
        join=False,
        start_method=start_method,
    )
    deadline = time.monotonic() + timeout_s

    def _terminated(signum, frame):  # SIGTERM to this process: stop the workers too
        raise SystemExit(128 + signum)

    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminated) if main_thread else None
    try:
        while not ctx.join(timeout=max(0.1, min(1.0, deadline - time.monotonic()))):
            if time.monotonic() > deadline:
                raise TimeoutError(f"launch: workers still running after {timeout_s:.0f} s")
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
        for p in ctx.processes:
            if p.is_alive():
                p.terminate()
        for p in ctx.processes:
            p.join(5)
