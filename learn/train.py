"""Train one model on one render variant of one setting, resumable epoch by epoch.

``train_one`` writes into ``run.train_dir(setting, variant, model, seed)``:

    config.json     the resolved settings (train config, model args, seeds, data sizes)
    metrics.csv     epoch, train_loss, train_acc, val_loss, val_acc, lr, seconds, and with a lattice
                    target train_shape, val_shape: the mean squared error of the predicted lattice
                    (standardised units: 1 is no better than the mean shape)
    tb/             TensorBoard scalars
    last.pt         model, optimizer, scheduler and RNG states after each epoch (tensors and plain
                    data only: it is read with ``weights_only=True``, so a run folder cannot run code)
    checkpoint.pt   the kept model (``train.keep``: the last epoch, or the best by validation
                    accuracy) in the contract format (docs/contracts.md)
    val_predictions.csv  the kept model on every validation window (``learn.predictions``'s CSV), so
                    recipes and ensembles of seeds can be compared on validation after the fact
    DONE            written last

A killed run resumes from ``last.pt`` and ends with the same weights as an
uninterrupted one: the data order and augmentations of an epoch depend only on
(seed, epoch), and every other random state is restored. Batches are cut from
the setting's frames held on the training device (``learn.windows``), so a step
costs what the network costs. A loss or weight that turns non-finite stops the
run with ``TrainingDiverged`` before anything is marked done. A network that gives
every validation window the same output (a dead layer: it cannot learn again) is
trained again from a new start drawn from its seed, at most ``DEAD_NETWORK_RESTARTS``
times (``restarts`` in config.json and DONE), then stopped with ``TrainingDead``.

With ``train.shared_regressor`` the named model trains as above and every other model of the same
(setting, variant, seed) takes its CNN and lattice head, frozen: those train their readers alone on the
shapes the regressor predicts, computed once a training (``learn.shapes``), not the CNN over every frame
each epoch.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import json
import math
import os
import random
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from clothgap import seeding
from clothgap.errors import ConfigError, UserError
from clothgap.files import atomic_path
from clothgap.runs import Run, atomic_write_json, atomic_write_text, file_sha256, fresh_dir, is_done, mark_done
from learn.config import SCHEDULES, TrainConfig
from learn.dataset import build_cache
from learn.geometry import geometry_targets
from learn.models import (NUM_CLASSES, ClipClassifier, ShapeReader, build_model, load_cnn_weights, model_args,
                          take_regressor)
from learn import predictions
from learn.registry import model_needs, reads_shared_regressor
from learn.shapes import ShapeSet
from learn.split import PARTS, get_or_make_split, part_clips, part_windows, training_subset
from learn.steps import GraphedReaderEpochs, train_step
from learn.windows import WindowSet

METRIC_COLUMNS = ("epoch", "train_loss", "train_acc", "val_loss", "val_acc", "lr", "seconds")
SHAPE_COLUMNS = ("train_shape", "val_shape")


def resolve_device(name: str) -> torch.device:
    """``"auto"`` is CUDA when there is one, else CPU; anything else goes to torch as given."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"train.device={name!r} but torch sees no CUDA device; use 'auto' or 'cpu'")
    return device


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def training_seed(run: Run, model_name: str, seed: int) -> int:
    """The torch/numpy/python seed of one training run (the same for every variant: paired)."""
    return seeding.derive_int(run.config.seed, seed, seeding.TRAIN, model_name)


def make_scheduler(optimizer: torch.optim.Optimizer, name: str, epochs: int):
    """Per-epoch learning-rate schedule: cosine to zero, or x0.1 at each third of the run."""
    if name == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(epochs, 1))
    if name == "step":
        return torch.optim.lr_scheduler.StepLR(optimizer, step_size=max(epochs // 3, 1), gamma=0.1)
    raise ConfigError(f"train.schedule={name!r}: known schedules are {', '.join(SCHEDULES)}")


class TrainingDiverged(UserError, RuntimeError):
    """The loss or the weights became non-finite; the run is left unfinished."""


def run_epoch(net: torch.nn.Module, model: ClipClassifier, batches, device: torch.device, optimizer=None,
              amp: bool = False, progress: bool = False, desc: str = "", total: int | None = None,
              geometry_weight: float = 0.0, label_smoothing: float = 0.0, truth_weight: float = 0.0) -> torch.Tensor:
    """One pass over ``batches`` (``WindowSet.batches``), training when given an optimizer, else evaluating.

    ``net`` is what runs the forward pass (``model`` itself, or it wrapped by
    DDP / torch.compile); ``model`` gives the loss and readout. Returns the sums
    (loss x clips, correct clips, clips, lattice squared error x clips) as a float64
    tensor, so that ranks can add them.
    """
    training = optimizer is not None
    net.train(training)
    sums = torch.zeros(4, dtype=torch.float64, device=device)   # summed on the device: no sync per step
    with torch.set_grad_enabled(training), _compile_failures_named():
        for x, y, target in tqdm(batches, desc=desc, disable=not progress, leave=False, total=total):
            if training:
                optimizer.zero_grad(set_to_none=True)
            train_step(net, model, x, y, target, device, optimizer, amp, sums, geometry_weight=geometry_weight,
                       label_smoothing=label_smoothing, truth_weight=truth_weight)
    return sums.cpu()


def _epoch_scores(sums: torch.Tensor, all_ranks: bool = False) -> tuple[float, float, float]:
    """(loss, accuracy, lattice squared error) per clip from ``run_epoch``'s sums."""
    if all_ranks and _world_size() > 1:
        sums = sums.to(_comm_device())
        torch.distributed.all_reduce(sums)
        sums = sums.cpu()
    loss, correct, count, shape = sums.tolist()
    return (loss / count, correct / count, shape / count) if count else (math.nan, math.nan, math.nan)


# ---------------------------------------------------------------- torchrun (DDP)

def _world_size() -> int:
    return torch.distributed.get_world_size() if torch.distributed.is_initialized() else 1


def _rank() -> int:
    return torch.distributed.get_rank() if torch.distributed.is_initialized() else 0


def is_main() -> bool:
    """True in the one process that writes files (rank 0, or the only process)."""
    return _rank() == 0


def _barrier() -> None:
    if _world_size() > 1:
        torch.distributed.barrier()


def _comm_device() -> torch.device:
    backend = torch.distributed.get_backend()
    return torch.device("cuda", torch.cuda.current_device()) if backend == "nccl" else torch.device("cpu")


def _process_device(cfg_device: str) -> torch.device:
    """The configured device; under torchrun on CUDA, this process's own GPU (LOCAL_RANK)."""
    device = resolve_device(cfg_device)
    if device.type == "cuda" and _world_size() > 1:
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
    return device


# ---------------------------------------------------------------- files of a training folder

def _save_state(path: Path, state: dict) -> None:
    """Write ``last.pt`` atomically: a kill mid-write leaves the previous epoch's state."""
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def _write_metrics(path: Path, rows: list[dict]) -> None:
    columns = METRIC_COLUMNS + tuple(c for c in SHAPE_COLUMNS
                                     if any(not math.isnan(row.get(c, math.nan)) for row in rows))
    cell = lambda v: f"{v:.6g}" if isinstance(v, float) else str(v)   # noqa: E731
    lines = [",".join(columns)] + [",".join(cell(row.get(c, math.nan)) for c in columns) for row in rows]
    atomic_write_text(path, "\n".join(lines) + "\n")


def _rng_states() -> dict:
    """Every random state, as tensors and plain data (``last.pt`` is read with ``weights_only=True``)."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    states = {"torch": torch.get_rng_state(),
              "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss), float(cached)],
              "python": random.getstate()}
    if torch.cuda.is_available():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def _set_rng_states(states: dict) -> None:
    torch.set_rng_state(states["torch"])
    kind, keys, pos, has_gauss, cached = states["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    version, internal, gauss = states["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in states and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(states["cuda"])


def _same_settings(stored: dict, resolved: dict, keys: tuple[str, ...]) -> bool:
    """Whether a folder's ``config.json`` (``stored``) has ``resolved``'s values at ``keys``. A train setting the
    stored one lacks was added since it was written, and counts as its default: what the code did before."""
    wanted = json.loads(json.dumps(resolved))   # tuples read back as lists
    stored = dict(stored)
    if isinstance(stored.get("train"), dict):
        defaults = json.loads(json.dumps(dataclasses.asdict(TrainConfig())))
        stored["train"] = {**{k: v for k, v in defaults.items() if k not in stored["train"]}, **stored["train"]}
    return all(stored.get(k) == wanted.get(k) for k in keys)


def _resumable_state(out: Path, resolved: dict) -> dict | None:
    """``last.pt`` of an unfinished run with the same settings, else None (the folder is then redone).

    Read with ``weights_only=True``: a ``last.pt`` that holds anything but tensors and plain
    data (a pickle payload, or a file cut short) is not resumed from, with a warning.
    """
    last, config = out / "last.pt", out / "config.json"
    if not (last.is_file() and config.is_file()):
        return None
    try:
        stored = json.loads(config.read_text())
    except (OSError, ValueError):
        return None
    if not _same_settings(stored, resolved, ("train", "model_args", "torch_seed", "cnn_init", "regressor_sha256")):
        return None
    try:
        return torch.load(last, map_location="cpu", weights_only=True)
    except Exception as err:   # noqa: BLE001 - any unreadable state means: start this model over
        warnings.warn(f"{last} cannot be resumed from ({type(err).__name__}: {str(err).splitlines()[0][:200]}); "
                      "training this model from its first epoch", stacklevel=2)
        return None


# ---------------------------------------------------------------- the model a model starts from

def _cnn_init(run: Run, setting: str, variant: str, model_name: str, seed: int, progress: bool,
              cfg: TrainConfig, root: Path | None) -> str:
    """Where the CNN's starting weights come from: a file path, or "random".

    A model whose registry entry ``needs`` another (base2 freezes base1's CNN), or every model but the
    ``train.shared_regressor``, starts from that model's checkpoint of the same (setting, variant, seed) beside
    it, trained first when missing, unless the config names ``train.pretrained`` weights, which are then used
    instead of training it (never for a shared regressor, whose lattice head they lack). The other models
    start from ``train.pretrained`` when given.
    """
    needs = model_needs(model_name, cfg.shared_regressor)
    if needs is None:
        return cfg.pretrained or "random"
    first = train_folder(run, setting, variant, needs, seed, root)
    if is_done(first):
        return str(first / "checkpoint.pt")
    if cfg.pretrained and not reads_shared_regressor(cfg.shared_regressor, model_name):
        return cfg.pretrained
    return str(train_one(run, setting, variant, needs, seed, progress, config=cfg, root=root) / "checkpoint.pt")


def shape_sets(resolved: dict, train_set: WindowSet, val_set: WindowSet, cfg: TrainConfig,
               device: torch.device) -> tuple[ShapeSet, ShapeSet]:
    """The train and validation windows as the shared regressor's predicted shapes (``learn.shapes``)."""
    regressor = build_training_model(resolved, device)
    amp = cfg.amp and device.type == "cuda"
    return (ShapeSet(train_set, regressor, cfg.batch_size, amp), ShapeSet(val_set, regressor, cfg.batch_size, amp))


def train_folder(run: Run, setting: str, variant: str, model_name: str, seed: int, root: Path | None = None) -> Path:
    """A model's training folder: the run's own, or the same layout under ``root`` (an ablation's)."""
    if root is None:
        return run.train_dir(setting, variant, model_name, seed)
    return Path(root) / setting / variant / model_name / f"s{seed}"


def window_sets(run: Run, setting: str, variant: str, cfg: TrainConfig, device: torch.device,
                progress: bool) -> tuple[WindowSet, WindowSet]:
    """The train and validation windows of a (setting, variant), their frames on ``device``.

    Under torchrun rank 0 writes the split, the frame cache and the geometry cache first.
    """
    main = is_main()
    if not main:
        _barrier()
    split = get_or_make_split(run, setting)
    cache = build_cache(run, variant, setting, cfg.image_size, progress)
    targets = (geometry_targets(run, setting, cache, progress, cfg.geometry_centre) if cfg.geometry_weight > 0
               else None)
    if main:
        _barrier()
    unassigned = sorted(set(cache.clips) - {c for part in PARTS for c in part_clips(split, part)})
    if unassigned and main:
        warnings.warn(f"{len(unassigned)} rendered clip(s) of {setting}/{variant} are in no part of "
                      f"{run.split_path(setting)} (rendered after the split was made?) and are not used: "
                      f"{', '.join(unassigned[:5])}{' ...' if len(unassigned) > 5 else ''}", stacklevel=2)
    not_rendered = sorted(c for part in ("train", "val") for c in part_clips(split, part) if c not in cache.clips)
    if not_rendered and main:
        warnings.warn(f"{len(not_rendered)} clip(s) of the train/val split of {setting}/{variant} are not rendered "
                      f"or were left out of the frame cache and are not used: {', '.join(not_rendered[:5])}"
                      f"{' ...' if len(not_rendered) > 5 else ''}", stacklevel=2)
    train_windows = part_windows(split, "train")
    if cfg.train_fraction < 1:
        rendered = {c: w for c, w in train_windows.items() if c in cache.clips}
        train_windows = training_subset(rendered, {c: cache.clips[c].class_index for c in rendered},
                                        cfg.train_fraction, run.config.seed)
    train_set = WindowSet(cache, train_windows, cfg.clip_len, cfg.clip_stride, device, targets)
    # Validation clips' lattices too: how well the shape is read on new clips, never a training signal.
    val_set = WindowSet(cache, part_windows(split, "val"), cfg.clip_len, cfg.clip_stride, device, targets)
    if not len(train_set):
        raise ConfigError(f"no training sub-sequences for {setting}/{variant}: {len(split['train'])} train clips, "
                          f"clip_len={cfg.clip_len}; are the clips rendered and long enough?")
    return train_set, val_set


def _check_finite(model: torch.nn.Module, train_loss: float, cfg: TrainConfig, where: str, epoch: int) -> None:
    bad = [name for name, p in model.named_parameters() if not bool(torch.isfinite(p).all())]
    if math.isfinite(train_loss) and not bad:
        return
    raise TrainingDiverged(
        f"{where}: training diverged at epoch {epoch} (loss {train_loss:g}, {len(bad)} non-finite weight "
        f"tensor(s){': ' + ', '.join(bad[:3]) if bad else ''}); the learning rate train.lr={cfg.lr:g} is the "
        "likely cause: lower it and run again (the folder is left unfinished and will start over)")


class TrainingDead(TrainingDiverged):
    """The network gave every input the same output after each of its restarts."""


# A network whose outputs are the same for every input stays so: in practice every unit of a ReLU layer (fc6) is
# off for every input, and no gradient reaches the layers below. Seen once in 31 GPU trainings (camera and colour
# augmentation, 80 epochs, seed 1: constant from the first epoch, chance for all 80). It is trained again from a
# new initialisation drawn from its seed, at most this many times. A restarted model no longer shares its
# initialisation with the same seed's models of other variants (``training_seed``'s pairing).
DEAD_NETWORK_RESTARTS = 2


def network_is_dead(model: torch.nn.Module, windows: WindowSet | ShapeSet, batch_size: int) -> bool:
    """True when ``model`` (or a ``ShapeReader`` on a ``ShapeSet``) gives a batch of ``windows`` spread over the set
    (two windows at least) one and the same output. Under torchrun the ranks' answers are combined (any rank's yes
    is every rank's), so that all restart."""
    dead = False
    if len(windows) >= 2:
        n = min(max(batch_size, 2), len(windows))
        spread_out = torch.linspace(0, len(windows) - 1, n).round().long()   # many clips, not one clip's windows
        x, _, _ = next(iter(windows.batches(n, order=spread_out)))
        training = model.training
        model.eval()
        with torch.no_grad():
            logits = model(x)["logits"].float()
        model.train(training)
        dead = bool((logits - logits[:1]).abs().max() <= 1e-6 * (1 + logits.abs().max()))
    if _world_size() > 1:
        flag = torch.tensor([float(dead)], device=_comm_device())
        torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
        dead = bool(flag.item())
    return dead


def restart_seed(torch_seed: int, restarts: int) -> int:
    """The torch seed of a training's ``restarts``-th new start (0: the seed itself)."""
    return torch_seed if restarts == 0 else seeding.derive_int(torch_seed, restarts, seeding.TRAIN, "restart")


def _adopt_restarts(out: Path, resolved: dict) -> None:
    """A folder whose training was restarted resumes as the restart: its ``config.json``'s restart count and
    seed replace the first start's in ``resolved`` when everything else that decides the weights matches."""
    try:
        stored = json.loads((out / "config.json").read_text())
    except (OSError, ValueError):
        return
    restarts = stored.get("restarts", 0)
    if (isinstance(restarts, int) and 0 < restarts <= DEAD_NETWORK_RESTARTS
            and stored.get("torch_seed") == restart_seed(resolved["torch_seed"], restarts)
            and _same_settings(stored, resolved, ("train", "model_args", "cnn_init", "regressor_sha256"))):
        resolved.update(restarts=restarts, first_torch_seed=resolved["torch_seed"], torch_seed=stored["torch_seed"])


def _restart_dead(t: Training, epoch: int) -> Training:
    """``t`` started over from a new initialisation (``restart_seed``), its folder cleared; TrainingDead when
    it has had its restarts."""
    resolved = dict(t.resolved)
    restarts = resolved.get("restarts", 0) + 1
    where = f"{t.out}: the network gives every validation window the same output after epoch {epoch}"
    if t.model.freeze_cnn and not t.reads_shapes:
        raise TrainingDead(f"{where}, and its CNN is frozen (from {resolved['cnn_init']}): a new start cannot "
                           "change it; retrain the model it comes from")
    if restarts > DEAD_NETWORK_RESTARTS:
        raise TrainingDead(f"{where}, after {DEAD_NETWORK_RESTARTS} new starts; lower train.lr={t.cfg.lr:g} or "
                           "the augmentation's strength and run again (the folder is left unfinished)")
    first_seed = resolved.get("first_torch_seed", resolved["torch_seed"])
    resolved.update(restarts=restarts, first_torch_seed=first_seed, torch_seed=restart_seed(first_seed, restarts))
    warnings.warn(f"{where} (its units are off for every input and cannot learn); training it again from a new "
                  f"initialisation, start {restarts + 1} of at most {DEAD_NETWORK_RESTARTS + 1}", stacklevel=3)
    if is_main():
        t.writer.close()
    return _start(t.out, t.cfg, t.device, resolved, t.train_set, t.val_set)


# ---------------------------------------------------------------- training, step by step

@dataclasses.dataclass
class Training:
    """One model's training in progress: what the steps of ``train_one`` share from epoch to epoch."""

    out: Path                       # the training folder
    cfg: TrainConfig
    device: torch.device
    resolved: dict                  # config.json: the settings that decide the weights, and the data sizes
    train_set: WindowSet | ShapeSet   # ShapeSet: the readers alone train, on a shared regressor's shapes
    val_set: WindowSet | ShapeSet
    model: ClipClassifier
    net: torch.nn.Module            # what runs the forward pass: the model, or it wrapped by DDP / torch.compile
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    metrics: list[dict]             # a row per finished epoch (``METRIC_COLUMNS`` + ``SHAPE_COLUMNS``)
    best: dict | None               # {"epoch", "val_acc", "model"}: the best epoch so far (train.keep=best)
    start_epoch: int                # the first epoch still to train
    writer: object | None = None    # TensorBoard's SummaryWriter, in the process that writes files
    shape_seconds: float | None = None   # the shared regressor's pass over the windows, in this process
    data_seconds: float | None = None    # the windows ready on the device in this process: split, frame cache
                                         # (built if missing), lattices, then frames and lattices onto it
    graphed: GraphedReaderEpochs | None = None   # a reader's epochs replayed from a CUDA graph (reader_graphs)

    @property
    def reads_shapes(self) -> bool:
        """Whether the data are a shared regressor's shapes (``learn.shapes``), read by the readers alone."""
        return isinstance(self.train_set, ShapeSet)

    @property
    def evaluator(self) -> torch.nn.Module:
        """What validation runs: the model, or its readers alone on shapes."""
        return ShapeReader(self.model) if self.reads_shapes else self.model

    @property
    def amp(self) -> bool:
        return self.cfg.amp and self.device.type == "cuda"


def train_one(run: Run, setting: str, variant: str, model_name: str, seed: int, progress: bool = True, *,
              config: TrainConfig | None = None, root: Path | None = None) -> Path:
    """Train ``model_name`` on ``variant``'s clips of ``setting``; returns the finished folder.

    A finished folder (``DONE``) is returned as is; an unfinished one with a
    matching ``last.pt`` resumes after its last epoch; anything else starts over.
    A model that needs another (``learn.registry``) has it trained first.
    Under torchrun (an initialised process group) every process trains its share
    of each epoch through DDP, ``batch_size`` is per process, and rank 0 writes.

    Args:
        run: the run whose rendered clips are trained on.
        setting, variant, model_name, seed: which model of the run's grid.
        progress: show progress bars (in the writing process only).
        config: replaces the run's train settings (ablations that train several recipes on the same data).
        root: replaces the run's ``train/`` folder (the same layout under another folder).

    Returns:
        The training folder, with ``checkpoint.pt`` and ``DONE``.
    """
    cfg = config or run.config.train
    out = train_folder(run, setting, variant, model_name, seed, root)
    if is_done(out):
        return out
    device = _setup_process(cfg)
    progress = progress and is_main()
    cnn_init = _cnn_init(run, setting, variant, model_name, seed, progress, cfg, root)
    if reads_shared_regressor(cfg.shared_regressor, model_name) and cfg.reader_epochs:
        cfg = dataclasses.replace(cfg, epochs=cfg.reader_epochs)     # (after the regressor, which keeps its own)
    started = time.perf_counter()
    train_set, val_set = window_sets(run, setting, variant, cfg, device, progress)
    data_seconds = time.perf_counter() - started
    resolved = _resolved_settings(run, setting, variant, model_name, seed, cfg, cnn_init, device, train_set, val_set)
    shape_seconds = None
    if reads_shared_regressor(cfg.shared_regressor, model_name):
        # The regressor's bytes, so that a last.pt whose frozen parts came from another training of it (retrained
        # at the same path) is not resumed with shapes from this one.
        resolved["regressor_sha256"] = file_sha256(cnn_init)
        started = time.perf_counter()
        train_set, val_set = shape_sets(resolved, train_set, val_set, cfg, device)   # the frames are let go
        shape_seconds = time.perf_counter() - started
    _adopt_restarts(out, resolved)
    t = _start(out, cfg, device, resolved, train_set, val_set)
    t.shape_seconds, t.data_seconds = shape_seconds, data_seconds

    bar = tqdm(desc=f"{model_name} {setting}/{variant} s{seed}", disable=not progress, initial=t.start_epoch,
               total=cfg.epochs)
    epoch = t.start_epoch
    while epoch < cfg.epochs:
        started = time.perf_counter()
        train_loss, train_acc, train_shape = train_epoch(t, epoch, progress)
        val_loss, val_acc, val_shape = validate(t)
        lr = float(t.optimizer.param_groups[0]["lr"])     # (a device tensor under reader graphs)
        t.scheduler.step()
        row = {"epoch": epoch, "train_loss": train_loss, "train_acc": train_acc, "val_loss": val_loss,
               "val_acc": val_acc, "lr": lr, "seconds": time.perf_counter() - started,
               "train_shape": train_shape, "val_shape": val_shape}
        # Before the epoch is saved: a dead network is never in last.pt, so no resume finishes one.
        if network_is_dead(t.evaluator, t.val_set if len(t.val_set) >= 2 else t.train_set, cfg.batch_size):
            t = _restart_dead(t, epoch)
            t.shape_seconds, t.data_seconds = shape_seconds, data_seconds
            epoch = t.start_epoch
            bar.reset()
            continue
        _end_epoch(t, row)
        bar.set_postfix(loss=f"{train_loss:.3f}", acc=f"{train_acc:.2f}", val=f"{val_acc:.2f}")
        epoch += 1
        bar.update()
    bar.close()
    if is_main():
        _finish(t)
    _barrier()  # no rank moves on (say, to a model that starts from this checkpoint) before DONE exists
    return out


def _setup_process(cfg: TrainConfig) -> torch.device:
    """Torch's CPU threads as configured; returns this process's training device."""
    if cfg.num_threads:
        torch.set_num_threads(cfg.num_threads)
    return _process_device(cfg.device)


def _resolved_settings(run: Run, setting: str, variant: str, model_name: str, seed: int, cfg: TrainConfig,
                       cnn_init: str, device: torch.device, train_set: WindowSet, val_set: WindowSet) -> dict:
    """What ``config.json`` records: the settings that decide the weights (compared on resume) and the data."""
    return {"train": dataclasses.asdict(cfg), "model": model_name, "model_args": model_args(cfg),
            "setting": setting, "variant": variant, "seed": seed, "run_seed": run.config.seed,
            "torch_seed": training_seed(run, model_name, seed), "cnn_init": cnn_init, "device": str(device),
            "world_size": _world_size(), "train_subsequences": len(train_set), "val_subsequences": len(val_set),
            "frames_on_device": train_set.resident}


def _start(out: Path, cfg: TrainConfig, device: torch.device, resolved: dict, train_set: WindowSet | ShapeSet,
           val_set: WindowSet | ShapeSet) -> Training:
    """The folder opened (resumed from ``last.pt``, or cleared), the model and optimiser built, and the
    training state at the first epoch still to train."""
    state = _resumable_state(out, resolved)
    _barrier()  # every rank has read last.pt before rank 0 may clear the folder
    if state is None and is_main():
        fresh_dir(out)
        atomic_write_json(out / "config.json", resolved)
    model = build_training_model(resolved, device)
    optimizer = make_optimizer(model, cfg, device)
    scheduler = make_scheduler(optimizer, cfg.schedule, cfg.epochs)
    t = Training(out, cfg, device, resolved, train_set, val_set, model, model, optimizer, scheduler,
                 metrics=[], best=None, start_epoch=0)
    if state is not None:
        _resume(t, state)
    t.net = forward_net(t.evaluator, cfg, device, t.reads_shapes)
    if is_main():
        # Imported here: TensorBoard is slow to import and only training needs it.
        from torch.utils.tensorboard import SummaryWriter

        t.writer = SummaryWriter(str(out / "tb"), purge_step=t.start_epoch)
    return t


def build_training_model(resolved: dict, device: torch.device) -> ClipClassifier:
    """The model at its starting weights (``resolved``: ``model``, ``model_args``, seeded from ``torch_seed``, its
    CNN from ``cnn_init``), on ``device`` in the layout training runs it in."""
    seed_everything(resolved["torch_seed"])
    model = build_model(resolved["model"], **resolved["model_args"])
    if reads_shared_regressor(resolved.get("train", {}).get("shared_regressor", ""), resolved["model"]):
        take_regressor(model, resolved["cnn_init"])
    elif resolved["cnn_init"] != "random":
        load_cnn_weights(model, resolved["cnn_init"])
    model.to(device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
        model.cnn.to(memory_format=torch.channels_last)
        model.channels_last = True
    return model


def make_optimizer(model: ClipClassifier, cfg: TrainConfig, device: torch.device) -> torch.optim.Optimizer:
    """AdamW over the trainable parameters; fused on CUDA: one kernel updates every parameter (a small model's
    step is bounded by launches)."""
    return torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=cfg.lr,
                             weight_decay=cfg.weight_decay, fused=device.type == "cuda")


def _resume(t: Training, state: dict) -> None:
    """Restore the weights, the optimiser, the schedule, every random state and the metrics from ``last.pt``."""
    t.model.load_state_dict(state["model"])
    t.optimizer.load_state_dict(state["optimizer"])
    t.scheduler.load_state_dict(state["scheduler"])
    rng, world = state["rng"], _world_size()
    if len(rng) != world:
        warnings.warn(f"{t.out}: last.pt was written by {len(rng)} process(es), resuming with {world}: "
                      "the result will differ from an uninterrupted run", stacklevel=4)
    _set_rng_states(rng[min(_rank(), len(rng) - 1)])
    t.metrics, t.start_epoch, t.best = state["metrics"], state["epoch"] + 1, state.get("best")


def compiles(cfg: TrainConfig, device: torch.device, reads_shapes: bool) -> bool:
    """Whether a training's forward pass is compiled: asked for, on CUDA, in one process (graphs under torchrun's DDP
    are not measured, so it trains eager), and not a reader on a shared regressor's shapes that
    ``train.compile_readers`` leaves eager."""
    return (cfg.compile and device.type == "cuda" and _world_size() == 1
            and (not reads_shapes or (cfg.compile_readers and not graphs_readers(cfg, device))))


def graphs_readers(cfg: TrainConfig, device: torch.device) -> bool:
    """Whether a reader on a shared regressor's shapes trains by replaying its step as one CUDA graph
    (``train.reader_graphs``, ``learn.steps``): asked for, on CUDA, in one process."""
    return cfg.reader_graphs and device.type == "cuda" and _world_size() == 1


def forward_net(model: ClipClassifier, cfg: TrainConfig, device: torch.device,
                reads_shapes: bool = False) -> torch.nn.Module:
    """What runs the training forward pass: ``model``, wrapped by DDP under torchrun, compiled if ``compiles``."""
    on_cuda = device.type == "cuda"
    net: torch.nn.Module = model
    if _world_size() > 1:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if on_cuda else None)
    if compiles(cfg, device, reads_shapes):
        if importlib.util.find_spec("triton") is None:      # torch.compile's CUDA code generator
            raise ConfigError("train.compile=true needs Triton on a CUDA device, and this Python has none (the paper "
                              "and study presets compile): install it, or set train.compile=false to train eager")
        net = torch.compile(net, mode=None if cfg.compile_mode == "default" else cfg.compile_mode)
    return net


@contextlib.contextmanager
def _compile_failures_named():
    """torch.compile compiles at the first forward and backward pass: a backend that fails there (a missing C++
    compiler, a Triton error) is a ConfigError that gives its cause and the way around it."""
    try:
        yield
    except Exception as e:
        dynamo = sys.modules.get("torch._dynamo.exc")       # imported only once something was compiled
        if dynamo is None or not isinstance(e, dynamo.BackendCompilerFailed):
            raise
        cause = getattr(e, "inner_exception", None) or e
        lines = [line.strip() for line in str(cause).splitlines() if line.strip()][:6]
        detail = "\n  ".join(lines)[:1500] or "no message"
        raise ConfigError(f"torch.compile could not compile the network: {type(cause).__name__}: {detail}\nSet "
                          "train.compile=false (or the recipe lever `eager`) to train without compiling") from e


def train_epoch(t: Training, epoch: int, progress: bool = False) -> tuple[float, float, float]:
    """Train one epoch on this process's share of the windows, in the order and with the augmentations that
    (seed, epoch) decide; returns (loss, accuracy, lattice squared error) over every process's clips."""
    cfg = t.cfg
    torch_seed = t.resolved["torch_seed"]
    order = t.train_set.order(torch_seed, epoch, _rank(), _world_size())
    steps = len(order) // cfg.batch_size if len(order) >= cfg.batch_size else 1
    if t.reads_shapes and graphs_readers(cfg, t.device) and len(order) >= cfg.batch_size:
        if t.graphed is None:
            t.graphed = GraphedReaderEpochs(t.net, t.model, t.optimizer, t.train_set, cfg.batch_size, t.device,
                                            t.amp, geometry_weight=cfg.geometry_weight,
                                            label_smoothing=cfg.label_smoothing, truth_weight=cfg.reader_truth)
        sums = t.graphed.epoch(order)
    else:
        if t.reads_shapes:
            # The frames' augmentations trained the regressor; its readers read the shapes it predicts unaugmented.
            batches = t.train_set.batches(cfg.batch_size, order=order, drop_last=True)
        else:
            augment = t.train_set.augment_table(torch_seed, epoch) if cfg.augment else None
            camera = t.train_set.camera_table(torch_seed, epoch) if cfg.augment_camera else None
            batches = t.train_set.batches(cfg.batch_size, order=order, augment=augment, drop_last=True,
                                          crop=cfg.augment_crop, camera=camera,
                                          camera_noise_seed=t.train_set.camera_noise_seed(torch_seed, epoch, _rank()))
        sums = run_epoch(t.net, t.model, batches, t.device, t.optimizer, t.amp, progress, f"epoch {epoch}", steps,
                         cfg.geometry_weight, cfg.label_smoothing, cfg.reader_truth)
    scores = _epoch_scores(sums, all_ranks=True)
    _check_finite(t.model, scores[0], cfg, str(t.out), epoch)
    return scores


def validate(t: Training) -> tuple[float, float, float]:
    """(loss, accuracy, lattice squared error) on the validation windows; NaNs without validation clips.

    Every process scores the whole (small) validation set with its own copy of the same weights."""
    if not len(t.val_set):
        return math.nan, math.nan, math.nan
    return _epoch_scores(run_epoch(t.evaluator, t.model, t.val_set.batches(t.cfg.batch_size), t.device, None,
                                   t.amp))


def _end_epoch(t: Training, row: dict) -> None:
    """Record a finished epoch: its metrics row, the best epoch's weights (train.keep=best), and in the writing
    process TensorBoard, ``metrics.csv`` and ``last.pt`` (every process's random states)."""
    t.metrics.append(row)
    if t.cfg.keep == "best" and not math.isnan(row["val_acc"]) and (t.best is None or
                                                                    row["val_acc"] > t.best["val_acc"]):
        t.best = {"epoch": row["epoch"], "val_acc": row["val_acc"],
                  "model": {k: v.detach().cpu().clone() for k, v in t.model.state_dict().items()}}
    rng = _gather(_rng_states())
    if not is_main():
        return
    for key in ("train_loss", "train_acc", "val_loss", "val_acc", "lr") + SHAPE_COLUMNS:
        if not math.isnan(row[key]):
            t.writer.add_scalar(key, row[key], row["epoch"])
    t.writer.flush()
    _write_metrics(t.out / "metrics.csv", t.metrics)
    _save_state(t.out / "last.pt", {"model": t.model.state_dict(), "optimizer": t.optimizer.state_dict(),
                                    "scheduler": t.scheduler.state_dict(), "rng": rng,
                                    "epoch": row["epoch"], "metrics": t.metrics, "best": t.best})


def _finish(t: Training) -> None:
    """Write the kept weights (``train.keep``) as ``checkpoint.pt`` in the contract format, then ``DONE``."""
    t.writer.close()
    cfg, resolved, metrics = t.cfg, t.resolved, t.metrics
    kept = t.best if cfg.keep == "best" and t.best is not None else None
    weights = kept["model"] if kept else t.model.state_dict()
    checkpoint = {"model": weights, "model_name": resolved["model"], "model_args": resolved["model_args"],
                  "num_classes": NUM_CLASSES, "setting": resolved["setting"], "variant": resolved["variant"],
                  "seed": resolved["seed"], "config": resolved}
    # Written in place, not through atomic_path: torch names the zip's inner folder after the file, so a
    # temporary name would change the bytes that eval hashes (checkpoint_sha256). DONE, written next, is what
    # says the folder is complete; a kill before it resumes from last.pt and writes this again.
    torch.save(checkpoint, t.out / "checkpoint.pt")
    if len(t.val_set):
        t.model.load_state_dict(weights)
        predictions.save(t.val_set.predict(t.model, t.cfg.batch_size, t.amp), t.out / "val_predictions.csv")
    final = metrics[-1] if metrics else {}
    summary = {k: final.get(k) for k in METRIC_COLUMNS[1:5]}
    kept_epoch = kept["epoch"] if kept else (final.get("epoch") if metrics else None)
    restarts = {"restarts": resolved["restarts"]} if resolved.get("restarts") else {}
    shapes = {"shape_seconds": round(t.shape_seconds, 3)} if t.shape_seconds is not None else {}
    data = {"data_seconds": round(t.data_seconds, 3)} if t.data_seconds is not None else {}
    mark_done(t.out, {"epochs": cfg.epochs, "seconds": sum(r["seconds"] for r in metrics),
                      "kept_epoch": kept_epoch, **restarts, **shapes, **data,
                      **{k: None if v is None or math.isnan(v) else v for k, v in summary.items()}})


def _gather(obj) -> list:
    """``obj`` of every rank, in rank order (a list of one without torchrun)."""
    if _world_size() == 1:
        return [obj]
    objs: list = [None] * _world_size()
    torch.distributed.all_gather_object(objs, obj)
    return objs
