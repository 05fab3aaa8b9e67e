"""How far, and which way, readings of the measured fabrics sit from where a reader of S / w and B / w would put
them (``sim.measured.over_weight_class``): per reading, the mean over fabrics of log(predicted k / that class's k)
(the bias: below zero reads the bending low), the mean of its absolute value (how far fabric by fabric), and the
same for p. A bin of the class grid is 0.3-0.7 of log apart mid-range.

    python3 scripts/reading_bias.py FILE[:KEY/KEY...] [...] [--out bias.json]

FILE is JSON; the keys lead inside it to either a results file's ``measured_fabrics`` look (``{model: [rows with
"Fabric" and "Predicted (p, k)"]}``, as ``scripts/gather_lease.py`` keeps ``clothgap eval measured``'s tables) or a
``clothgap eval learnability --measured`` report (``{"settings": [{"results": [{"classifier", "fabrics": [{"fabric",
"pred_p", "pred_k"}]}]}]}``). A file or key that leads to neither is named and nothing is written.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from clothgap.files import print_json, script_command  # noqa: E402


def readings(doc, where: str) -> dict[str, dict[str, tuple[float, float]]]:
    """{reading name: {fabric: (predicted p, predicted k)}} from a measured-fabrics look or a probe report."""
    if isinstance(doc, dict) and "settings" in doc:
        return {f"{s.get('setting', i)} {r['classifier']}": {f["fabric"]: (float(f["pred_p"]), float(f["pred_k"]))
                                                            for f in r["fabrics"]}
                for i, s in enumerate(doc["settings"]) for r in s["results"]}
    if isinstance(doc, dict) and doc and all(isinstance(v, list) for v in doc.values()):
        out = {}
        for model, rows in doc.items():
            out[model] = {}
            for row in rows:
                numbers = re.findall(r"[0-9]+(?:\.[0-9]+)?", row["Predicted (p, k)"])
                if len(numbers) != 2:
                    raise ValueError(f"{row['Predicted (p, k)']!r} is not '(p, k)'")
                out[model][row["Fabric"]] = (float(numbers[0]), float(numbers[1]))
        return out
    raise ValueError(f"{where} is neither a measured-fabrics look nor a learnability-measured report")


def bias(reading: dict[str, tuple[float, float]]) -> dict:
    from sim.classes import class_values
    from sim.measured import over_weight_class

    logs = {axis: [math.log(pred[i] / class_values(over_weight_class(fabric))[i]) for fabric, pred in reading.items()]
            for i, axis in enumerate("pk")}
    return {"fabrics": len(reading),
            **{f"{axis}_{name}": sum(f(x) for x in v) / len(v)
               for axis, v in logs.items() for name, f in (("bias", lambda x: x), ("mean_abs", abs))}}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="+", metavar="FILE[:KEY/KEY...]")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    result: dict = {"command": script_command(__file__, argv), "readings": {}}
    for item in args.inputs:
        path, _, keys = item.partition(":")
        try:
            doc = json.loads(Path(path).read_text())
            for key in filter(None, keys.split("/")):
                doc = doc[key]
            found = readings(doc, item)
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise SystemExit(f"reading_bias: {item}: {e}") from e
        for name, reading in found.items():
            result["readings"][f"{item} {name}"] = bias(reading)
    print_json(result, args.out)


if __name__ == "__main__":
    main()
