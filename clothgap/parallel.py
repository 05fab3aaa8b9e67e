"""How many host processes a stage may start for its own pools (remeshing cloths, writing clips).

A process executor runs several stage workers on one host; each gets an equal share of the CPUs through
``CLOTHGAP_HOST_PROCESSES``, so that their pools do not oversubscribe the host together.
"""

from __future__ import annotations

import os

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
