"""The eval stage's settings (no heavy imports here)."""

from __future__ import annotations

from dataclasses import dataclass

from clothgap import checks


@dataclass(frozen=True)
class EvalConfig:
    bootstrap: int = 1000                   # resamples for confidence intervals
    confidence: float = 0.95

    def problems(self) -> list[str]:
        """What is wrong with these settings, one message each (empty when they are valid)."""
        return (checks.number("eval.bootstrap", self.bootstrap, 1)
                + checks.number("eval.confidence", self.confidence, 0, 1, lo_open=True, hi_open=True))
