"""A combined render variant from the variants that helped: chosen on even test sequences, reported on odd ones.

    python scripts/combined_variant.py select RUN [--setting S ...] [--model lrcn] [--test heldout]
                                              [--reference paper] [--name randomised] [--variants-dir DIR]
    CLOTHGAP_VARIANTS_DIR=DIR clothgap pipeline RUN --set render.variants=<the run's variants>,randomised
    python scripts/combined_variant.py report RUN [--name randomised] [--setting S ...] [--variants-dir DIR]

select reads the run's eval predictions (after ``clothgap eval RUN``), weighs each training variant's gain
over the reference on the test variant on the even test sequences, and writes ``DIR/NAME.toml`` (the union of
what the variants that gained change from paper) and ``RUN/eval/combined-NAME.json``. It exits 3, writing
nothing, when no variant gained. report, once the combined variant is rendered, trained and evaluated, writes
``RUN/eval/combined-NAME-report.{json,md}`` from the odd test sequences only. ``eval/combine.py`` says why.
Bad input is one ``error:`` line and exit status 2.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import clothgap.config  # noqa: E402,F401  (registers the study config that Run.open reads)
from clothgap.errors import ConfigError, UserError  # noqa: E402
from clothgap.runs import Run  # noqa: E402
from eval import combine  # noqa: E402
from render.variants import USER_VARIANTS_ENV  # noqa: E402

NOTHING_HELPED = 3


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    sel = sub.add_parser("select", help="choose on the even test sequences; write the variant file")
    rep = sub.add_parser("report", help="score the combined variant on the odd test sequences")
    for p in (sel, rep):
        p.add_argument("run", type=Path)
        p.add_argument("--setting", action="append", help="a setting (repeatable; default: "
                       + ("every setting with predictions)" if p is sel else "the selection's)"))
        p.add_argument("--name", default="randomised", help="the combined variant's name (default randomised)")
        p.add_argument("--variants-dir", type=Path, help=f"the folder of the user's variants (default "
                       f"${USER_VARIANTS_ENV})")
    # report takes the selection's model, test and reference; naming another one is an error.
    sel.add_argument("--model", default="lrcn")
    sel.add_argument("--test", default="heldout", help="the test variant (default heldout)")
    sel.add_argument("--reference", default="paper")
    for flag in ("--model", "--test", "--reference"):
        rep.add_argument(flag, help="must be the selection's (default: the selection's)")
    return ap


def _variants_dir(args: argparse.Namespace, required: bool) -> Path | None:
    """--variants-dir, else $CLOTHGAP_VARIANTS_DIR; put in the environment so that the run's config, which may
    name the combined variant, is checked against it."""
    folder = args.variants_dir or (Path(os.environ[USER_VARIANTS_ENV]) if os.environ.get(USER_VARIANTS_ENV)
                                   else None)
    if folder is None and required:
        raise ConfigError(f"where should the variant file go? give --variants-dir or set ${USER_VARIANTS_ENV}")
    if folder is not None and folder.is_dir():
        os.environ[USER_VARIANTS_ENV] = str(folder)
    return folder


def _open(path: Path, folder: Path | None) -> Run:
    try:
        return Run.open(path)
    except ConfigError as e:
        if folder is None and "unknown render variant" in str(e):
            raise ConfigError(f"{e} (a variant of your own, such as the combined one? give --variants-dir or set "
                              f"${USER_VARIANTS_ENV})") from None
        raise


def run_select(args: argparse.Namespace) -> int:
    folder = _variants_dir(args, required=True)
    run = _open(args.run, folder)
    settings = tuple(args.setting) if args.setting else combine.default_settings(run, args.model, args.test,
                                                                                  args.reference)
    q = combine.Question(settings, args.model, args.test, args.reference)
    record = combine.select(run, q, args.name, folder)
    print("\n".join(combine.selection_lines(record)))
    if not record["settings"]:
        why = "no variant gained" if not record["chosen"] else "the variants that gained change nothing from paper"
        print(f"{why} on the even half: nothing written, no combined variant to make")
        return NOTHING_HELPED
    toml, selection = combine.write_selection(run, record, folder)
    print(f"combined: {', '.join(record['chosen'])} -> "
          + ", ".join(f"{k}={v!r}" for k, v in record["settings"].items()))
    print(f"wrote {toml}\nwrote {selection}")
    variants = ",".join(dict.fromkeys([*run.config.render.variants, args.name]))
    print(f"next: CLOTHGAP_VARIANTS_DIR={toml.parent} clothgap pipeline {run.root} --set render.variants={variants}\n"
          f"      python scripts/combined_variant.py report {run.root} --name {args.name} --variants-dir {toml.parent}")
    return 0


def run_report(args: argparse.Namespace) -> int:
    run = _open(args.run, _variants_dir(args, required=False))
    record = combine.read_selection(run, args.name)
    q = combine.report_question(record, tuple(args.setting) if args.setting else None, args.model, args.test,
                                args.reference)
    rep = combine.report(run, record, q)
    json_path, md_path, text = combine.write_report(run, rep)
    print(text)
    print(f"wrote {json_path}\nwrote {md_path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return run_select(args) if args.command == "select" else run_report(args)
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
