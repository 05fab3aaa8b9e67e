"""What the sim benchmarks share: the paper preset's sim settings on the CPU, and writing a result with its command."""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import clothgap.config as study_config  # noqa: E402
from clothgap.settings import apply_overrides  # noqa: E402

RESULTS = Path(__file__).parent / "results"


def paper_sim_cpu():
    """The ``paper`` preset's sim settings with the simulation on the CPU."""
    return apply_overrides(study_config.preset("paper"), ["sim.device=cpu"]).sim


def write_result(script: str, argv: list[str] | None, result: dict, out: Path) -> None:
    """Writes ``result`` (JSON) to ``out`` with the command that made it first, and says where."""
    command = f"python benchmarks/{script} " + " ".join(argv if argv is not None else sys.argv[1:])
    out.write_text(json.dumps({"command": command.strip(), **result}, indent=2) + "\n")
    print(f"wrote {out}")
