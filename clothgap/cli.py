"""The `clothgap` command: one subcommand per stage, plus `pipeline`.

Each stage reads the previous stage's outputs from the run folder, so stages can
be run, resumed and scaled one at a time:

    clothgap sim --preset smoke --out runs/smoke     # starts the run, writes config.json
    clothgap render runs/smoke
    clothgap train runs/smoke
    clothgap eval runs/smoke
    clothgap report runs/smoke

or all of it at once with `clothgap pipeline --preset smoke --out runs/smoke`.
Heavy libraries (Warp, Mitsuba, torch) are imported inside the commands, so
`--help` and bad-input errors are instant.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import click

from clothgap.api import FIX_FAILURES, StageFailures, failure_message, resolve_config
from clothgap.config import ConfigError, PRESETS, changed_settings, pairs, shown
from clothgap.errors import UserError
from clothgap.runs import Run, atomic_write_json, clip_id, is_done, storage_error


class DefaultGroup(click.Group):
    """A group that runs its `run` subcommand when no subcommand is named.

    `clothgap sim runs/x` and `clothgap sim sensitivity --out d` both work.
    """

    default_command = "run"

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if not args or (args[0] not in self.commands and args[0] not in ctx.help_option_names):
            args = [self.default_command, *args]
        return super().parse_args(ctx, args)


# ------------------------------------------------------------------ shared options

def _run_options(fn):
    """RUN_DIR, or --preset/--out/--set to start (or resume) a run."""
    fn = click.option("--set", "overrides", multiple=True, metavar="SECTION.KEY=VALUE",
                      help="Override one setting, e.g. --set sim.frames=30 (repeatable; applied after --config).")(fn)
    fn = click.option("--config", "config_file", type=click.Path(path_type=Path), metavar="FILE",
                      help="A TOML file of settings ([sim], [render], ... tables as in config.json, and an "
                           "optional preset = NAME to start from), for studies kept in version control.")(fn)
    fn = click.option("--out", type=click.Path(path_type=Path),
                      help="Run folder to create or resume (default: runs/<preset>).")(fn)
    fn = click.option("--preset", "preset_name", type=str, metavar="NAME",
                      help=f"Start a run from a named preset: {', '.join(PRESETS)}.")(fn)
    fn = click.argument("run_dir", required=False, type=click.Path(path_type=Path))(fn)
    return fn


def _executor_options(fn):
    """Where sim/render/train work runs: --executor, --workers, --address, --gpus-per-worker, --shard-size,
    --cuda-mps."""
    fn = click.option("--cuda-mps", type=click.Choice(["auto", "on", "off"]), default="auto", show_default=True,
                      help="Process workers sharing a GPU run under a private CUDA MPS daemon, so their kernels "
                           "overlap instead of time-slicing the GPU (render 2.2x on H100s). auto: for render "
                           "when nvidia-cuda-mps-control exists; on: for sim and training too (not measured "
                           "there), and an error without MPS; off: never.")(fn)
    fn = click.option("--shard-size", type=click.IntRange(min=1), metavar="N",
                      help="Clip indices per shard (default: an even split over the workers).")(fn)
    fn = click.option("--gpus-per-worker", type=click.FloatRange(min=0), default=0.0, metavar="G",
                      help="GPUs per worker. process: one worker per G GPUs of this host, pinned with "
                           "CUDA_VISIBLE_DEVICES (0.5 = two workers per GPU); ray: num_gpus of each task.")(fn)
    fn = click.option("--address", metavar="ADDR",
                      help="Ray cluster: 'auto' (the cluster this machine belongs to, `ray start --head`) "
                           "or ray://HEAD:10001; default: start a local Ray instance.")(fn)
    fn = click.option("--workers", type=click.IntRange(min=1), metavar="N",
                      help="Parallel workers (process: pool size, default one per CPU or GPU slot; "
                           "ray: most shards in flight, default the cluster's CPUs or GPUs).")(fn)
    fn = click.option("--executor", type=click.Choice(["local", "process", "ray"]), default="local",
                      show_default=True,
                      help="Run the work in this process, a local process pool, or on a Ray cluster "
                           "(sim and render shard by clip index, train by model; finished work is "
                           "skipped on a re-run).")(fn)
    return fn


def _allow_failures_option(fn):
    """--allow-failures: exit 0 even when clips failed or were left out (they are listed all the same)."""
    return click.option("--allow-failures", is_flag=True,
                        help="Exit 0 even when clips failed or were left out (they are still listed in the "
                             "summary). Without it the stage does all it can, then exits 1.")(fn)


def check_failures(stage: str, summary: object, allow_failures: bool) -> None:
    """After a stage did everything else: its failures as one error (or a warning with --allow-failures)."""
    message = failure_message(stage, summary)
    if not message:
        return
    if allow_failures:
        click.echo(f"warning: {message}", err=True)
        return
    raise StageFailures(f"{message}. {FIX_FAILURES}")


def executor_options(executor: str, workers: int | None, address: str | None, gpus_per_worker: float,
                     shard_size: int | None, cuda_mps: str = "auto"):
    from clothgap.executor import ExecutorOptions

    if cuda_mps == "on" and executor == "local":
        executor = "process"        # MPS serves several processes; `--cuda-mps on` alone means a pool
    return ExecutorOptions(executor=executor, workers=workers, address=address, gpus_per_worker=gpus_per_worker,
                           shard_size=shard_size, cuda_mps=cuda_mps).validate()


def measured_clips_beforehand(run: Run, options) -> dict | None:
    """The measured-fabric clips that eval scores (when the run's config asks for them and a model is trained),
    made through ``options``' executor when it is not this process; ``run_eval`` then finds them made (its
    measured.json's generation counts them as skipped). Returns the executor's summary, or None."""
    if run.config.eval.measured_sequences <= 0 or options.whole_here:
        return None
    from eval.trained import finished_models

    if not finished_models(run):
        return None             # run_eval says so, before anything is simulated
    from clothgap.executor import run_stage

    t0 = time.perf_counter()
    summary = run_stage(run, "measured", options)
    _echo_summary("measured clips", summary, time.perf_counter() - t0)
    return summary


def resolve_run(run_dir: Path | None, preset_name: str | None, out: Path | None,
                overrides: tuple[str, ...], config_file: Path | None = None) -> Run:
    """Open an existing run, or create/resume one from a preset, a config file and overrides.

    Settings apply in order: the preset (``--preset``, else ``preset`` in the file, else the run's own config),
    the file's settings, then each ``--set``. A resumed run may take a config that only adds work (see
    ``clothgap.runs.Run.create_or_resume``); what changed is said on stderr.
    """
    if run_dir is not None and out is not None and run_dir != out:
        raise ConfigError(f"give the run folder once: RUN_DIR {run_dir} and --out {out} differ")
    if preset_name is None and not overrides and config_file is None:
        if run_dir is None and out is None:
            raise ConfigError("name a run folder (RUN_DIR) or start one with --preset NAME [--out DIR]")
        return Run.open(run_dir or out)
    cfg = resolve_config(run_dir or out, preset_name, config_file, list(overrides))
    root = run_dir or out or Path("runs") / cfg.name
    before = Run.open(root).config if (root / "config.json").is_file() else None
    run = Run.create_or_resume(root, cfg)
    if before is not None:
        for key, (old, new) in changed_settings(before, run.config).items():
            click.echo(f"{root}: {key} {shown(old)} -> {shown(new)}", err=True)
    return run


def _echo_summary(stage: str, summary: object, seconds: float) -> None:
    click.echo(f"[{stage}] done in {seconds:.1f} s: {json.dumps(summary, default=str)}")


# ------------------------------------------------------------------ the command

@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="clothgap")
def cli() -> None:
    """clothgap: simulate cloth (Warp), render it (Mitsuba 3), learn its material
    (torch CNN+LSTM) and measure the sim-to-real gap."""


# ---- sim
@cli.group(cls=DefaultGroup)
def sim() -> None:
    """Simulate cloth sequences with Warp (`clothgap sim RUN_DIR`), run the
    paper's material analyses (`sensitivity`, `table2`) or the cantilever
    bending test (`cantilever`), or write a clip's frames as meshes (`export`)."""


@sim.command("run")
@_run_options
@_executor_options
@_allow_failures_option
@click.option("--list-motions", is_flag=True, help="List the registered motions and exit.")
def sim_run(run_dir, preset_name, out, overrides, config_file, allow_failures, list_motions, **execution) -> None:
    """Simulate every clip of the run that is not done yet."""
    if list_motions:
        from sim.motions import describe_motions

        click.echo(describe_motions())
        return
    opts = executor_options(**execution)
    run = resolve_run(run_dir, preset_name, out, overrides, config_file)
    from clothgap.executor import run_stage

    t0 = time.perf_counter()
    summary = run_stage(run, "sim", opts)
    _echo_summary("sim", summary, time.perf_counter() - t0)
    check_failures("sim", summary, allow_failures)


@sim.command("sensitivity")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Folder for the CSV and plot.")
@click.option("--device", default="cpu", show_default=True, help="Warp device: cpu, cuda, cuda:N.")
@click.option("--refine", default=1, show_default=True, type=click.IntRange(1, 8),
              help="Subdivide the hanging cloth and the strip this many times per edge (finer, slower).")
def sim_sensitivity(out: Path, device: str, refine: int) -> None:
    """Sensitivity curves (the paper's Figure 3): max stretch D(M) vs 1/p, max curvature C(M) vs 1/k."""
    from sim.analysis import Setup, sensitivity

    click.echo(f"wrote {sensitivity(out, device=device, setup=Setup(refine=refine))}")


@sim.command("table2")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Folder for the CSV and plot.")
@click.option("--device", default="cpu", show_default=True, help="Warp device: cpu, cuda, cuda:N.")
@click.option("--refine", default=1, show_default=True, type=click.IntRange(1, 8),
              help="Subdivide the hanging cloth and the strip this many times per edge (finer, slower).")
def sim_table2(out: Path, device: str, refine: int) -> None:
    """The paper's Table 2: each measured fabric's (p~, k~) from simulated sag and fold, its class,
    and whether that class matches the paper's (CSV + plot)."""
    import csv

    from sim.analysis import Setup, match_counts, table2

    path = table2(out, device=device, setup=Setup(refine=refine))
    counts = match_counts(list(csv.DictReader(path.open())))
    click.echo(f"wrote {path} and {path.with_suffix('.png')}")
    click.echo("classes matching the paper: simulated p {p_match}, k {k_match}; "
               "table ratio p {p_table_match}, k {k_table_match}".format(**counts))


@sim.command("cantilever")
@click.argument("fabric")
@click.option("--level", default=1, show_default=True, type=click.IntRange(1, 7),
              help="Mesh level: the edge length of the sim stage's uniform<LEVEL> mesh (33 mm at 1, halved per level).")
@click.option("--overhang", "overhangs", multiple=True, type=click.FloatRange(0, min_open=True), metavar="CM",
              help="Overhang in cm, rounded to whole edges (repeatable). Default: whole edges around the ASTM "
                   "overhang (twice the model's bending length).")
@click.option("--axis", type=click.Choice(["u", "v"]), default="u", show_default=True,
              help="Material axis along the strip's length.")
@click.option("--device", default="cpu", show_default=True, help="Warp device: cpu, cuda, cuda:N.")
def sim_cantilever(fabric: str, level: int, overhangs: tuple[float, ...], axis: str, device: str) -> None:
    """The cantilever bending test (ASTM D1388 / Peirce) on the solver: FABRIC is a measured fabric's
    name or a class index 0..53. Prints each overhang's chord angle, bending length and flexural
    rigidity, the ASTM 41.5 deg reading, and the model's own value beside them."""
    from sim.cantilever import run_test

    click.echo(run_test(fabric, level, overhangs, axis, device))


@sim.command("export")
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.argument("clip")
@click.option("--setting", help="The clip's setting, e.g. wind-uniform1 (default: the first that holds it).")
@click.option("--frames", metavar="LIST", help="Frames to write, e.g. 0,5,10-19 (default: all).")
@click.option("--format", "fmt", type=click.Choice(["ply", "obj", "glb"]), default="ply", show_default=True,
              help="Mesh format (glb is turned to glTF's +Y up; ply and obj keep the simulation's z up).")
@click.option("--out", type=click.Path(path_type=Path), help="Folder for the files (default: RUN_DIR/export/<setting>/<clip>).")
def sim_export(run_dir: Path, clip: str, setting: str | None, frames: str | None, fmt: str, out: Path | None) -> None:
    """Write a simulated clip's frames as mesh files (one per frame) for Blender or MeshLab. CLIP is a clip
    id (c00003), a clip index (3) or a measured-fabric clip (<fabric>-<n>)."""
    run = Run.open(run_dir)
    name = clip_id(int(clip)) if clip.isdigit() else clip
    known = run.config.sim.settings()
    if setting is not None and setting not in known:
        raise ConfigError(f"unknown setting {setting!r}; this run has {', '.join(known)}")
    folders = [d / name for s in ([setting] if setting else known) for d in (run.sim_dir(s), run.measured_sim_dir(s))]
    folder = next((f for f in folders if is_done(f)), None)
    if folder is None:
        raise ConfigError(f"no finished sim clip {name} in {run.root} ({', '.join(str(f) for f in folders[:2])}"
                          f"{', ...' if len(folders) > 2 else ''}): run `clothgap sim {run.root}` first, or name "
                          "another clip")
    from sim.export import export_clip

    out = out or run.export_dir(folder.parent.name, name)
    files = export_clip(folder, out, fmt, frames)
    click.echo(f"wrote {len(files)} {fmt} file(s) of {folder} to {out}")


# ---- render
@cli.command()
@_run_options
@click.option("--list-variants", is_flag=True, help="List the named render variants and exit.")
@click.option("--test-variant", "test_variants", multiple=True, metavar="NAME",
              help="Also render this variant for testing only (repeatable): no model trains on it, and "
                   "`clothgap eval` tests every model on it, e.g. heldout. Only the split's test clips, through "
                   "the same executor.")
@_executor_options
@_allow_failures_option
def render(run_dir, preset_name, out, overrides, config_file, list_variants, test_variants, allow_failures,
           **execution) -> None:
    """Render the run's simulated clips under each render variant (Mitsuba 3)."""
    if list_variants:
        from render.variants import describe_variants

        click.echo(describe_variants())
        return
    opts = executor_options(**execution)
    run = resolve_run(run_dir, preset_name, out, overrides, config_file)
    for setting in run.config.sim.settings():
        run.require(run.sim_dir(setting), "sim")
    from clothgap.api import render_test_variants
    from clothgap.executor import run_for_test_variants, run_stage

    if test_variants:
        run_for_test_variants(run, test_variants)          # an unknown look refused before any rendering
    t0 = time.perf_counter()
    summary = run_stage(run, "render", opts)
    _echo_summary("render", summary, time.perf_counter() - t0)
    check_failures("render", summary, allow_failures)
    if test_variants:
        t0 = time.perf_counter()
        summary = render_test_variants(run, test_variants, opts)
        _echo_summary("render (test only)", summary, time.perf_counter() - t0)
        check_failures("render", summary, allow_failures)


# ---- train
@cli.command()
@_run_options
@click.option("--model", "model_name", help="Train only this model (see --list-models).")
@click.option("--variant", help="Train only on this render variant.")
@click.option("--setting", help="Train only on this setting, e.g. wind-uniform1.")
@click.option("--seed", "train_seed", type=int, help="Train only this seed.")
@click.option("--parallel", type=click.IntRange(min=1), default=1, show_default=True,
              help="Models trained at a time, each in its own process, spread over the visible GPUs.")
@click.option("--list-models", is_flag=True, help="List the registered models and exit.")
@_executor_options
def train(run_dir, preset_name, out, overrides, config_file, model_name, variant, setting, train_seed,
          parallel, list_models, **execution) -> None:
    """Train the models on the rendered clips (every setting x variant x model x seed
    not done yet, or the one selected by --model/--variant/--setting/--seed).

    --parallel N trains N models at once (a model at the paper preset leaves most of an H100 idle, and
    DDP does not speed one up: one model per process is what scales). --executor process
    --gpus-per-worker G pins one worker per G GPUs; --executor ray runs one task per model on a
    Ray cluster (--address, --gpus-per-worker = each task's GPUs, --workers = tasks in flight)."""
    if list_models:
        from learn.registry import describe_models

        click.echo(describe_models())
        return
    run = resolve_run(run_dir, preset_name, out, overrides, config_file)
    from clothgap.api import train_selected

    t0 = time.perf_counter()
    chosen = (execution["executor"] != "local" or execution["workers"] or execution["gpus_per_worker"]
              or execution["shard_size"] or execution["cuda_mps"] == "on")
    opts = executor_options(**execution) if chosen else None
    done = train_selected(run, [setting] if setting else None, [variant] if variant else None,
                          [model_name] if model_name else None, [train_seed] if train_seed is not None else None,
                          parallel=parallel, options=opts)
    _echo_summary("train", {"trained": [str(p) for p in done]}, time.perf_counter() - t0)


# ---- eval
@cli.group(cls=DefaultGroup)
def eval() -> None:  # noqa: A001 - the subcommand is called eval
    """Evaluate trained models (`clothgap eval RUN_DIR`), on real videos (`eval real`) or on the
    measured fabrics (`eval measured`)."""


@eval.command("run")
@_run_options
@_allow_failures_option
@_executor_options
def eval_run(run_dir, preset_name, out, overrides, config_file, allow_failures, **execution) -> None:
    """Accuracy tables (the paper's Table 3) and the domain-gap matrix for a run.

    Test clips of the split with no prediction (not rendered, unreadable) are listed in
    eval/summary.json ("left_out") and make the command exit 1 unless --allow-failures.
    --executor/--workers/--gpus-per-worker spread the simulation and rendering of the measured-fabric
    set (eval.measured_sequences > 0) as they do the sim and render stages'."""
    run = resolve_run(run_dir, preset_name, out, overrides, config_file)
    run.require(run.train_root, "train")
    from eval.stage import run_eval

    t0 = time.perf_counter()
    opts = executor_options(**execution)
    measured_clips_beforehand(run, opts)
    summary = run_eval(run)
    _echo_summary("eval", summary, time.perf_counter() - t0)
    check_failures("eval", summary, allow_failures)


@eval.command("real")
@click.argument("video_dir", type=click.Path(path_type=Path))
@click.option("--truth", type=click.Path(path_type=Path), required=True,
              help="CSV of measured stiffness/density per video (format: see eval/real.py).")
@click.option("--model", "train_dir", type=click.Path(path_type=Path), required=True,
              help="A trained model's folder (run/train/<setting>/<variant>/<model>/s<seed>).")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Folder for the tables.")
def eval_real(video_dir: Path, truth: Path, train_dir: Path, out: Path) -> None:
    """Correlate predicted material with measured stiffness and density (the paper's Table 4)."""
    for p, what in ((video_dir, "video folder"), (truth, "truth CSV"), (train_dir, "model folder")):
        if not p.exists():
            raise ConfigError(f"{what} {p} does not exist")
    from eval.real import evaluate_real

    click.echo(f"wrote {evaluate_real(video_dir, truth, train_dir, out)}")


@eval.command("measured")
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--model", "train_dirs", type=click.Path(path_type=Path), multiple=True,
              help="Only this trained model's folder (RUN_DIR/train/<setting>/<variant>/<model>/s<seed>, or a "
                   "recipe's RUN_DIR/ablation/<recipe>/<setting>/<variant>/<model>/s<seed>; repeatable). "
                   "Default: every finished model of the run.")
@click.option("--sequences", type=click.IntRange(min=1), metavar="N",
              help="Clips per fabric and setting (default: eval.measured_sequences, else 2).")
@click.option("--variant", metavar="NAME", help="Render variant of the clips (default: eval.measured_variant).")
def eval_measured(run_dir: Path, train_dirs: tuple[Path, ...], sequences: int | None, variant: str | None) -> None:
    """The measured-fabric set: the Wang et al. fabrics simulated with their own tables, rendered in a
    held-out variant, predicted like real videos and compared with the paper's Table 2 classes and
    the fabrics' measured stiffness and density (writes RUN_DIR/eval/measured.{csv,md,json})."""
    run = Run.open(run_dir)
    if not train_dirs:
        run.require(run.train_root, "train")
    from eval.measured import model_from_dir, run_measured

    models = [model_from_dir(run, d) for d in train_dirs] or None
    t0 = time.perf_counter()
    _echo_summary("eval measured", run_measured(run, models=models, sequences=sequences, variant=variant),
                  time.perf_counter() - t0)


@eval.command("learnability")
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--setting", "settings", multiple=True, metavar="NAME",
              help="Only this simulated setting, e.g. wind-uniform1 (repeatable). Default: every simulated one.")
@click.option("--clip-len", type=click.IntRange(min=2), default=10, show_default=True,
              help="Frames per window.")
@click.option("--stride", type=click.IntRange(min=1), metavar="N",
              help="Start-frame step between windows (default: --clip-len, so windows share no frame).")
@click.option("--pixels", "variant", metavar="VARIANT",
              help="Probe the rendered frames of this variant (16 px window summaries) instead of the geometry: "
                   "how well a clip is recognised by its look (texture, background, light) alone.")
@click.option("--measured", "measured", type=click.IntRange(min=1), metavar="N",
              help="Instead: simulate N clips of each Table 2 fabric with its own tables (finished ones kept) and "
                   "read them with classifiers trained on all the setting's clips: the class the simulated geometry "
                   "gives each measured fabric, beside its Table 2 class (eval/learnability-measured.{json,md}).")
def eval_learnability(run_dir: Path, settings: tuple[str, ...], clip_len: int, stride: int | None,
                      variant: str | None, measured: int | None) -> None:
    """How well the simulated 3D sequences alone tell the material, split by sequence and by the
    paper's sub-sequence protocol (writes RUN_DIR/eval/learnability.{json,md}; needs only `clothgap sim`);
    with --measured, where they put the measured fabrics (eval/learnability-measured.{json,md})."""
    if measured and variant:
        raise ConfigError("--measured probes the geometry: it does not take --pixels")
    run = Run.open(run_dir)
    run.require(run.root / ("render" if variant else "sim"), "render" if variant else "sim")
    known = run.config.sim.settings()
    unknown = [s for s in settings if s not in known]
    if unknown:
        raise ConfigError(f"unknown setting(s) {', '.join(unknown)}; this run simulates {', '.join(known)}")
    if stride is not None and stride < clip_len:
        raise ConfigError(f"--stride {stride} < --clip-len {clip_len}: overlapping windows would share frames "
                          "across train and test in the split by sub-sequence")
    from eval.learnability import run_probe, run_probe_measured

    t0 = time.perf_counter()
    options = {"clip_len": clip_len, "stride": stride or clip_len}
    summary = (run_probe_measured(run, measured, list(settings) or None, **options) if measured
               else run_probe(run, list(settings) or None, pixels=variant, **options))
    _echo_summary("eval learnability", summary, time.perf_counter() - t0)


@eval.command("ablation")
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--recipe", "recipes", multiple=True, required=True, metavar="LEVER[+LEVER...]",
              help="A training recipe: levers joined by '+', each a named lever (baseline, augment, camera, best, "
                   "motion, geometry, bottleneck, factored, smooth, last, narrow, decay, graphs, eager) or a train "
                   "setting key=value, e.g. augment+geometry+aux_geometry=0.3 (repeatable; the first is the "
                   "reference).")
@click.option("--setting", help="The simulated setting (default: the run's first).")
@click.option("--variant", help="The render variant trained and tested on (default: the run's first).")
@click.option("--model", "models", multiple=True, metavar="NAME", help="Models to train (default: train.models).")
@click.option("--seed", "seeds", multiple=True, type=int, help="Training seeds (default: train.seeds).")
@click.option("--name", metavar="NAME", help="Write RUN_DIR/eval/NAME.{json,md} (default: ablation-<setting>-<variant>).")
@click.option("--parallel", type=click.IntRange(min=1), default=1, show_default=True,
              help="Models trained at a time, each in its own process, spread over the visible GPUs.")
@click.option("--test-variant", "test_variants", multiple=True, metavar="VARIANT",
              help="Also score every recipe on the same test clips rendered in this look (e.g. heldout, "
                   "rendered with `clothgap render RUN --test-variant heldout`; repeatable).")
def eval_ablation(run_dir: Path, recipes: tuple[str, ...], setting: str | None, variant: str | None,
                  models: tuple[str, ...], seeds: tuple[int, ...], name: str | None, parallel: int,
                  test_variants: tuple[str, ...]) -> None:
    """Train several recipes on the same data and score them on the same test clips, with intervals and
    paired differences (trains into RUN_DIR/ablation/<recipe>/, writes RUN_DIR/eval/ablation-*.{json,md})."""
    run = Run.open(run_dir)
    run.require(run.render_root, "render")
    known = pairs(run.config)
    setting = setting or known[0][0]
    variant = variant or next((v for s, v in known if s == setting), known[0][1])
    if (setting, variant) not in known:
        raise ConfigError(f"--setting {setting} --variant {variant} is not a pair this run renders: "
                          f"{', '.join(f'{s}/{v}' for s, v in known)}")
    from eval.ablation import recipe_config, require_test_clips, run_ablation

    for recipe in recipes:
        recipe_config(run.config, recipe)   # every recipe is checked before any training
    require_test_clips(run, setting)        # and that the split has test clips to score them on
    t0 = time.perf_counter()
    if name is not None and (not name or "/" in name):
        raise ConfigError(f"--name {name!r}: must be a plain file name")
    if parallel > 1:
        from clothgap.executor import run_train_parallel
        from eval.ablation import ablation_grid

        run_train_parallel(run, ablation_grid(run, setting, variant, list(recipes), list(models) or None,
                                              list(seeds) or None), parallel)
    _echo_summary("eval ablation", run_ablation(run, setting, variant, list(recipes), list(models) or None,
                                                list(seeds) or None, name=name, test_variants=list(test_variants)),
                  time.perf_counter() - t0)


# ---- clone
@cli.command()
@click.argument("video", type=click.Path(path_type=Path))
@click.option("--run", "run_dir", type=click.Path(path_type=Path), required=True,
              help="Run folder holding a trained model (train/<setting>/<variant>/<model>/s<seed>).")
@click.option("--model", "model_name", default="lrcn", show_default=True, help="Which trained model predicts.")
@click.option("--setting", help="The model's training setting (default: the first trained one).")
@click.option("--variant", help="The model's render variant (default: the first trained one).")
@click.option("--seed", "train_seed", type=int, help="The model's training seed (default: the first trained one).")
@click.option("--garment", type=click.Choice(["skirt"]), default="skirt", show_default=True)
@click.option("--motion", type=click.Choice(["twirl", "walk"]), default="twirl", show_default=True,
              help="How the skirt's waist moves.")
@click.option("--frames", type=click.IntRange(min=1), default=50, show_default=True,
              help="Frames of the clone (at the sim's fps).")
@click.option("--render-variant", help="Render variant of the skirt (default: the model's variant).")
@click.option("--resolution", type=click.IntRange(min=1), default=128, show_default=True,
              help="Pixels per panel side.")
@click.option("--spp", type=click.IntRange(min=1), default=16, show_default=True, help="Samples per pixel.")
@click.option("--backend", help="Mitsuba backend: auto, cuda_ad_rgb, llvm_ad_rgb, scalar_rgb (default: auto).")
@click.option("--no-compare", is_flag=True, help="Simulate only the clone, not a softer and a stiffer class.")
@click.option("--out", type=click.Path(path_type=Path), help="Output folder (default: RUN_DIR/clone/<video>).")
def clone(video, run_dir, model_name, setting, variant, train_seed, garment, motion, frames, render_variant,
          resolution, spp, backend, no_compare, out) -> None:
    """Material cloning (the paper's Figure 9): predict VIDEO's cloth class with a model trained in the run,
    simulate a skirt of that material (beside a softer and a stiffer one) and render it next to the input."""
    if not video.exists():
        raise ConfigError(f"input video {video} does not exist")
    from eval.clone import CloneOptions, clone_video

    options = CloneOptions(model=model_name, setting=setting, variant=variant, seed=train_seed, garment=garment,
                           motion=motion, frames=frames, render_variant=render_variant, resolution=resolution,
                           spp=spp, backend=backend, compare=not no_compare)
    path = clone_video(video, run_dir, options, out=out)
    click.echo(f"wrote {path}")


# ---- report
@cli.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
def report(run_dir: Path) -> None:
    """Write one self-contained HTML report of a run."""
    run = Run.open(run_dir)
    run.require(run.eval_dir, "eval")
    from eval.report import write_report

    click.echo(f"wrote {write_report(run)}")


# ---- pipeline
@cli.command()
@_run_options
@_executor_options
@_allow_failures_option
@click.option("--train-parallel", type=click.IntRange(min=1), default=1, show_default=True,
              help="Models trained at a time, each in its own process, spread over the visible GPUs.")
def pipeline(run_dir, preset_name, out, overrides, config_file, allow_failures, train_parallel,
             **execution) -> None:
    """Run sim, render, train, eval and report in turn (each skips what is done).

    --executor/--workers/--address/--gpus-per-worker spread sim and render; --train-parallel N
    trains N models at once over the visible GPUs (one model over several GPUs: torchrun)."""
    opts = executor_options(**execution)
    run = resolve_run(run_dir, preset_name, out, overrides, config_file)
    click.echo(f"run folder: {run.root}  (config: {run.root / 'config.json'})")
    timings: dict[str, float] = {}
    summaries: dict[str, object] = {}

    def stage(name: str, fn) -> None:
        click.echo(f"== {name}")
        t0 = time.perf_counter()
        summaries[name] = fn(run)
        timings[name] = round(time.perf_counter() - t0, 2)
        _echo_summary(name, summaries[name], timings[name])

    from clothgap.executor import run_stage

    stage("sim", lambda r: run_stage(r, "sim", opts))
    stage("render", lambda r: run_stage(r, "render", opts))
    from clothgap.api import train_all

    from clothgap.executor import ExecutorOptions

    # --cuda-mps on serves training's pool too (its models share the GPUs round robin)
    train_opts = ExecutorOptions("process", workers=train_parallel, cuda_mps="on") if opts.cuda_mps == "on" else None
    stage("train", lambda r: train_all(r, parallel=train_parallel, options=train_opts))
    from eval.stage import run_eval

    def evaluate(r: Run) -> dict:
        made = measured_clips_beforehand(r, opts)          # through the executor, as sim and render
        if made is not None:
            summaries["measured clips"] = made
        return run_eval(r)

    stage("eval", evaluate)
    from eval.report import write_report

    stage("report", lambda r: str(write_report(r)))
    atomic_write_json(run.root / "pipeline.json", {"seconds": timings, "summaries": summaries})
    click.echo(f"report: {summaries['report']}")
    # Every stage ran on what the one before produced; now say what failed or was left out on the way.
    failures = [m for m in (failure_message(name, summaries[name]) for name in ("sim", "render", "eval")) if m]
    if failures and allow_failures:
        click.echo(f"warning: {'; '.join(failures)}", err=True)
    elif failures:
        raise StageFailures(f"{'; '.join(failures)}. {FIX_FAILURES}")


def _shard_error() -> type[BaseException] | tuple[()]:
    """``clothgap.executor.ShardError`` when the executor was imported (only then can it be raised)."""
    executor = sys.modules.get("clothgap.executor")
    return executor.ShardError if executor is not None else ()


def main() -> None:
    """The ``clothgap`` entry point: bad input is one ``error: ...`` line on stderr and exit status 2.

    User errors are the project's ``clothgap.errors.UserError`` types: ConfigError (settings, presets,
    overrides, run folders), render.variants.VariantError, render.backend.BackendError,
    eval.real.VideoError, InputError / MissingInputError (files and folders the user named) and
    StorageError, as is any OSError of a full, read-only or forbidden disk (it names the path). A failed
    shard (clothgap.executor.ShardError, whose message carries the worker's error) exits 1, as does a stage
    whose clips failed or were left out (StageFailures; --allow-failures makes that exit 0). Anything
    else is a bug and keeps its traceback.
    """
    try:
        cli(standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as e:
        e.show()
        sys.exit(e.exit_code)
    except UserError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    except StageFailures as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(1)
    except _shard_error() as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(1)
    except OSError as e:
        # A full, read-only or forbidden disk is the user's to fix: one line naming the path.
        err = storage_error(e)
        if err is None:
            raise
        click.echo(f"error: {err}", err=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
