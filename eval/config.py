"""The eval stage's settings (no heavy imports here)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EvalConfig:
    bootstrap: int = 1000                   # resamples for confidence intervals
    confidence: float = 0.95
