"""Texture sweep: the paper's three texture families (random procedural, a fixed grid, one solid colour).

The paper trains on each family separately (its Table 3); here every model is also tested on the other
families, which says how much of what a model learnt was the texture rather than the cloth's motion.
Prints Table 3 (in-domain accuracy per family) and the off-diagonal accuracy, stretching and bending
scores beside exact accuracy, so the sweep says something while exact accuracy is still low.

    python examples/texture_sweep.py --out runs/texture                     # smoke size, minutes on a CPU
    python examples/texture_sweep.py --out runs/texture --preset paper      # the paper's size, on a GPU
"""

from __future__ import annotations

from clothgap import api

TEXTURES = ("paper", "grid", "color")        # paper = the random procedural family


def main(argv: list[str] | None = None) -> api.Study:
    study = api.from_command_line(argv, out="runs/texture", description=__doc__)
    study.add_variants(*TEXTURES)
    study.simulate()
    study.render()
    study.train()
    study.evaluate()
    study.report()

    print("Table 3 (in-domain accuracy per texture family):")
    print(study.table3().to_string(index=False))
    results = study.results()
    cols = ["setting", "model", "train_variant", "test_variant", "acc", "stretch_acc", "bend_acc", "within1"]
    print("\nEvery model on every texture (fractions of test windows):")
    print(results[[c for c in cols if c in results]].round(3).to_string(index=False))
    print(f"\nreport: {study.root / 'report' / 'report.html'}")
    return study


if __name__ == "__main__":
    main()
