"""Where generation work runs: in this process, a local process pool, or a Ray cluster.

The sim and render stages are cut into shards of clip indices (``shard``), as is
the generation of the measured-fabric set (``measured``: its (setting, fabric,
sequence) units, ``eval.measured.generation_units``). A shard is handled by a
plain, picklable function ``fn(run_root: str, indices: list[int]) -> dict``
(``sim_shard``, ``render_shard``, ``measured_shard``, or a ``functools.partial``
of one: the test-only looks' ``render_shard``) that calls the stage
restricted to those indices; the stage skips finished clips and writes every
clip folder with its ``DONE`` marker last. That makes every executor idempotent
and resumable: a worker killed mid-shard loses only the clip it was writing, a
retried or re-run shard skips what is finished and redoes what is not, and
disjoint shards never write the same clip, so no clip is done twice. A shard
covers its indices under every setting (and render variant), so shards never
touch the same folder.

The stages write nothing at stage level: each shard returns its summary, and
the driver (``run_stage``) merges them once all shards are finished with the
stage's own ``merge_shard_summaries`` (``sim.stage``, ``render.stage``, ``eval.measured``), so
this module knows no stage's summary.

    local     in this process (default; what CPU runs and tests use)
    process   a local pool of spawned processes (Warp, Mitsuba and torch are not
              fork-safe); with ``gpus_per_worker`` one worker per GPU (or per
              share of one), pinned with CUDA_VISIBLE_DEVICES; render workers that
              share a GPU run under a private CUDA MPS daemon (``cuda_mps``; sim and
              training with ``on``); a pool broken by a killed worker is rebuilt and
              the unfinished shards are run again
    ray       tasks on a Ray cluster (``address``: "auto", "ray://host:10001",
              or None for a fresh local instance); ``gpus_per_worker`` is each
              task's ``num_gpus``; a task whose worker dies is retried

On a cluster, every node needs the project installed (``pip install
clothgap[ray]``, same version) and the run folder on a filesystem all nodes
share, at the same path.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# clothgap.config also registers the study config that a worker's Run.open reads (workers import this module).
from clothgap.config import ConfigError, validate
from clothgap.cuda_mps import MODES as CUDA_MPS_MODES
from clothgap.cuda_mps import cuda_mps
from clothgap.parallel import HOST_PROCESSES_ENV, host_processes, share_of_host
from clothgap.runs import Run

EXECUTORS = ("local", "process", "ray")
MPS_AUTO_STAGES = ("render",)       # measured faster under MPS (the stage 2.2x); sim, the measured set and training not
STAGES = ("sim", "render", "measured")
ShardFn = Callable[[str, list[int]], dict]
RAY_MISSING = "the ray executor needs Ray: pip install 'clothgap[ray]' (or pip install 'ray[default]')"


class ShardError(RuntimeError):
    """A shard failed for good; finished clips are kept and a re-run redoes the rest."""


@dataclass(frozen=True)
class ExecutorOptions:
    """How generation is spread: the CLI's --executor, --workers, --address, --gpus-per-worker, --shard-size."""

    executor: str = "local"
    workers: int | None = None          # process: pool size; ray: most tasks in flight (and CPUs of a local instance)
    address: str | None = None          # ray only: "auto", "ray://host:10001", "host:6379"; None = start a local instance
    gpus_per_worker: float = 0.0        # process: GPUs pinned per worker; ray: num_gpus per task
    shard_size: int | None = None       # clip indices per shard; None = an even split over the workers
    retries: int = 2                    # times a shard whose worker died is run again (process, ray)
    progress: bool = True
    # process workers sharing a GPU: "auto" = under an MPS daemon for MPS_AUTO_STAGES; "on" = for every stage
    # and training, and an error without MPS
    cuda_mps: str = "auto"

    @property
    def whole_here(self) -> bool:
        """Whether a shardable stage runs whole in this process (no executor to spread it)."""
        return self.executor == "local" and self.shard_size is None

    def validate(self) -> "ExecutorOptions":
        if self.executor not in EXECUTORS:
            raise ConfigError(f"unknown executor {self.executor!r}; known: {', '.join(EXECUTORS)}")
        if self.workers is not None and self.workers < 1:
            raise ConfigError(f"--workers must be at least 1, got {self.workers}")
        if self.shard_size is not None and self.shard_size < 1:
            raise ConfigError(f"--shard-size must be at least 1, got {self.shard_size}")
        if self.gpus_per_worker < 0:
            raise ConfigError(f"--gpus-per-worker must not be negative, got {self.gpus_per_worker}")
        if self.address is not None and self.executor != "ray":
            raise ConfigError("--address names a Ray cluster: use it with --executor ray")
        if self.executor == "local" and (self.workers not in (None, 1) or self.gpus_per_worker):
            raise ConfigError("--workers and --gpus-per-worker need --executor process or ray")
        if self.cuda_mps not in CUDA_MPS_MODES:
            raise ConfigError(f"--cuda-mps must be one of {', '.join(CUDA_MPS_MODES)}, got {self.cuda_mps!r}")
        if self.cuda_mps == "on" and self.executor != "process":
            raise ConfigError("--cuda-mps on serves a local process pool: use it with --executor process")
        return self


# ---------------------------------------------------------------- shards

def shard(indices: Sequence[int], shard_size: int) -> list[list[int]]:
    """Consecutive shards of at most ``shard_size`` clip indices."""
    if shard_size < 1:
        raise ConfigError(f"shard size must be at least 1, got {shard_size}")
    items = list(indices)
    return [items[i:i + shard_size] for i in range(0, len(items), shard_size)]


def default_shard_size(num_indices: int, workers: int) -> int:
    """An even split: one shard per worker (big shards keep the GPU solver's batches full)."""
    return max(1, math.ceil(num_indices / max(1, workers)))


def sim_shard(run_root: str, indices: list[int]) -> dict:
    """Simulate the unfinished clips among ``indices`` under every setting of the run."""
    from sim.stage import run_sim

    return run_sim(Run.open(run_root, check=False), progress=False, indices=indices)   # validated by the driver


def render_shard(run_root: str, indices: list[int], test_variants: tuple[str, ...] = ()) -> dict:
    """Render the unfinished clips among ``indices`` under every variant and setting of the run, or under
    ``test_variants`` alone (``run_for_test_variants``)."""
    from render.stage import run_render

    run = Run.open(run_root, check=False)
    return run_render(run_for_test_variants(run, test_variants) if test_variants else run, progress=False,
                      indices=indices)


def run_for_test_variants(run: Run, variants: Iterable[str]) -> Run:
    """The run seen with only ``variants`` as its render variants, for rendering looks no model trains on
    (``clothgap eval`` tests every model on every rendered variant); an unknown name is refused here. Its
    config is never saved: the run's own variants stay its training set."""
    render = dataclasses.replace(run.config.render, variants=tuple(dict.fromkeys(variants)), variant_settings=())
    return Run(run.root, validate(dataclasses.replace(run.config, render=render)))


def measured_shard(run_root: str, indices: list[int]) -> dict:
    """Simulate and render the unfinished measured-fabric clips among ``indices`` (``eval.measured.generation_units``:
    (setting, fabric, sequence) in the run's config)."""
    from eval.measured import make_measured_clips

    return make_measured_clips(Run.open(run_root, check=False), progress=False, indices=indices)


SHARD_FNS: dict[str, ShardFn] = {"sim": sim_shard, "render": render_shard, "measured": measured_shard}


def _stage_functions(stage: str) -> tuple[Callable[..., dict], Callable[[list[dict]], dict]]:
    """A shardable stage's ``run(run, progress=, indices=)`` and the function that merges its shards' summaries
    (the stage knows its summary); imported when used, since the stages load Warp and Mitsuba."""
    if stage == "sim":
        from sim.stage import merge_shard_summaries, run_sim

        return run_sim, merge_shard_summaries
    if stage == "measured":
        from eval.measured import make_measured_clips, merge_shard_summaries

        return make_measured_clips, merge_shard_summaries
    from render.stage import merge_shard_summaries, run_render

    return run_render, merge_shard_summaries


def stage_units(run: Run, stage: str) -> int:
    """How many units a shardable stage's indices number: the run's clips, or for ``measured`` its measured-fabric
    clips under every setting."""
    if stage == "measured":
        from eval.measured import generation_units

        return len(generation_units(run))
    return run.config.sim.num_clips()


def run_stage(run: Run, stage: str, options: ExecutorOptions = ExecutorOptions(), *,
              indices: Sequence[int] | None = None, test_variants: Sequence[str] = ()) -> dict:
    """Run the sim or render stage of ``run``, or the generation of its measured-fabric set (``measured``), through
    an executor; returns the merged summary. ``indices``: only these units (clips; default all).
    ``test_variants`` (render only): render these looks instead of the run's (``run_for_test_variants``), in
    the workers too.

    With the default options this is the plain ``run_sim(run)`` / ``run_render(run)`` / ``make_measured_clips(run)``.
    """
    if stage not in STAGES:
        raise ConfigError(f"stage {stage!r} cannot be sharded; shardable: {', '.join(STAGES)}")
    if test_variants and stage != "render":
        raise ConfigError(f"test variants are rendered by the render stage, not {stage!r}")
    options = options.validate()
    run_whole, merge = _stage_functions(stage)
    shard_fn = SHARD_FNS[stage]
    if test_variants:
        run = run_for_test_variants(run, test_variants)
        shard_fn = functools.partial(render_shard, test_variants=run.config.render.variants)
    if options.cuda_mps == "on" and not options.gpus_per_worker:
        raise ConfigError(f"--cuda-mps on: give the {stage} workers their share of a GPU with --gpus-per-worker "
                          "(0.25 = four workers a GPU)")
    if options.whole_here:
        return run_whole(run, progress=options.progress, indices=indices)
    # The workers open the run unchecked (Run.open(check=False)): a bad setting (e.g. an unknown render variant)
    # is a config error here, not a failed shard later.
    validate(run.config)
    start = time.perf_counter()
    indices = list(range(stage_units(run, stage))) if indices is None else list(indices)
    mps_state = None
    with ray_session(options) as ray, contextlib.ExitStack() as stack:
        env = None
        if ray is not None:
            workers = options.workers or ray_parallelism(ray, options)
            slots = None
        elif options.executor == "process" and options.gpus_per_worker:
            visible = visible_gpus()
            slots = gpu_slots(visible, options.gpus_per_worker, options.workers)
            workers = len(slots)
            mps = stack.enter_context(cuda_mps(slots, visible, mps_mode(options, stage), say=_say))
            slots, env, mps_state = mps.slots, mps.env, mps.state
        else:
            slots = None
            workers = options.workers or (os.cpu_count() or 1 if options.executor == "process" else 1)
        shards = shard(indices, options.shard_size or default_shard_size(len(indices), workers))
        parts = run_shards(shard_fn, str(run.root.resolve()), shards, options=options,
                           label=f"{stage} (test only)" if test_variants else stage,
                           gpu_slots=slots, worker_env=env)
    summary = merge(parts)
    summary["seconds"] = round(time.perf_counter() - start, 3)
    summary["executor"] = {"name": options.executor, "workers": workers, "shards": len(shards),
                           **({"address": options.address} if options.address else {}),
                           **({"gpus_per_worker": options.gpus_per_worker} if options.gpus_per_worker else {}),
                           **({"cuda_mps": mps_state} if mps_state else {})}
    return summary


def mps_mode(options: ExecutorOptions | None, stage: str) -> str:
    """The ``cuda_mps`` mode a stage's (or training's, ``"train"``) process workers get: ``auto`` serves only the
    stages measured faster under MPS."""
    if options is None or (options.cuda_mps == "auto" and stage not in MPS_AUTO_STAGES):
        return "off"
    return options.cuda_mps


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


# ---------------------------------------------------------------- training several models at once

TrainEntry = tuple   # (setting, variant, model, seed), or with a fifth item: an eval.ablation recipe


def train_jobs(grid: Sequence[TrainEntry], shared_regressor: Callable[[TrainEntry], str] = lambda entry: "",
               trained: Callable[[TrainEntry], bool] | None = None) -> list[list[TrainEntry]]:
    """The training grid cut into jobs that may run at once: a model and the untrained model it needs (base1, then
    base2, which freezes base1's CNN, of the same setting, variant, seed and recipe; with
    ``train.shared_regressor``, given per entry by ``shared_regressor``, that model and every other) form one job,
    in grid order, so that no two jobs train the model they need; every other entry is a job of its own.
    ``trained`` says whether an entry is trained already (default: whether it is outside ``grid``); a needed
    model that is neither trained nor in ``grid`` is trained inside the job of the models that need it."""
    from learn.registry import model_needs

    present = {tuple(entry) for entry in grid}
    is_trained = trained or (lambda entry: entry not in present)

    def root(entry: tuple) -> str:
        setting, variant, model, seed, *recipe = entry
        shared = shared_regressor(entry)
        while (needs := model_needs(model, shared)) and not is_trained((setting, variant, needs, seed, *recipe)):
            model = needs
        return model

    jobs: dict[tuple, list] = {}
    for entry in map(tuple, grid):
        setting, variant, model, seed, *recipe = entry
        jobs.setdefault((setting, variant, seed, root(entry), *recipe), []).append(entry)
    return list(jobs.values())


def train_waves(jobs: list[list[TrainEntry]], shared_regressor: Callable[[TrainEntry], str] = lambda entry: ""
                ) -> list[list[list[TrainEntry]]]:
    """``train_jobs``'s jobs in the waves that run one after another: first every job with the readers of a shared
    regressor trained in it taken out, then those readers, each a job of its own. A reader trains in a minute or
    two where its regressor takes several, so once the regressors are trained their readers run side by side
    instead of one after another behind each regressor. A wave left empty is dropped. The second wave starts when
    the whole first has finished (every regressor of the call, and any other model in it), and a failure in the
    first stops the call before it, as a failing job stops the queued ones."""
    from learn.registry import reads_shared_regressor

    first: list[list[TrainEntry]] = []
    readers: list[list[TrainEntry]] = []
    for job in jobs:
        in_job = {tuple(entry) for entry in job}
        kept = []
        for entry in job:
            setting, variant, model, seed, *recipe = entry
            shared = shared_regressor(entry)
            if reads_shared_regressor(shared, model) and (setting, variant, shared, seed, *recipe) in in_job:
                readers.append([entry])
            else:
                kept.append(entry)
        first.append(kept)
    return [wave for wave in (first, readers) if wave]


def _entry_config(run: Run, entry: TrainEntry):
    """The train settings and train root of an entry: the run's, or its recipe's (``eval.ablation``)."""
    if len(entry) < 5:
        return run.config.train, None
    from eval.ablation import recipe_config, recipe_root

    return recipe_config(run.config, entry[4]), recipe_root(run, entry[4])


def describe_models(job: list[TrainEntry]) -> str:
    return "models " + ", ".join("/".join(map(str, entry)) for entry in job)


def train_shard(run_root: str, entries: list[TrainEntry]) -> dict:
    """Train ``entries`` in turn (one job of ``train_jobs``); torch uses this worker's share of the CPUs."""
    import torch

    from learn.train import train_one

    torch.set_num_threads(host_processes())
    run = Run.open(run_root, check=False)
    trained = []
    for entry in entries:
        config, root = _entry_config(run, entry)
        trained.append(str(train_one(run, *entry[:4], progress=False, config=config, root=root)))
    return {"trained": trained}


def run_train_parallel(run: Run, grid: Sequence[TrainEntry], parallel: int = 1, progress: bool = True,
                       options: ExecutorOptions | None = None) -> list[Path]:
    """Train ``grid`` several models at a time. By default ``parallel`` spawned processes, spread over the
    visible GPUs on CUDA (CUDA_VISIBLE_DEVICES, round robin): a model of this size leaves most of an H100
    idle and gains nothing from DDP (benchmarks/results/train_scaling-*), so a study's many models run side
    by side instead. ``options`` runs the jobs through another executor instead: ``process`` with
    ``gpus_per_worker`` (one worker per GPU slot, as generation does), or ``ray`` (a task per job, each with
    ``gpus_per_worker`` GPUs, ``workers`` in flight; the run folder on storage every node shares).
    An entry (setting, variant, model, seed) may carry a fifth item, an ``eval.ablation`` recipe, whose
    settings and folder it then trains with. Finished models are skipped; a killed run resumes each model
    from its last epoch. Returns the training folders in grid order."""
    from learn.stage import prepare_shared_inputs
    from learn.train import resolve_device, train_folder

    if parallel < 1:
        raise ConfigError(f"--parallel must be at least 1, got {parallel}")
    if options is not None and options.shard_size is not None:
        raise ConfigError("--shard-size cuts sim and render into clip shards; training runs one job per model")
    grid = [tuple(e) for e in grid]
    settings = {e: _entry_config(run, e) for e in grid}                 # (train settings, train root)
    folders = [train_folder(run, *e[:4], root=settings[e][1]) for e in grid]
    # once each: a grid may name a model twice (a seed or recipe given twice), and two jobs must never train one folder
    pending = list(dict.fromkeys(e for e, folder in zip(grid, folders) if not (folder / "DONE").is_file()))
    if pending:
        configs = [settings[e][0] for e in pending]
        started = time.perf_counter()
        parts = prepare_shared_inputs(run, [e[:4] for e in pending], progress, configs=configs)
        # (a study's twelve caches and eight settings' lattices: its time before any model starts)
        _say(f"train: splits, frame caches and lattices ready in {time.perf_counter() - started:.1f} s ("
             + ", ".join(f"{name} {s:.1f} s" for name, s in parts.items()) + ")")
        slots = gpus = None
        mode = mps_mode(options, "train")       # before the default path replaces the options
        if options is None or (options.executor == "process" and not options.gpus_per_worker):
            workers = (options and options.workers) or parallel
            devices = {resolve_device(c.device).type for c in configs}
            gpus = visible_gpus() if "cuda" in devices else []
            slots = [gpus[i % len(gpus)] for i in range(workers)] if gpus else None
            options = ExecutorOptions("process", workers=workers)
        elif options.executor == "process":
            gpus = visible_gpus()
            slots = gpu_slots(gpus, options.gpus_per_worker, options.workers)
        def trained(entry: TrainEntry) -> bool:
            return (train_folder(run, *entry[:4], root=_entry_config(run, entry)[1]) / "DONE").is_file()

        shared_of = lambda e: settings[e][0].shared_regressor   # noqa: E731
        waves = train_waves(train_jobs(pending, shared_of, trained), shared_of)
        # (`on` without GPUs is refused by cuda_mps: its workers would have none to share)
        with cuda_mps(slots, gpus or [], mode, say=_say) as mps:
            for n, wave in enumerate(waves, 1):
                started = time.perf_counter()
                run_shards(train_shard, str(run.root.resolve()), wave,
                           options=dataclasses.replace(options, progress=progress), label="train",
                           gpu_slots=mps.slots, describe=describe_models, worker_env=mps.env)
                # (a wave's models start together: its first finishes after their start-up and its own epochs)
                _say(f"train: wave {n} of {len(waves)}, {sum(map(len, wave))} model(s) in {len(wave)} job(s), "
                     f"{time.perf_counter() - started:.1f} s")
    return folders


def merge_summaries(stage: str, parts: list[dict]) -> dict:
    """One stage summary from the shards' summaries: the stage's own ``merge_shard_summaries``."""
    return _stage_functions(stage)[1](parts)


# ---------------------------------------------------------------- GPUs of this host

def visible_gpus() -> list[str]:
    """This host's GPUs as CUDA_VISIBLE_DEVICES entries: that variable when set, else nvidia-smi's list."""
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        return [g.strip() for g in env.split(",") if g.strip() and g.strip() != "-1"]
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=index", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=30, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return [line.strip() for line in out.splitlines() if line.strip()]


def gpu_slots(gpus: Sequence[str], gpus_per_worker: float, workers: int | None = None) -> list[str]:
    """CUDA_VISIBLE_DEVICES of each process worker: ``gpus_per_worker`` GPUs each (or a 1/n share of one).

    ``gpu_slots(["0", "1"], 1)`` -> ``["0", "1"]``; ``(["0", "1", "2", "3"], 2)`` -> ``["0,1", "2,3"]``;
    ``(["0"], 0.5)`` -> ``["0", "0"]`` (two workers share GPU 0).
    """
    if not gpus:
        raise ConfigError(f"--gpus-per-worker {gpus_per_worker:g} but no GPU is visible "
                          "(nvidia-smi finds none, or CUDA_VISIBLE_DEVICES is empty)")
    if gpus_per_worker >= 1:
        if gpus_per_worker != int(gpus_per_worker):
            raise ConfigError(f"--gpus-per-worker {gpus_per_worker:g}: give a whole number of GPUs, "
                              "or a fraction below 1 (0.5 = two workers per GPU)")
        k = int(gpus_per_worker)
        slots = [",".join(gpus[i:i + k]) for i in range(0, len(gpus) - k + 1, k)]
    else:
        per_gpu = max(1, round(1 / gpus_per_worker))
        slots = [g for g in gpus for _ in range(per_gpu)]
    if not slots:
        raise ConfigError(f"--gpus-per-worker {gpus_per_worker:g} but only {len(gpus)} GPU(s) are visible")
    if workers is not None:
        if workers > len(slots):
            raise ConfigError(f"--workers {workers} with --gpus-per-worker {gpus_per_worker:g} needs "
                              f"{workers * gpus_per_worker:g} GPUs; {len(gpus)} are visible")
        slots = slots[:workers]
    return slots


# ---------------------------------------------------------------- running shards

def describe_clips(shard: list[int]) -> str:
    return f"clips {shard[0]}..{shard[-1]}" if shard else "no clips"


def run_shards(fn: ShardFn, run_root: str, shards: list[list[int]], *,
               options: ExecutorOptions = ExecutorOptions(), label: str = "shards",
               gpu_slots: list[str] | None = None, describe: Callable[[list], str] = describe_clips,
               worker_env: dict[str, str] | None = None) -> list[dict]:
    """Run ``fn(run_root, shard)`` for every shard; returns the shards' summaries in shard order.
    ``describe`` names a shard in errors (a shard of clip indices by default); ``worker_env`` is set in each
    process worker before it starts (an MPS daemon's pipe folder)."""
    options = options.validate()
    if not shards:
        return []
    if options.executor == "local":
        with _progress(len(shards), options.progress and len(shards) > 1, label) as bar:
            results = []
            for s in shards:
                results.append(fn(run_root, s))
                bar.update()
            return results
    if options.executor == "process":
        return _run_process_pool(fn, run_root, shards, options, label, gpu_slots, describe, worker_env or {})
    return _run_ray(fn, run_root, shards, options, label, describe)


def _progress(total: int, enabled: bool, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, disable=not enabled, desc=desc, unit="shard")


def _init_worker(slots, host_share: int, env: dict[str, str]) -> None:
    """Pool initializer: this worker's share of the host's CPUs for its own pools, ``env`` (an MPS daemon's
    pipe folder), and (with GPU slots) one slot's GPUs, all set before anything initialises CUDA."""
    os.environ.update(env)
    os.environ[HOST_PROCESSES_ENV] = str(host_share)
    if slots is not None:
        os.environ["CUDA_VISIBLE_DEVICES"] = slots.get()


def _run_process_pool(fn, run_root, shards, options, label, slots, describe, env) -> list[dict]:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    ctx = mp.get_context("spawn")
    workers = len(slots) if slots else min(len(shards), options.workers or os.cpu_count() or 1)
    results: list[Any] = [None] * len(shards)
    pending = list(range(len(shards)))
    with _progress(len(shards), options.progress, f"{label} (process x{workers})") as bar:
        for attempt in range(options.retries + 1):
            queue = None
            if slots:
                queue = ctx.Queue()
                for s in slots:
                    queue.put(s)
            init = {"initializer": _init_worker, "initargs": (queue, share_of_host(workers), env)}
            broken: list[int] = []
            with ProcessPoolExecutor(max_workers=min(workers, len(pending)), mp_context=ctx, **init) as pool:
                futures = {pool.submit(fn, run_root, shards[i]): i for i in pending}
                try:
                    for fut in as_completed(futures):
                        i = futures[fut]
                        try:
                            results[i] = fut.result()
                        except BrokenProcessPool:
                            broken.append(i)        # a worker died (killed, out of memory): run it again
                            continue
                        except Exception as e:
                            pool.shutdown(wait=True, cancel_futures=True)     # shards not started are dropped
                            raise ShardError(f"{label} shard {i} ({describe(shards[i])}) failed: "
                                             f"{type(e).__name__}: {e}; finished clips are kept") from e
                        bar.update()
                except (KeyboardInterrupt, SystemExit):
                    # Stopped (Ctrl-C, or SIGTERM turned into SystemExit while an MPS daemon runs): stop the
                    # workers now instead of letting the pool's exit run every queued shard first.
                    processes = list((getattr(pool, "_processes", None) or {}).values())   # shutdown forgets them
                    pool.shutdown(wait=False, cancel_futures=True)
                    for process in processes:
                        process.terminate()
                    raise
            if not broken:
                return results
            pending = sorted(broken)
            if attempt < options.retries:
                bar.write(f"{label}: a worker died; running {len(pending)} unfinished shard(s) again")
    raise ShardError(f"{label}: a worker died {options.retries + 1} times running "
                     f"{', '.join(describe(shards[i]) for i in pending)}; finished clips are kept, "
                     "re-run the same command to redo the rest")


def check_reachable(address: str, timeout: float = 5.0) -> None:
    """Fail fast (ConfigError) when a ``ray://host:port`` or ``host:port`` address does not answer.

    Ray itself waits for minutes on an unreachable GCS address, then exits the process.
    """
    if address in ("auto", "local"):
        return
    rest = address[len("ray://"):] if address.startswith("ray://") else address
    host, sep, port = rest.rpartition(":")
    if not sep:
        host, port = rest, "10001" if address.startswith("ray://") else "6379"
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            pass
    except (OSError, ValueError) as e:
        raise ConfigError(f"cannot reach the Ray cluster at {address!r} ({e}); start it with "
                          "`ray start --head` on the head node, then use --address auto there or "
                          "--address ray://HEAD:10001 from another machine") from None


@contextlib.contextmanager
def ray_session(options: ExecutorOptions, **init_kwargs):
    """Ray, connected (None for the other executors); a session started here is shut down on exit.

    ``address`` None starts a local instance (``workers`` CPUs when given), or joins RAY_ADDRESS when
    that is set; an address that does not answer is a ConfigError, not a long hang.
    """
    if options.executor != "ray":
        yield None
        return
    try:
        import ray
    except ImportError:
        raise ConfigError(RAY_MISSING) from None
    if ray.is_initialized():
        yield ray
        return
    # None: RAY_ADDRESS when set (as Ray itself does), else a new local instance ("local": never an
    # existing cluster that `ray start` left running on this machine)
    address = options.address or os.environ.get("RAY_ADDRESS") or "local"
    check_reachable(address)
    kwargs = dict(address=address, log_to_driver=False,
                  runtime_env={"env_vars": {"PYTHONPATH": _project_path()}}, **init_kwargs)
    if address == "local":
        kwargs["include_dashboard"] = False
        if options.workers and "num_cpus" not in kwargs:
            kwargs["num_cpus"] = options.workers
    try:
        ray.init(**kwargs)
    except (ConnectionError, SystemExit, RuntimeError, ValueError) as e:
        if address == "local":
            raise ConfigError(f"cannot start a local Ray instance: {e}") from None
        raise ConfigError(f"cannot connect to the Ray cluster at {address!r}: {e}; is it running (`ray start "
                          "--head`)? A cluster with token authentication also needs RAY_AUTH_MODE=token and "
                          "its token here (~/.ray/auth_token, RAY_AUTH_TOKEN or RAY_AUTH_TOKEN_PATH)") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def ray_parallelism(ray, options: ExecutorOptions) -> int:
    """How many shard tasks the connected cluster runs at once: its GPUs / gpus_per_worker, else its CPUs."""
    res = ray.cluster_resources()
    if options.gpus_per_worker:
        n = int(res.get("GPU", 0) // options.gpus_per_worker)
        if n < 1:
            raise ConfigError(f"--gpus-per-worker {options.gpus_per_worker:g} but the Ray cluster has "
                              f"{res.get('GPU', 0):g} GPU(s)")
        return n
    return max(1, int(res.get("CPU", 1)))


def _run_ray(fn, run_root, shards, options, label, describe) -> list[dict]:
    with ray_session(options) as ray:
        from ray.exceptions import RayTaskError

        # max_retries: a task whose worker or node dies runs again (its finished clips are skipped);
        # exceptions raised by the stage itself are not retried (they would fail the same way).
        task = ray.remote(num_gpus=options.gpus_per_worker, max_retries=options.retries,
                          retry_exceptions=False)(_call_shard)
        in_flight = options.workers or len(shards)
        results: list[Any] = [None] * len(shards)
        queue = list(range(len(shards)))
        running: dict[Any, int] = {}
        with _progress(len(shards), options.progress, f"{label} (ray)") as bar:
            while queue or running:
                while queue and len(running) < in_flight:
                    i = queue.pop(0)
                    running[task.remote(fn, run_root, shards[i])] = i
                done, _ = ray.wait(list(running), num_returns=1)
                i = running.pop(done[0])
                try:
                    results[i] = ray.get(done[0])
                except RayTaskError as e:
                    cause = getattr(e, "cause", None)
                    why = f"{type(cause).__name__}: {cause}" if cause is not None else str(e)
                    raise ShardError(f"{label} shard {i} ({describe(shards[i])}) failed on Ray: {why}") from e
                except Exception as e:      # WorkerCrashedError, NodeDiedError, ... after the retries
                    raise ShardError(f"{label} shard {i} ({describe(shards[i])}) could not finish on Ray: "
                                     f"{type(e).__name__}: {e}; finished clips are kept, re-run the same "
                                     "command to redo the rest") from e
                bar.update()
        return results


def _call_shard(fn: ShardFn, run_root: str, indices: list[int]) -> dict:
    """``fn(run_root, indices)`` as a Ray task: Ray makes tasks of functions only, and a shard function may be a
    ``functools.partial`` (it travels as the task's argument)."""
    return fn(run_root, indices)


def _project_path() -> str:
    """The project's root, so Ray workers on this machine import the same sim/render packages."""
    here = str(Path(__file__).resolve().parent.parent)
    return os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH", "")) if p)
