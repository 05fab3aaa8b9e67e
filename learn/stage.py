"""The learn stage's entry point: every (setting, variant, model, seed) of the run's grid, in this
process or under torchrun (``python -m learn``, ``torchrun --nproc-per-node N -m learn RUN_DIR``)."""

from __future__ import annotations

import gc
import os
import sys
from pathlib import Path

import torch

from clothgap.runs import Run, atomic_write_json, is_done
from learn.registry import MODEL_NAMES
from learn.registry import training_grid as registry_grid
from learn.train import is_main, train_one
from sim.phases import timed


def training_grid(run: Run) -> list[tuple[str, str, str, int]]:
    """(setting, variant, model, seed) in training order (``learn.registry.training_grid``): a model after
    the one it needs (base1 before base2, which freezes base1's CNN)."""
    cfg = run.config.train
    unknown = [m for m in cfg.models if m not in MODEL_NAMES]
    if unknown:
        raise ValueError(f"unknown model(s) {', '.join(unknown)} in train.models; known: {', '.join(MODEL_NAMES)}")
    return registry_grid(run.config)


def prepare_shared_inputs(run: Run, grid: list[tuple[str, str, str, int]], progress: bool = True,
                          configs: list | None = None) -> dict[str, float]:
    """What several trainings of ``grid`` read and the first would write: each setting's split, each
    (variant, setting)'s frame cache at each image size and each setting's simulated lattices (when a recipe
    regresses them). ``configs``: each entry's train settings (default: the run's). Built once here, so
    that trainings running at once only read them. Returns the seconds each kind took (``splits``, ``caches``,
    ``lattices``)."""
    from learn.dataset import build_cache
    from learn.geometry import clip_lattices
    from learn.split import get_or_make_split

    seconds: dict[str, float] = {"splits": 0.0, "caches": 0.0, "lattices": 0.0}
    configs = configs or [run.config.train] * len(grid)
    with timed(seconds, "splits"):
        for setting in dict.fromkeys(s for s, _, _, _ in grid):
            get_or_make_split(run, setting)
    needs = dict.fromkeys((s, v, c.image_size, c.geometry_weight > 0) for (s, v, _, _), c in zip(grid, configs))
    for setting, variant, size, lattices in needs:
        with timed(seconds, "caches"):
            cache = build_cache(run, variant, setting, size, progress)
        if lattices:
            with timed(seconds, "lattices"):
                clip_lattices(run, setting, sorted(cache.clips), progress)
        del cache
    return seconds


def run_train(run: Run, progress: bool = True) -> dict:
    """Train the whole grid, skipping finished folders; writes and returns ``train/index.json``.

    The index lists every grid entry with its folder (relative to the run) and
    whether it is done, so eval finds results without walking the tree.
    """
    grid = training_grid(run)
    index_path = run.train_index_path

    def write_index() -> dict:
        entries = []
        for setting, variant, model, seed in grid:
            folder = run.train_dir(setting, variant, model, seed)
            entries.append({"setting": setting, "variant": variant, "model": model, "seed": seed,
                            "dir": str(folder.relative_to(run.root)), "done": is_done(folder)})
        index = {"entries": entries}
        if is_main():   # under torchrun, one process writes
            atomic_write_json(index_path, index)
        return index

    for setting, variant, model, seed in grid:
        train_one(run, setting, variant, model, seed, progress)
        write_index()
    return write_index()


def main(argv: list[str] | None = None) -> None:
    """``python -m learn RUN_DIR [--setting S --variant V --model M --seed N]``.

    Trains the whole grid of the run, or the selected part of it. The same
    command under ``torchrun --nproc-per-node N -m learn ...`` trains with
    DDP over N processes (NCCL on GPUs, gloo on CPU), reading RANK, WORLD_SIZE
    and LOCAL_RANK from the environment as torchrun sets them.
    """
    import argparse

    parser = argparse.ArgumentParser(prog="python -m learn", description=main.__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="an existing run folder (with rendered clips)")
    parser.add_argument("--setting", action="append", help="train only this setting (repeatable)")
    parser.add_argument("--variant", action="append", help="train only this render variant (repeatable)")
    parser.add_argument("--model", action="append", choices=MODEL_NAMES, help="train only this model (repeatable)")
    parser.add_argument("--seed", action="append", type=int, help="train only this seed (repeatable)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    opts = parser.parse_args(argv)

    world = int(os.environ.get("WORLD_SIZE", 1))
    if world > 1:
        use_nccl = torch.cuda.is_available()
        if use_nccl:
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", 0)))
        torch.distributed.init_process_group("nccl" if use_nccl else "gloo")
    finished = False
    try:
        run = Run.open(opts.run_dir)
        cfg = run.config
        if not (opts.setting or opts.variant or opts.model or opts.seed is not None):
            run_train(run, progress=not opts.no_progress)
            finished = True
            return
        chosen = {"--setting": (opts.setting, cfg.sim.settings()), "--variant": (opts.variant, cfg.render.variants),
                  "--model": (opts.model, cfg.train.models), "--seed": (opts.seed, cfg.train.seeds)}
        for flag, (wanted, known) in chosen.items():
            missing = [w for w in wanted or () if w not in known]
            if missing:
                parser.error(f"{flag} {', '.join(map(str, missing))}: not in this run's config "
                             f"({', '.join(map(str, known))})")
        for setting, variant, model_name, seed in registry_grid(cfg, opts.setting, opts.variant, opts.model,
                                                                 opts.seed):
            folder = train_one(run, setting, variant, model_name, seed, progress=not opts.no_progress)
            if is_main():
                print(folder)
        finished = True
    finally:
        if torch.distributed.is_initialized():
            # What still holds the group (a DDP reducer in a reference cycle) goes first: one left for the
            # interpreter's exit can find the group's C++ threads already gone (a rank once died with SIGABRT,
            # "terminate called without an active exception", after its training had finished).
            gc.collect()
            if finished:
                # Both ranks leave together: gloo aborted a rank whose peer had already torn its group down.
                torch.distributed.barrier()
            torch.distributed.destroy_process_group()
            if finished:
                # and without the interpreter's teardown, its work written and closed: the transport's C++
                # threads met at exit still aborted a finished rank now and then (SIGABRT, "terminate called
                # without an active exception": one full test run in six on a 2-core CPU after the two guards
                # above).
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(0)
