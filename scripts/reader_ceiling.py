"""How much of the class the shape bottleneck's reader gets from the TRUE lattice: its ceiling.

The `train.bottleneck` model reads classes only from the lattice its CNN predicts (learn.models). This
trains the same model's reader (``ClipClassifier.read_lattice``: per-frame MLP on the shape and its change,
LSTM, per-step heads; its loss and readout) on the simulator's own 8 x 8 lattices of a run's sim clips, split
by sequence with the run's seed, and prints top-1 on the validation windows (where a choice is made) and
top-1, within-one-bin, stretching and bending class accuracy on the test windows. ``--noise`` adds Gaussian
noise (standardised units) to the training, validation, test and ``--transfer`` lattices (not to the measured
fabrics'): what white regression error of that size alone costs. AdamW at 1e-3 with a cosine schedule;
``--weight-decay``, ``--batch-size`` and ``--keep best`` (the epoch of the best validation top-1) train it as the
`paper` preset trains the network (0.05, 16, best).

    python scripts/reader_ceiling.py RUN_DIR --setting wind-uniform1 [--noise 0.18] [--per-coordinate]
                                     [--clip-len 10 --stride 5] [--centre median|frame]
                                     [--reader frames|stats] [--transfer OTHER_RUN ...] [--device cuda]
                                     [--weight-decay 0.05 --batch-size 16 --keep best] [--seed S] [--measured N]

``--clip-len``/``--stride`` cut the windows as ``train.clip_len``/``train.clip_stride`` do (40: the whole clip);
``--centre frame`` measures each lattice from the median shape at its frame index, as ``train.geometry_centre``.

``--measured N`` then simulates N clips of each of the Wang et al. fabrics with their own tables (what
``clothgap eval measured`` simulates, into ``RUN/measured/sim``; finished clips are kept) and reads their true
lattices with the same reader: each fabric's class (argmax of its clips' mean window probabilities) against
its Table 2 class (exact; grid steps and within one grid step; within one bin, at most one bin off in p and in
k: goal 3's count, as `clothgap eval measured` counts it) and predicted bending ranked against measured bending.
This is what the geometry alone tells of the measured set, with no pixels and no render look in the way.

``--reader stats`` replaces the reader by one that reads a window's statistics of the shape (each point's mean and
spread over the window, its mean speed, the window's bounding box: what ``eval.learnability``'s probes read) with
an MLP, instead of a recurrence over frames. ``--transfer OTHER_RUN`` reads the test clips of another run of the
same setting whose class clips differ in one thing (``sim.table_spread``: the same clip ids, classes and motion
draws, the tables reshaped) with the reader trained here: how far a reader carries to material shapes it never saw,
measured on labelled clips, so that a reader can be chosen without the measured fabrics.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
import pandas as pd
import torch

import clothgap.config  # noqa: F401  (registers the study config that Run.open reads)
from clothgap.runs import Run, read_meta
from eval import metrics
from learn.geometry import TARGET_LIMIT, clip_lattices, median_shape
from learn.models import GEOMETRY_DIM, build_model, model_args
from learn.split import split_sequences
from sim.lattice import clip_lattice


class StatsReader(torch.nn.Module):
    """A window's shape statistics read by an MLP: the reader interface (``read_lattice``, ``probs``, ``loss``) of
    ``learn.models.ClipClassifier`` with one step a window."""

    def __init__(self, geometry_dim: int, hidden: int, classes: int = 54, dropout: float = 0.3):
        super().__init__()
        points = geometry_dim // 3
        features = 2 * geometry_dim + points + 6
        # No per-feature standardisation: the lattice comes standardised as a whole (as the frames reader gets it),
        # and scaling each statistic to unit spread lifts the ones that hold nothing but noise.
        self.mlp = torch.nn.Sequential(torch.nn.Linear(features, hidden),
                                       torch.nn.ReLU(), torch.nn.Dropout(dropout), torch.nn.Linear(hidden, hidden),
                                       torch.nn.ReLU(), torch.nn.Dropout(dropout), torch.nn.Linear(hidden, classes))

    @staticmethod
    def statistics(shape: torch.Tensor) -> torch.Tensor:
        """(B, T, P*3) -> (B, 2*P*3 + P + 6): eval.learnability.window_features of each window."""
        pts = shape.unflatten(-1, (-1, 3))
        speed = (pts[:, 1:] - pts[:, :-1]).norm(dim=-1).mean(1) if shape.shape[1] > 1 else pts[:, 0, :, 0] * 0
        box = torch.cat([pts.amin(dim=(1, 2)), pts.amax(dim=(1, 2))], dim=-1)
        return torch.cat([shape.mean(1), shape.std(1, unbiased=False), speed, box], dim=-1)

    def read_lattice(self, shape: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"logits": self.mlp(self.statistics(shape))[:, None]}

    @staticmethod
    def probs(out: dict[str, torch.Tensor]) -> torch.Tensor:
        return out["logits"].float().softmax(-1).mean(1)

    @staticmethod
    def loss(out: dict[str, torch.Tensor], labels: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.cross_entropy(out["logits"][:, 0].float(), labels)


def windows(lattices, labels, clips, centre, scale, clip_len, stride):
    x, y = [], []
    for c in clips:
        lat = np.clip((lattices[c] - centre[:len(lattices[c])]) / scale, -TARGET_LIMIT, TARGET_LIMIT)
        for s in range(0, len(lat) - clip_len + 1, stride):
            x.append(lat[s:s + clip_len])
            y.append(labels[c])
    return torch.tensor(np.array(x), dtype=torch.float32), torch.tensor(y)


def read_measured(run, setting, model, sequences, centre, scale, clip_len, stride) -> dict:
    """The reader's class for each measured fabric from its clips' true lattices, against Table 2."""
    from scipy import stats

    from eval.measured import with_predicted_values
    from sim.measured import clip_name, measured_values, table2_class, table2_fabrics, wanted_clips
    from sim.stage import simulate_measured

    fabrics = table2_fabrics()
    simulate_measured(run, fabrics, sequences, progress=False)
    folder = run.measured_sim_dir(setting)
    preds, device = [], next(model.parameters()).device
    for fabric in fabrics:
        names = [clip_name(f, n) for f, n in wanted_clips([fabric], sequences)]
        lattices = {c: clip_lattice(folder / c).reshape(-1, GEOMETRY_DIM) for c in names}
        probs = []
        for c in names:         # a clip's mean window probabilities, as the real-video path reads a video
            x, _ = windows(lattices, {c: 0}, [c], centre, scale, clip_len, stride)
            with torch.no_grad():
                probs.append(model.probs(model.read_lattice(x.to(device))).mean(0).cpu().numpy())
        preds.append(int(np.mean(probs, 0).argmax()))
    # the stiffness a class stands for, as `clothgap eval measured` reads it
    pred_bending = with_predicted_values(pd.DataFrame({"pred": preds}))["pred_bending_N_m"]
    truth = [table2_class(f) for f in fabrics]
    steps, within = metrics.class_distance(truth, preds), metrics.within_one_bin(truth, preds)
    rows = [{"fabric": fabric, "pred": pred, "table2_class": t, "grid_steps": int(step), "within_one_bin": bool(w),
             "pred_bending_N_m": float(bending), "bending_N_m": measured_values(fabric)["bending_N_m"]}
            for fabric, pred, t, step, w, bending in zip(fabrics, preds, truth, steps, within, pred_bending)]
    rho = stats.spearmanr([r["pred_bending_N_m"] for r in rows], [r["bending_N_m"] for r in rows]).statistic
    return {"sequences": sequences, "fabrics": len(rows), "exact": int((steps == 0).sum()),
            "within_one_step": int((steps <= 1).sum()),
            # the goal's count, as `clothgap eval measured` counts it: at most one bin off in p and in k
            "within_one_bin": int(within.sum()),
            "mean_grid_steps": round(float(steps.mean()), 2),
            "bending_spearman": None if np.isnan(rho) else round(float(rho), 3), "rows": rows}


def load_run(run: Run, setting: str):
    """A run's finished clip ids, their true lattices (T, GEOMETRY_DIM), classes and split by sequence."""
    folder = run.sim_dir(setting)
    ids = run.done_clips(folder)
    lattices = {c: lat.reshape(-1, GEOMETRY_DIM) for c, lat in clip_lattices(run, setting, ids, progress=False).items()}
    labels = {c: int(read_meta(folder / c)["class_index"]) for c in ids}
    split = split_sequences(labels, run.config.train.val_fraction, run.config.train.test_fraction, run.config.seed)
    return ids, lattices, labels, split


def scores(truth: np.ndarray, pred: np.ndarray) -> dict:
    return {"top1": round(float((pred == truth).mean()), 4),
            "within_one": round(float(metrics.within_one_bin(truth, pred).mean()), 4),
            "stretching": round(float(metrics.stretch_correct(truth, pred).mean()), 4),
            "bending": round(float(metrics.bend_correct(truth, pred).mean()), 4)}


def load_transfer(other: str, setting: str, test_labels: dict[str, int], centre, scale, clip_len: int,
                  stride: int) -> tuple[str, torch.Tensor, torch.Tensor]:
    """Another run's test windows, checked (before any training) to be this run's test clips under the same classes."""
    run = Run.open(other)
    _, lattices, labels, split = load_run(run, setting)
    if {c: labels[c] for c in split["test"]} != test_labels:
        raise SystemExit(f"{other}: its test clips are not this run's; --transfer reads a run of the same clip ids "
                         "and classes (the same seed, classes and sequences a class)")
    x, y = windows(lattices, labels, split["test"], centre, scale, clip_len, stride)
    return str(run.root), x, y


def read_transfer(root: str, x: torch.Tensor, y: torch.Tensor, model, noise: float) -> dict:
    """``model``'s scores on another run's test windows (``load_transfer``), noised as this run's test windows."""
    x = x.to(next(model.parameters()).device)
    with torch.no_grad():
        pred = model.probs(model.read_lattice(x + noise * torch.randn_like(x))).argmax(1).cpu().numpy()
    return {"run": root, "windows": int(len(y)), **scores(y.numpy(), pred)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a run folder with finished sim clips")
    ap.add_argument("--setting", required=True)
    ap.add_argument("--noise", type=float, default=0.0, help="std of noise on the lattices (standardised units)")
    ap.add_argument("--per-coordinate", action="store_true", help="standardise each coordinate on its own")
    ap.add_argument("--clip-len", type=int, default=10)
    ap.add_argument("--stride", type=int, default=5)
    ap.add_argument("--centre", choices=("median", "frame"), default="median")
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reader", choices=("frames", "stats"), default="frames",
                    help="frames: the bottleneck's reader (per-frame MLP, LSTM); stats: an MLP on window statistics")
    ap.add_argument("--weight-decay", type=float, default=1e-4, help="AdamW's (the paper preset trains with 0.05)")
    ap.add_argument("--batch-size", type=int, default=64, help="windows a step (the paper preset's: 16)")
    ap.add_argument("--keep", choices=("last", "best"), default="last",
                    help="the last epoch, or the one with the best validation top-1 (as train.keep=best)")
    ap.add_argument("--device", default="cpu", help="where the reader trains and reads (cpu, cuda)")
    ap.add_argument("--transfer", nargs="*", default=[], metavar="OTHER_RUN",
                    help="also read the test clips of these runs (same clip ids, reshaped tables)")
    ap.add_argument("--measured", type=int, default=0, metavar="N",
                    help="also read N simulated clips of each measured fabric (their Table 2 classes)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    run = Run.open(args.run)
    ids, lattices, labels, split = load_run(run, args.setting)
    # Scaled as learn.geometry does (median centre, the median clip's RMS spread), or per coordinate.
    train = [lattices[c] for c in split["train"]]
    ends = np.cumsum([len(t) for t in train])
    centre = median_shape(np.concatenate(train), dict(enumerate(slice(e - len(t), e) for t, e in zip(train, ends))),
                          args.centre)
    scale = (np.concatenate([t - centre[:len(t)] for t in train]).std(0) + 1e-9 if args.per_coordinate else
             float(np.sqrt(np.median([((t - centre[:len(t)]) ** 2).mean() for t in train]))))
    xtr, ytr = windows(lattices, labels, split["train"], centre, scale, args.clip_len, args.stride)
    xte, yte = windows(lattices, labels, split["test"], centre, scale, args.clip_len, args.stride)
    xva, yva = windows(lattices, labels, split["val"], centre, scale, args.clip_len, args.stride)
    if not len(ytr) or not len(yte):
        raise SystemExit(f"{run.root}: {len(split['train'])} training and {len(split['test'])} test sequences give "
                         f"{len(ytr)} and {len(yte)} windows of {args.clip_len} frames; the reader needs both")
    if args.keep == "best" and not len(yva):
        raise SystemExit(f"{run.root}: --keep best needs validation windows, and the split has none")
    others = [load_transfer(other, args.setting, {c: labels[c] for c in split["test"]}, centre, scale, args.clip_len,
                            args.stride) for other in args.transfer]
    device = torch.device(args.device)
    xtr, ytr, xte, xva = xtr.to(device), ytr.to(device), xte.to(device), xva.to(device)
    torch.manual_seed(args.seed)
    # --keep best compares the epochs on one noise draw of the validation windows; the last epoch's draw is taken
    # after the test windows', so that a run that keeps the last epoch draws what it always drew
    xva_noised = xva + args.noise * torch.randn_like(xva) if args.keep == "best" else None
    # The run's lrcn with the bottleneck on (its CNN is built but never used here).
    cfg = dataclasses.replace(run.config.train, bottleneck=True)
    model = (build_model("lrcn", **model_args(cfg)) if args.reader == "frames" else
             StatsReader(GEOMETRY_DIM, cfg.hidden)).to(device)
    opt = torch.optim.AdamW(model.parameters(), 1e-3, weight_decay=args.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.epochs)
    best_top1, best_state, kept_epoch = -1.0, None, args.epochs
    for epoch in range(1, args.epochs + 1):
        model.train()
        order = torch.randperm(len(xtr), device=device)
        for i in range(0, len(order), args.batch_size):
            b = order[i:i + args.batch_size]
            loss = model.loss(model.read_lattice(xtr[b] + args.noise * torch.randn_like(xtr[b])), ytr[b])
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
        if args.keep == "best":
            model.eval()
            with torch.no_grad():
                top1 = float((model.probs(model.read_lattice(xva_noised)).argmax(1).cpu() == yva).float().mean())
            if top1 > best_top1:
                best_top1, kept_epoch = top1, epoch
                best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    if best_state is not None:
        model.load_state_dict(best_state)
    model.eval()
    with torch.no_grad():
        pred = model.probs(model.read_lattice(xte + args.noise * torch.randn_like(xte))).argmax(1).cpu().numpy()
        if xva_noised is None:
            xva_noised = xva + args.noise * torch.randn_like(xva)
        val_pred = (model.probs(model.read_lattice(xva_noised)).argmax(1).cpu().numpy()
                    if len(yva) else np.zeros(0, int))
    truth = yte.numpy()
    val_top1 = round(float((val_pred == yva.numpy()).mean()), 4) if len(yva) else None
    transfer = [read_transfer(root, x, y, model, args.noise) for root, x, y in others]
    measured = (read_measured(run, args.setting, model, args.measured, centre, scale, args.clip_len, args.stride)
                if args.measured else None)
    print(json.dumps({"run": str(run.root), "setting": args.setting, "clips": len(ids),
                      "test_sequences": len(split["test"]), "test_windows": int(len(truth)),
                      "noise": args.noise, "per_coordinate": args.per_coordinate, "epochs": args.epochs,
                      "clip_len": args.clip_len, "stride": args.stride, "centre": args.centre,
                      "val_windows": int(len(yva)), "val_top1": val_top1,
                      "reader": args.reader, "seed": args.seed, "weight_decay": args.weight_decay,
                      "batch_size": args.batch_size, "keep": args.keep, "kept_epoch": kept_epoch,
                      **scores(truth, pred),
                      **({"transfer": transfer} if transfer else {}),
                      **({"measured": measured} if measured else {}),
                      "seconds": round(time.perf_counter() - t0, 1)}))


if __name__ == "__main__":
    main()
