"""The eval stage's settings (no heavy imports here)."""

from __future__ import annotations

from dataclasses import dataclass

from clothgap import checks


SIM_ANALYSES = ("table2", "sensitivity")  # what eval.sim_analysis may name


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
    # "table2" (the paper's Table 2) and/or "sensitivity" (Fig. 3); both simulate, on sim.device.
    sim_analysis: tuple[str, ...] = ()
    # Cells of two or more seeds are also scored as one model, the seeds' class probabilities averaged per
    # window (model ``<model>-avg<N>`` in every table), beside the seeds pooled.
    seed_ensemble: bool = False

    def problems(self) -> list[str]:
        """What is wrong with these settings, one message each (empty when they are valid)."""
        return (checks.number("eval.bootstrap", self.bootstrap, 1)
                + checks.number("eval.confidence", self.confidence, 0, 1, lo_open=True, hi_open=True)
                + checks.number("eval.measured_sequences", self.measured_sequences, 0)
                + checks.names("eval.sim_analysis", self.sim_analysis, SIM_ANALYSES, "analysis", required=False))
