"""Where a stage's time goes: named phases and their wall seconds (the sim stage's ``phases_s``, the seconds
`clothgap eval` prints). Phases timed in one thread add up; one timed in another thread (the sim stage's ``write``)
overlaps them."""

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
