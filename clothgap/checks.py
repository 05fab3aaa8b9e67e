"""Small checks the stage configs use to describe what is wrong with a setting (no heavy imports).

Each returns a list of messages (empty when the value is fine); every message
names the setting, the bad value and what is allowed.
"""

from __future__ import annotations

import math
import numbers
import re
from collections.abc import Sequence


def names(where: str, values: Sequence, allowed: Sequence, what: str, *, required: bool = True) -> list[str]:
    """A list setting whose entries must come from ``allowed``, each once (and at least one if ``required``)."""
    known = ", ".join(map(str, allowed))
    if required and not values:
        return [f"{where} is empty; choose from {known}"]
    out = []
    unknown = [v for v in values if v not in allowed]
    if unknown:
        out.append(f"{where}: unknown {what} {', '.join(map(repr, unknown))}; known: {known}")
    twice = sorted({v for v in values if list(values).count(v) > 1}, key=str)
    if twice:
        out.append(f"{where}: {', '.join(map(repr, twice))} listed more than once")
    return out


def choice(where: str, value: str, allowed: Sequence[str]) -> list[str]:
    """A setting that must be one of ``allowed``."""
    if value in allowed:
        return []
    return [f"{where}={value!r}: not one of {', '.join(allowed)}"]


def number(where: str, value: float, lo: float | None = None, hi: float | None = None, *,
           lo_open: bool = False, hi_open: bool = False) -> list[str]:
    """A finite number that must lie in [lo, hi] (or open at either end, or unbounded where None).

    NaN compares false with every bound and inf passes an open upper end, so both are refused
    here, before any stage spends minutes on a setting that ends in a traceback deep in Warp or torch.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return [f"{where}={value!r}: must be a number"]
    if not math.isfinite(value):
        return [f"{where}={value!r}: must be a finite number"]
    bad = ((lo is not None and (value <= lo if lo_open else value < lo))
           or (hi is not None and (value >= hi if hi_open else value > hi)))
    if not bad:
        return []
    if hi is None:
        need = f"{'>' if lo_open else '>='} {lo:g}"
    elif lo is None:
        need = f"{'<' if hi_open else '<='} {hi:g}"
    else:
        need = f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    return [f"{where}={value!r}: must be {need}"]


def device(where: str, value: str, extra: Sequence[str] = ()) -> list[str]:
    """A compute device name: auto, cpu, cuda, cuda:N (or one of ``extra``)."""
    if re.fullmatch(r"auto|cpu|cuda(:\d+)?", value) or value in extra:
        return []
    return [f"{where}={value!r}: must be one of auto, cpu, cuda, cuda:N{''.join(', ' + e for e in extra)}"]
