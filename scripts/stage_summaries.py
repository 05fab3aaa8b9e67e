"""The stage summaries that `clothgap` prints (``[STAGE] done in WALL s: {JSON}``) of several logs, as one JSON.

    python3 scripts/stage_summaries.py gpw1=render-gpw1.log gpw025-mps=render-gpw025-mps.log --out render_stage.json

Each ``LABEL=LOG`` gives the last summary line of LOG under LABEL: the stage, its wall time as printed, and the
summary's own fields; where the summary counts frames, ``frames_per_s`` is frames over its own ``seconds`` (the
stage's clock). A log without a summary line is named and nothing is written.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from clothgap.files import print_json  # noqa: E402

SUMMARY = re.compile(r"^\[([^\]]+)\] done in ([\d.]+) s: (\{.*\})\s*$", re.M)


def summary(log: Path) -> dict:
    try:
        found = SUMMARY.findall(log.read_text(errors="replace"))
    except OSError as e:
        raise SystemExit(f"stage_summaries: cannot read {log}: {e}") from e
    if not found:
        raise SystemExit(f"stage_summaries: {log} has no '[STAGE] done in ... s: {{...}}' line (did the stage finish?)")
    stage, wall, fields = found[-1]
    try:
        # the CLI prints with json.dumps, which writes NaN and Infinity; the summary written here has null instead
        row = {"stage": stage, "wall_s": float(wall), **json.loads(fields, parse_constant=lambda _: None)}
    except ValueError as e:
        raise SystemExit(f"stage_summaries: {log}: its summary is not JSON ({e})") from e
    if isinstance(row.get("frames"), int) and row.get("seconds"):
        row["frames_per_s"] = round(row["frames"] / row["seconds"], 1)
    return row


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("logs", nargs="+", metavar="LABEL=LOG")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    result = {}
    for spec in args.logs:
        label, sep, path = spec.partition("=")
        if not sep or not label:
            raise SystemExit(f"stage_summaries: expected LABEL=LOG, got {spec!r}")
        result[label] = summary(Path(path))
    print_json(result, args.out)


if __name__ == "__main__":
    main()
