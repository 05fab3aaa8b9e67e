"""Where readings put each measured fabric, fabric by fabric: each reading's class for each fabric beside Table 2's
and the classes of two readers that look at no clip (the nearest class to the fabric's tables, and to its tables
over its weight relative to the basis's: a perfect reader of a motion that shows S / w and B / w alone), how many
fabrics each reading puts within one bin of those three, and for every two readings how many fabrics they put
within one bin of each other (whether two readers land alike, not only equally often on Table 2).

    python3 scripts/fabric_classes.py FILE[:KEY/KEY...] [...] [--out classes.json]

Inputs are what scripts/reading_bias.py reads: `clothgap eval measured`'s JSON or its tables in a results file, a
`clothgap eval learnability --measured` report, or scripts/reader_ceiling.py's output (its reader on the measured
fabrics' true lattices). A reading is named by its input and its own name. Within one bin is goal 3's count (at
most one bin off in p and in k, ``eval.metrics.within_one_bin``). A file, key or row that holds no reading of the
ten fabrics is named and nothing is written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from clothgap.files import print_json, script_command  # noqa: E402
from eval import classes, metrics  # noqa: E402
from reading_bias import input_readings  # noqa: E402


def _label(index: int) -> str:
    return f"({classes.p_value(index):g}, {classes.k_value(index):g})"


def _within(a: dict[str, int], b: dict[str, int], fabrics: list[str]) -> int:
    return int(metrics.within_one_bin([a[f] for f in fabrics], [b[f] for f in fabrics]).sum())


def compare(found: dict[str, dict[str, tuple[float, float]]]) -> dict:
    """The classes, the counts against the references and the agreement of every two of ``found`` ({reading:
    {fabric: (p, k)}}, each reading of all ten fabrics)."""
    from sim.measured import reference_classes

    refs = reference_classes()
    fabrics = sorted(refs["table2"])
    picked: dict[str, dict[str, int]] = {}
    for name, reading in found.items():
        missing = [f for f in fabrics if f not in reading]
        if missing:
            raise ValueError(f"{name}: no reading of {', '.join(missing)}")
        picked[name] = {f: classes.nearest_class(*reading[f]) for f in fabrics}
    return {"fabrics": fabrics,
            "references": {ref: {f: _label(c) for f, c in by.items()} for ref, by in refs.items()},
            "readings": {name: {"classes": {f: _label(c) for f, c in by.items()},
                                "within_one_bin": {ref: _within(refs[ref], by, fabrics) for ref in refs},
                                "exact_table2": int(sum(by[f] == refs["table2"][f] for f in fabrics))}
                         for name, by in picked.items()},
            "agreement_within_one_bin": {a: {b: _within(picked[a], picked[b], fabrics) for b in picked if b != a}
                                         for a in picked}}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="+", metavar="FILE[:KEY/KEY...]")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    found: dict[str, dict[str, tuple[float, float]]] = {}
    for item in args.inputs:
        try:
            for name, reading in input_readings(item).items():
                found[f"{item} {name}"] = reading
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise SystemExit(f"fabric_classes: {item}: {e}") from e
    try:
        result = {"command": script_command(__file__, argv), **compare(found)}
    except ValueError as e:
        raise SystemExit(f"fabric_classes: {e}") from e
    print_json(result, args.out)
    return result


if __name__ == "__main__":
    main()
