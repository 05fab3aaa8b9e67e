"""Render-variant studies as Python scripts: start or open a run, add variants, run the stages, read the
results as pandas DataFrames.

    from clothgap import api

    study = api.start("runs/lighting", preset="smoke")
    study.add_variants("lighting-random", "daylight")
    study.run()                     # sim, render, train, eval, report: each skips what is done
    print(study.gap_matrix())       # accuracy, rows = trained on, columns = tested on
    print(study.axis_ranking())     # which render axis closes most of the gap

A study is a run folder like any other: ``clothgap render runs/lighting`` and ``api.open("runs/lighting")``
work on the same folder, and both skip finished clips and models. A run may gain variants, models, seeds
and settings at any time (finished simulations are reused); a change that would make finished work
disagree with the config is refused, naming the settings (``clothgap.runs.Run.create_or_resume``).
Failed clips raise ``StageFailures`` after the rest of the stage is done, as the command exits 1.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from clothgap.config import (ConfigError, StudyConfig, apply_overrides, apply_settings, pairs, preset as preset_config,
                             read_config_file, shown, with_name)
from clothgap.errors import MissingInputError
from clothgap.runs import Run, clip_index

if TYPE_CHECKING:
    import pandas as pd


class StageFailures(Exception):
    """A stage finished the rest of its work but some clips failed or were left out (the command exits 1)."""


def failure_lines(stage: str, summary: object) -> list[str]:
    """What a stage's summary says failed or was left out.

    Args:
        stage: ``"sim"``, ``"render"`` or ``"eval"`` (any other stage lists nothing).
        summary: The summary the stage returned.

    Returns:
        One ``where: why`` line per clip (empty when none failed).
    """
    if not isinstance(summary, dict):
        return []
    if stage == "sim":
        return [f"{f['setting']}/{f['clip_id']}: {f['error']}" for f in summary.get("failed_clips", [])]
    if stage == "render":
        return [f"{f['variant']}/{f['setting']}/{f['clip_id']}: {f['error']}" for f in summary.get("failed", [])]
    if stage == "eval":
        return sorted(set(summary.get("left_out_clips", [])))
    return []


def failure_message(stage: str, summary: object) -> str:
    """One line naming the clips a stage's summary lists as failed or left out.

    Args:
        stage: ``"sim"``, ``"render"`` or ``"eval"``.
        summary: The summary the stage returned.

    Returns:
        The line (the first five clips and a count of the rest), or "" when none failed.
    """
    lines = failure_lines(stage, summary)
    if not lines:
        return ""
    what = "test clip(s) left out of the numbers" if stage == "eval" else "clip(s) failed"
    shown_lines = "; ".join(lines[:5]) + (f"; ... ({len(lines) - 5} more)" if len(lines) > 5 else "")
    return f"{stage}: {len(lines)} {what}: {shown_lines}"


FIX_FAILURES = ("Fix or redo them and run again (finished work is kept), or pass --allow-failures "
                "(allow_failures=True) to accept the results without them")


def _overrides(settings: Mapping[str, Any] | None) -> list[str]:
    """``{"sim.frames": 30, "render.variants": ["paper", "grid"]}`` as ``--set`` strings."""
    return [f"{key}={shown(value)}" for key, value in (settings or {}).items()]


def start(out: Path | str, preset: str | None = None, *, config_file: Path | str | None = None,
          settings: Mapping[str, Any] | None = None) -> "Study":
    """Start a run, or resume the one in ``out`` (the same as ``clothgap sim --preset P --config F --set ...``).

    Args:
        out: The run folder; created when missing.
        preset: The preset to start from (``smoke``, ``small``, ``paper``, ``study``), over the one named in
            ``config_file``; None: the file's, else the run's own config (``out`` must then hold a run).
        config_file: A TOML file of settings (tables ``[sim]``, ``[render]``, ... as in ``config.json``, and
            an optional ``preset = NAME``), laid over the preset.
        settings: Settings by dotted name, applied last, e.g. ``{"sim.frames": 30, "train.epochs": 3}``.

    Returns:
        The study. Nothing is simulated or rendered yet.

    Raises:
        ConfigError: an unknown preset or setting, a bad value, bad TOML, or a change that would invalidate
            finished work in ``out`` (each setting named).
    """
    out = Path(out)
    cfg = resolve_config(out, preset, config_file, _overrides(settings))
    return Study(Run.create_or_resume(out, cfg).root)


def resolve_config(root: Path | None, preset: str | None, config_file: Path | str | None,
                   overrides: list[str]) -> StudyConfig:
    """The config a run in ``root`` gets: the preset, then the file's settings, then each override.

    Args:
        root: The run folder, or None when it is not chosen yet (``runs/<name>`` by the CLI's convention).
        preset: The preset to start from; None: the one ``config_file`` names, else the run's own config.
        config_file: A TOML file of settings (as ``start``'s), or None.
        overrides: ``section.key=value`` strings, applied last.

    Returns:
        The config. A run started from a preset is named after its folder unless the file or an override
        names it.

    Raises:
        ConfigError: no run folder and no preset, an unknown preset or setting, a bad value or bad TOML.
    """
    file_preset, file_settings = read_config_file(config_file) if config_file is not None else (None, {})
    preset = preset or file_preset
    if preset is None and root is None:
        raise ConfigError("name a run folder (RUN_DIR or --out), or a preset to start from (--preset NAME, "
                          "or preset = NAME in the --config file)")
    cfg = preset_config(preset) if preset is not None else Run.open(root).config
    if config_file is not None:
        cfg = apply_settings(cfg, file_settings, str(config_file))
    cfg = apply_overrides(cfg, overrides)
    named = "name" in file_settings or any(o.partition("=")[0].strip() == "name" for o in overrides)
    return with_name(cfg, root.name) if root is not None and preset is not None and not named else cfg


def from_command_line(argv: list[str] | None = None, out: str = "runs/study", description: str = "") -> "Study":
    """Start or resume a study from a script's command line: ``--out DIR``, ``--preset NAME`` (default ``smoke``),
    ``--config FILE``, ``--set SECTION.KEY=VALUE`` (repeatable), as the ``clothgap`` commands take them.

    Args:
        argv: The arguments (default: ``sys.argv[1:]``).
        out: The run folder when ``--out`` is not given.
        description: The script's ``--help`` text (e.g. its ``__doc__``).

    Returns:
        The study (``start`` with those arguments).
    """
    import argparse

    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=out, help=f"run folder, created or resumed (default: {out})")
    parser.add_argument("--preset", default=None, help="preset a new run starts from (default: smoke, or the "
                                                       "config file's)")
    parser.add_argument("--config", dest="config_file", metavar="FILE", help="a TOML file of settings")
    parser.add_argument("--set", dest="settings", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override a setting (repeatable; after --config)")
    args = parser.parse_args(argv)
    bad = [s for s in args.settings if "=" not in s]
    if bad:
        parser.error(f"--set {bad[0]!r} is not of the form section.key=value")
    preset = args.preset
    if preset is None and not (Path(args.out) / "config.json").is_file():     # a new run: the file's preset, or smoke
        preset = (read_config_file(args.config_file)[0] if args.config_file else None) or "smoke"
    return start(args.out, preset, config_file=args.config_file, settings=dict(s.split("=", 1) for s in args.settings))


def open(path: Path | str) -> "Study":  # noqa: A001 - api.open, as gzip.open
    """Open an existing run folder.

    Args:
        path: A run folder (one with a ``config.json``), made by ``start`` or the ``clothgap`` command.

    Returns:
        The study.

    Raises:
        ConfigError: ``path`` is not a run folder, or its config is invalid.
    """
    return Study(Run.open(path).root)


def render_test_variants(run: Run, variants: Iterable[str], executor: Any = None) -> dict:
    """Render ``variants`` (looks no model trains on: ``clothgap.executor.run_for_test_variants``) on the clips the
    split tests on (the split training makes, when the run has none yet), through ``executor`` (a
    ``clothgap.executor.ExecutorOptions``; None: this process). Returns the render stage's summary."""
    from clothgap.executor import ExecutorOptions, run_stage
    from learn.split import current_split, part_clips

    tested = sorted({clip_index(c) for setting in run.config.sim.settings()
                     for c in part_clips(current_split(run, setting), "test")})
    return run_stage(run, "render", executor or ExecutorOptions(), indices=tested, test_variants=tuple(variants))


class Study:
    """One run folder and the stages that fill it; every method reads the run's current ``config.json``."""

    def __init__(self, root: Path | str):
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"Study({str(self.root)!r})"

    # ---------------------------------------------------------------- the config

    @property
    def run(self) -> Run:
        """The run (folder and validated config), read afresh from ``config.json``."""
        return Run.open(self.root)

    @property
    def config(self) -> StudyConfig:
        """The run's resolved config."""
        return self.run.config

    @property
    def variants(self) -> tuple[str, ...]:
        """The render variants the run renders and trains on (``render.variants``)."""
        return self.config.render.variants

    def update(self, settings: Mapping[str, Any]) -> "Study":
        """Change settings of the run, e.g. ``{"train.models": ["lrcn", "base1"], "train.seeds": [0, 1]}``.

        Args:
            settings: Settings by dotted name; lists as Python lists or comma-separated strings.

        Returns:
            The study, for chaining.

        Raises:
            ConfigError: an unknown setting or bad value, or a change that would invalidate finished work
                (settings of a stage that has finished work, other than lists that only grow).
        """
        cfg = apply_overrides(self.config, _overrides(settings))
        Run.create_or_resume(self.root, cfg)
        return self

    def add_variants(self, *names: str, settings: Iterable[str] | None = None) -> "Study":
        """Render, train and test on more render variants; finished simulations and renders are reused.

        Args:
            *names: Variant names from the registry (``clothgap render --list-variants``, or TOML files in
                ``$CLOTHGAP_VARIANTS_DIR``); names the run already has are kept once.
            settings: Only for these simulated settings (e.g. ``["wind-adaptive"]``, through
                ``render.variant_settings``); None: every setting of the run.

        Returns:
            The study, for chaining.

        Raises:
            ConfigError: an unknown variant or setting.
        """
        cfg = self.config
        new = [n for n in dict.fromkeys(names) if n not in cfg.render.variants]
        pairs_ = list(cfg.render.variant_settings)
        if settings is not None:
            pairs_ += [f"{n}:{s}" for n in new for s in settings]
        render = replace(cfg.render, variants=cfg.render.variants + tuple(new), variant_settings=tuple(pairs_))
        Run.create_or_resume(self.root, replace(cfg, render=render))
        return self

    # ---------------------------------------------------------------- the stages

    def _check(self, stage: str, summary: dict, allow_failures: bool) -> dict:
        message = failure_message(stage, summary)
        if message and not allow_failures:
            raise StageFailures(f"{message}. {FIX_FAILURES}")
        return summary

    def simulate(self, executor: Any = None, *, progress: bool = True, allow_failures: bool = False) -> dict:
        """Simulate every clip of the run that is not done yet (``clothgap sim RUN``).

        Args:
            executor: A ``clothgap.executor.ExecutorOptions`` (process pool, Ray); None: this process.
            progress: Show progress bars.
            allow_failures: Return even when clips failed (they are listed in the summary).

        Returns:
            The stage's summary (clips simulated, skipped, failed, seconds).

        Raises:
            StageFailures: some clips failed (after all others were simulated), unless ``allow_failures``.
        """
        from clothgap.executor import ExecutorOptions, run_stage

        opts = replace(executor or ExecutorOptions(), progress=progress)
        return self._check("sim", run_stage(self.run, "sim", opts), allow_failures)

    def render(self, executor: Any = None, *, test_variants: Iterable[str] = (), progress: bool = True,
               allow_failures: bool = False) -> dict:
        """Render every simulated clip under each of the run's variants, skipping finished clips
        (``clothgap render RUN``).

        Args:
            executor: A ``clothgap.executor.ExecutorOptions``; None: this process.
            test_variants: Variants rendered for testing only (no model trains on them; ``evaluate`` tests every
                model on them), e.g. ``["heldout"]``: the test clips of the run's split (the one training makes,
                when there is none yet), through the same executor.
            progress: Show progress bars.
            allow_failures: Return even when clips failed.

        Returns:
            The stage's summary (``test_variants``: the summary of the test-only renders, when asked for).

        Raises:
            ConfigError: the run has no simulated clips yet, or a variant is unknown.
            StageFailures: some clips failed (after all others were rendered), unless ``allow_failures``.
        """
        from clothgap.executor import ExecutorOptions, run_for_test_variants, run_stage

        run = self.run
        for setting in run.config.sim.settings():
            run.require(run.sim_dir(setting), "sim")
        test_variants = tuple(test_variants)
        if test_variants:
            run_for_test_variants(run, test_variants)          # an unknown look refused before any rendering
        opts = replace(executor or ExecutorOptions(), progress=progress)
        summary = self._check("render", run_stage(run, "render", opts), allow_failures)
        if test_variants:
            summary["test_variants"] = self._check("render", render_test_variants(run, test_variants, opts),
                                                   allow_failures)
        return summary

    def train(self, *, settings: Iterable[str] | None = None, variants: Iterable[str] | None = None,
              models: Iterable[str] | None = None, seeds: Iterable[int] | None = None,
              progress: bool = True, parallel: int = 1, executor: Any = None) -> list[Path]:
        """Train every (setting, variant, model, seed) of the run's grid not done yet, or the part selected
        (``clothgap train RUN [--setting S --variant V --model M --seed N] [--parallel N]``).

        Args:
            settings: Only these simulated settings (default: all of the run's).
            variants: Only these of the run's variants.
            models: Only these models (default: ``train.models``).
            seeds: Only these seeds (default: ``train.seeds``).
            progress: Show progress bars.
            parallel: Models trained at a time, each in its own process, over the visible GPUs.
            executor: A ``clothgap.executor.ExecutorOptions`` to train through instead (GPU slots, Ray tasks).

        Returns:
            The finished train folders, one per (setting, variant, model, seed).

        Raises:
            ConfigError: a name the run does not have, or a variant not rendered yet.
        """
        return train_selected(self.run, settings, variants, models, seeds, progress, parallel=parallel,
                              options=executor)

    def evaluate(self, *, progress: bool = True, allow_failures: bool = False) -> dict:
        """Test every finished model on every rendered variant and write the tables (``clothgap eval RUN``).

        Args:
            progress: Print what is predicted.
            allow_failures: Return even when test clips had no prediction (listed in ``eval/summary.json``).

        Returns:
            A short summary (cells scored, in-domain accuracy per model).

        Raises:
            ConfigError: no finished model yet.
            StageFailures: test clips were left out, unless ``allow_failures``.
        """
        from eval.stage import run_eval

        run = self.run
        run.require(run.train_root, "train")
        return self._check("eval", run_eval(run, progress=progress), allow_failures)

    def report(self) -> Path:
        """Write the run's HTML report (``clothgap report RUN``).

        Returns:
            The path of ``report/report.html``.

        Raises:
            ConfigError: the run is not evaluated yet.
        """
        from eval.report import write_report

        run = self.run
        run.require(run.eval_dir, "eval")
        return write_report(run)

    def run_all(self, executor: Any = None, *, report: bool = True, progress: bool = True,
                allow_failures: bool = False, train_parallel: int = 1) -> dict[str, Any]:
        """Simulate, render, train and evaluate in turn, then write the report (``clothgap pipeline RUN``);
        each stage skips what is done.

        Args:
            executor: A ``clothgap.executor.ExecutorOptions`` for simulation and rendering; None: this process.
            train_parallel: Models trained at a time (``--train-parallel``).
            report: Write ``report/report.html`` at the end.
            progress: Show progress bars.
            allow_failures: Go on past failed clips (they are listed in the summaries).

        Returns:
            Each stage's summary by name (``sim``, ``render``, ``train``, ``eval``, ``report``).

        Raises:
            StageFailures: some clips failed or were left out, unless ``allow_failures``.
        """
        out: dict[str, Any] = {
            "sim": self.simulate(executor, progress=progress, allow_failures=allow_failures),
            "render": self.render(executor, progress=progress, allow_failures=allow_failures),
            "train": [str(p) for p in self.train(progress=progress, parallel=train_parallel)],
            "eval": self.evaluate(progress=progress, allow_failures=allow_failures)}
        if report:
            out["report"] = str(self.report())
        return out

    # ---------------------------------------------------------------- the results

    def _table(self, name: str) -> pd.DataFrame:
        import pandas as pd

        path = self.root / "eval" / name
        if not path.is_file():
            raise MissingInputError(f"{path} does not exist: evaluate the run first (study.evaluate(), or "
                                    f"`clothgap eval {self.root}`)")
        return pd.read_csv(path)

    def results(self) -> pd.DataFrame:
        """Every score of every (setting, train variant, model, test variant), seeds pooled, with intervals.

        Returns:
            ``eval/results.csv``: ``acc``, ``top3``, ``stretch_acc``, ``bend_acc``, ``within1``, ``class_dist``,
            ``seq_acc`` (each with ``_lo``/``_hi``), ``in_domain``, ``sequences``, ``checkpoints``, ...
        """
        return self._table("results.csv")

    def domain_gap(self) -> pd.DataFrame:
        """Accuracy for every (train variant, test variant) pair with its drop and gap, paired by clip.

        Returns:
            ``eval/domain_gap.csv``: ``acc``, ``drop`` (in-domain accuracy of the training variant minus this),
            ``gap`` (accuracy of a model trained on the test variant minus this), the stiffness correlations,
            each with ``_lo``/``_hi``.
        """
        return self._table("domain_gap.csv")

    def gap_matrix(self, setting: str | None = None, model: str | None = None, score: str = "acc") -> pd.DataFrame:
        """One score as a matrix: rows the training variant, columns the test variant.

        Args:
            setting: The simulated setting (default: the run's first).
            model: The model (default: the first in ``train.models``).
            score: A column of ``domain_gap()`` (``acc``, ``drop``, ``gap``, ``p_spearman``, ...).

        Returns:
            The matrix (NaN where a pair was not scored).
        """
        gap = self.domain_gap()
        cfg = self.config
        setting = setting or cfg.sim.settings()[0]
        model = model or cfg.train.models[0]
        if score not in gap:
            raise ConfigError(f"unknown score {score!r}; domain_gap() has {', '.join(gap.columns)}")
        sub = gap[(gap["setting"] == setting) & (gap["model"] == model)]
        return sub.pivot(index="train_variant", columns="test_variant", values=score)

    def axis_ranking(self) -> pd.DataFrame:
        """Render axes ranked by the accuracy they win back when training matches the test variant on them.

        Returns:
            ``eval/axis_ranking.csv``: ``axis``, ``mean_gain`` (fraction of test windows) with ``_lo``/``_hi``,
            ``mean_share``, ``pairs``, ``clean``, ``examples``; empty with fewer than two variants.
        """
        return self._table("axis_ranking.csv")

    def table3(self) -> pd.DataFrame:
        """The paper's Table 3.

        Returns:
            ``eval/table3.csv``: in-domain accuracy per motion x remeshing x texture, one column per model.
        """
        return self._table("table3.csv")

    def measured(self) -> pd.DataFrame:
        """The measured-fabric set's results (``eval.measured_sequences`` > 0, or ``clothgap eval measured``).

        Returns:
            ``eval/measured.csv``: one row per (model, fabric) with the predicted class beside the paper's
            Table 2 class and the measured stiffness (seeds' ensembles: ``eval/measured_ensembles.csv``).
        """
        return self._table("measured.csv")

    def summary(self) -> dict:
        """What the evaluation used and left out.

        Returns:
            ``eval/summary.json`` as a dict: models and checkpoints, test variants, axes, left-out clips, config.
        """
        path = self.root / "eval" / "summary.json"
        if not path.is_file():
            raise MissingInputError(f"{path} does not exist: evaluate the run first (study.evaluate())")
        return json.loads(path.read_text())


def train_selected(run: Run, settings: Iterable[str] | None = None, variants: Iterable[str] | None = None,
                   models: Iterable[str] | None = None, seeds: Iterable[int] | None = None,
                   progress: bool = True, parallel: int = 1, options=None) -> list[Path]:
    """Train the selected part of the run's grid (all of it when nothing is selected); finished folders are kept.

    Args:
        run: The run.
        settings, variants, models, seeds: Selections; each name must be one the run has.
        progress: Show progress bars.
        parallel: Models trained at a time, each in its own process, spread over the visible GPUs
            (``clothgap.executor.run_train_parallel``); 1 trains them one after another in this process.
        options: A ``clothgap.executor.ExecutorOptions`` to train through instead (a process pool with GPU
            slots, or Ray tasks).

    Returns:
        The finished train folders.

    Raises:
        ConfigError: a name the run does not have, or a selected (setting, variant) not rendered yet.
    """
    from learn.registry import MODEL_NAMES, training_order

    cfg = run.config
    everything = settings is None and variants is None and models is None and seeds is None
    settings = list(settings) if settings is not None else cfg.sim.settings()
    variants = list(variants) if variants is not None else list(cfg.render.variants)
    models = list(models) if models is not None else list(cfg.train.models)
    seeds = list(seeds) if seeds is not None else list(cfg.train.seeds)
    for v in variants:
        if v not in cfg.render.variants:
            raise ConfigError(f"unknown variant {v!r}; this run renders {', '.join(cfg.render.variants)}")
    for s in settings:
        if s not in cfg.sim.settings():
            raise ConfigError(f"unknown setting {s!r}; this run has {', '.join(cfg.sim.settings())}")
    for m in models:
        if m not in MODEL_NAMES:
            raise ConfigError(f"unknown model {m!r}; known models: {', '.join(MODEL_NAMES)}")
    chosen = [(s, v) for s, v in pairs(cfg) if s in settings and v in variants]
    for s, v in chosen:
        run.require(run.render_dir(v, s), "render")
    if everything:
        index = train_all(run, progress=progress, parallel=parallel, options=options)
        return [run.root / e["dir"] for e in index["entries"]]
    # A model that needs another (base2 freezes base1's CNN of the same setting, variant and seed; with
    # train.shared_regressor every model reads that one's) comes after it.
    ordered = training_order(models, cfg.train.shared_regressor)
    grid = [(s, v, m, seed) for s, v in chosen for seed in seeds for m in ordered]
    if parallel != 1 or options is not None:
        from clothgap.executor import run_train_parallel

        return run_train_parallel(run, grid, parallel, progress, options)
    from learn.train import train_one

    return [train_one(run, *entry, progress) for entry in grid]


def train_all(run: Run, *, progress: bool = True, parallel: int = 1, options=None) -> dict:
    """Train the run's whole grid (``clothgap train RUN``, the pipeline's train stage), one model after another
    or, with ``parallel`` / ``options``, side by side (``clothgap.executor.run_train_parallel``); returns
    ``train/index.json`` as written."""
    from learn.stage import run_train, training_grid

    if parallel != 1 or options is not None:
        from clothgap.executor import run_train_parallel

        run_train_parallel(run, training_grid(run), parallel, progress, options)
    return run_train(run, progress)         # after a parallel run every model is done: only the index is written
