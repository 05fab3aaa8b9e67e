"""Where a stage's time goes: named phases and their wall seconds (the sim stage's ``phases_s``, the seconds
`clothgap eval` prints). A stage's top phases add up (sim: scenes, simulate, write_wait); others lie inside one of
them (solver, record, remesh... inside simulate) or run beside them in another thread (sim's write)."""

from __future__ import annotations

import contextlib
import time


@contextlib.contextmanager
def timed(phases: dict[str, float] | None, name: str):
    """Adds the block's wall time to ``phases[name]`` (seconds), when ``phases`` is a dict."""
    start = time.perf_counter()
    try:
        yield
    finally:
        if phases is not None:
            phases[name] = phases.get(name, 0.0) + time.perf_counter() - start
