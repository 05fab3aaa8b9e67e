"""The eval stage's settings (no heavy imports here)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EvalConfig:
    bootstrap: int = 1000                   # resamples for confidence intervals
    confidence: float = 0.95
    # Measured-fabric test set (eval.measured): the Wang et al. fabrics simulated with their own tables,
    # rendered in a held-out variant and predicted through the real-video path. Sequences per fabric and
    # setting; 0 = not part of `clothgap eval` (`clothgap eval measured RUN` still makes it).
    measured_sequences: int = 0
    measured_variant: str = "heldout"       # render variant of the measured clips: one no model trains on
    measured_fabrics: tuple[str, ...] = ()  # assets/materials names; empty = the ten fabrics of the paper's Table 2
    # The sim stage's material analyses run by `clothgap eval` into RUN/sim_analysis (the report shows them):
    # "table2" (the paper's Table 2, no simulation) and/or "sensitivity" (Fig. 3, simulates).
    sim_analysis: tuple[str, ...] = ()
