"""Lighting sweep: does a model trained under one lighting still read the material under another?

Trains one model per lighting (the paper's fixed studio, lighting drawn per clip, daylight), tests every
model on every lighting, and prints the accuracy matrix (rows: trained on, columns: tested on), each
model's drop when the lighting changes, and the render axes ranked by the accuracy they win back.

    python examples/lighting_sweep.py --out runs/lighting                    # smoke size, minutes on a CPU
    python examples/lighting_sweep.py --out runs/lighting --preset paper     # the paper's size, on a GPU
    python examples/lighting_sweep.py --out runs/lighting --set train.epochs=3

Run it again to resume; point --out at an existing run to add the lighting variants to it (its
simulations and finished renders are reused).
"""

from __future__ import annotations

from clothgap import api

LIGHTING = ("paper", "lighting-random", "daylight")


def main(argv: list[str] | None = None) -> api.Study:
    study = api.from_command_line(argv, out="runs/lighting", description=__doc__)
    study.add_variants(*LIGHTING)
    study.run_all()

    gap = study.domain_gap()
    for (setting, model), _ in gap.groupby(["setting", "model"]):
        print(f"\n{setting}, {model}: accuracy (%), rows trained on, columns tested on")
        print((100 * study.gap_matrix(setting, model)).round(1).to_string())
    moved = gap[gap["train_variant"] != gap["test_variant"]]
    print("\nAccuracy lost when the lighting changes (drop, % points, 95% interval):")
    for r in moved.itertuples():
        print(f"  {r.model} {r.train_variant:>16} -> {r.test_variant:<16} {100 * r.drop:6.1f} "
              f"[{100 * r.drop_lo:.1f}, {100 * r.drop_hi:.1f}]")
    print("\nRender axes by the accuracy they win back:")
    print(study.axis_ranking().to_string(index=False))
    print(f"\nreport: {study.root / 'report' / 'report.html'}")
    return study


if __name__ == "__main__":
    main()
