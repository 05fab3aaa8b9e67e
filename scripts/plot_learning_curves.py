"""Learning curves (validation solid, training dotted) of the rows of learn result JSONs, one panel per JSON.

    python scripts/plot_learning_curves.py docs/learning-curves.png \
        benchmarks/results/learn_ablation-wind-uniform1-h100-bottleneck2.json \
        benchmarks/results/learn_models-wind-uniform1-h100-bottleneck.json

Each JSON is an `clothgap eval ablation` result (its ``recipes`` rows carry ``curves``); a panel's title
is the JSON's file name. ``FILE.json:NAME`` takes the table NAME of a results file that holds several
(``{"tables": {NAME: ablation result}}``, e.g. learn_levers-*.json), titled NAME. Rows are labelled recipe
(and model where a JSON holds several models); ``--recipe R`` (repeatable) keeps only those recipes' rows.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def _result(spec: str) -> tuple[str, dict]:
    """(panel title, ablation result) of a results argument: a file, or FILE.json:TABLE."""
    path, sep, table = spec.partition(".json:")
    if not sep:
        return Path(spec).stem, json.loads(Path(spec).read_text())
    tables = json.loads(Path(path + ".json").read_text()).get("tables", {})
    if table not in tables:
        raise SystemExit(f"{path}.json has no table {table!r}; it has: {', '.join(tables) or 'none'}")
    return table, tables[table]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="PNG to write")
    ap.add_argument("results", nargs="+", help="result JSONs (clothgap eval ablation), or FILE.json:TABLE")
    ap.add_argument("--recipe", action="append", help="plot only this recipe's rows (repeatable; default all)")
    args = ap.parse_args(argv)
    fig, axes = plt.subplots(1, len(args.results), figsize=(6.5 * len(args.results), 4.5), squeeze=False)
    for ax, spec in zip(axes[0], args.results):
        title, result = _result(spec)
        rows = [r for r in result["recipes"] if not args.recipe or r["recipe"] in args.recipe]
        several_models = len({r["model"] for r in rows}) > 1
        for i, row in enumerate(rows):
            curve = next(iter(row["curves"].values()))     # the first seed
            label = f"{row['recipe']} / {row['model']}" if several_models else row["recipe"]
            colour = f"C{i % 10}"
            epochs = [e["epoch"] for e in curve]
            ax.plot(epochs, [100 * e["val_acc"] for e in curve], color=colour, label=label)
            ax.plot(epochs, [100 * e["train_acc"] for e in curve], color=colour, linestyle=":")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("epoch")
        ax.set_ylabel("accuracy % (validation solid, training dotted)")
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
