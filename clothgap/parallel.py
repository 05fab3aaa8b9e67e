"""How many host processes a stage may start for its own pools (remeshing cloths, writing clips).

A process executor runs several stage workers on one host; each gets an equal share of the CPUs through
``CLOTHGAP_HOST_PROCESSES``, so that their pools do not oversubscribe the host together.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor

HOST_PROCESSES_ENV = "CLOTHGAP_HOST_PROCESSES"


def host_processes() -> int:
    """This process's share of the host's CPUs: ``CLOTHGAP_HOST_PROCESSES`` where an executor set it for its
    workers (a positive integer), else every CPU."""
    value = os.environ.get(HOST_PROCESSES_ENV, "").strip()
    if value.isdigit() and int(value) >= 1:
        return int(value)
    return os.cpu_count() or 1


def share_of_host(workers: int) -> int:
    """The CPUs each of ``workers`` processes on this host gets (at least one)."""
    return max(1, host_processes() // max(1, workers))


def pool_size(items: int, min_items: int, min_cpus: int) -> int:
    """Processes for a pool over ``items``: this process's share of the CPUs when there are at least
    ``min_items`` items and the share has at least ``min_cpus`` CPUs, else 0 (the work stays in this process)."""
    cpus = host_processes()
    return cpus if items >= min_items and cpus >= min_cpus else 0


def spawn_pool(processes: int) -> ProcessPoolExecutor:
    """A pool of spawned processes: not forked, since the parent may hold a CUDA context."""
    return ProcessPoolExecutor(max_workers=processes, mp_context=mp.get_context("spawn"))


def chunk_size(items: int, processes: int) -> int:
    """Items per task of ``pool.map``: about four tasks a process, so that a slow chunk does not hold the rest."""
    return max(1, math.ceil(items / (4 * max(1, processes))))


def pool_map(fn: Callable, *iterables: Iterable, processes: int, chunksize: int | None = None) -> Iterator:
    """``map(fn, *iterables)`` in a spawned pool of up to ``processes`` when that is more than one and there are two
    or more items, else in this process; results in order, the pool shut when they are all read. ``chunksize``:
    items a task (default ``chunk_size``)."""
    columns = [list(it) for it in iterables]
    items = len(columns[0]) if columns else 0
    if processes <= 1 or items < 2:
        yield from map(fn, *columns)
        return
    with spawn_pool(min(processes, items)) as pool:
        yield from pool.map(fn, *columns, chunksize=chunksize or chunk_size(items, processes))
