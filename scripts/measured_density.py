"""How much of where the measured fabrics' simulated geometry lands is their density?

The 54 classes scale the basis fabric's tables at the basis's area density (0.284 kg/m^2); the ten measured
fabrics have their own (0.113-0.324). A cloth in wind or on an arm moves by its stiffness against its weight, so a
light fabric may move like a stiffer class. This simulates the Table 2 fabrics with their own tables but at one
density (default the basis fabric's) into ``RUN/measured-density-<value>/sim/<setting>/``, and reads them with
the geometry probe of ``clothgap eval learnability --measured`` (``eval.learnability.probe_measured``; one fit
of ``fit_classes`` reads both folders) beside the same fabrics at their own density (``RUN/measured/sim``,
simulated here if missing): the classifiers, windows and class clips are the same, so the difference is the
density's.

    python scripts/measured_density.py RUN [--setting wind-uniform1] [--sequences 8] [--density basis|KG_M2]
        [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import clothgap.config  # noqa: E402,F401  (the study config, which Run.open reads)
from clothgap.runs import Run  # noqa: E402


def summary(report: dict) -> dict:
    """Per classifier: fabrics within one bin, grid steps, and the bending rank against the measured bending."""
    from eval.learnability import measured_reading

    out = {}
    for r in report["results"]:
        read = measured_reading(r)
        out[r["classifier"]] = {
            "within1_fabrics": read["within1_fabrics"], "fabrics": read["fabrics"], "class_dist": read["class_dist"],
            "spearman_k_vs_measured_bending": read["bending_rank"]["spearman"],
            "spearman_k_vs_table2_k": r["spearman"]["pred_k~table2_k_est"]["spearman"],
            "read_as": {f["fabric"]: [f["pred_p"], f["pred_k"]] for f in r["fabrics"]}}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("run", type=Path)
    ap.add_argument("--setting", help="default: the run's first simulated setting")
    ap.add_argument("--sequences", type=int, default=8, help="clips a fabric (default 8)")
    ap.add_argument("--density", default="basis", help="'basis' (the basis fabric's) or kg/m^2")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)

    from eval.learnability import fit_classes, probe_measured
    from sim.materials import load_material
    from sim.measured import table2_fabrics
    from sim.stage import simulate_measured

    run = Run.open(args.run)
    simulated = run.simulated_settings()
    if not simulated:
        raise SystemExit(f"{run.root}: no simulated clips (run `clothgap sim {run.root}` first)")
    setting = args.setting or simulated[0]
    density = load_material(run.config.sim.basis).density if args.density == "basis" else float(args.density)
    root = run.root / f"measured-density-{density:g}" / "sim"
    t0 = time.perf_counter()
    simulate_measured(run, table2_fabrics(), args.sequences, settings=[setting])
    simulate_measured(run, table2_fabrics(), args.sequences, settings=[setting], density=density,
                      folder_of=lambda s: root / s)
    sim_s = time.perf_counter() - t0
    fitted = fit_classes(run, setting, progress=False)       # one fit reads both folders
    own = probe_measured(run, setting, args.sequences, progress=False, fitted=fitted)
    fixed = probe_measured(run, setting, args.sequences, progress=False, folder=root / setting, fitted=fitted)
    command = sys.argv[1:] if argv is None else argv
    result = {"command": " ".join(["python", "scripts/measured_density.py", *command]),
              "run": str(run.root), "setting": setting, "sequences": args.sequences, "density_kg_m2": density,
              "own_density": summary(own), "one_density": summary(fixed),
              "seconds": {"sim": round(sim_s, 1), "total": round(time.perf_counter() - t0, 1)},
              "reports": {"own_density": own, "one_density": fixed}}
    text = json.dumps(result, indent=1)
    if args.out:
        args.out.write_text(text + "\n")
    for name in ("own_density", "one_density"):
        print(name, {k: (v["within1_fabrics"], round(v["spearman_k_vs_measured_bending"], 2))
                     for k, v in result[name].items()}, file=sys.stderr)
    if not args.out:
        print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
