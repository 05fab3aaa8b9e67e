"""How much of the material class the simulated geometry itself carries: a probe on the sim clips.

A CNN trained on renders can only learn what the pixels carry, and the pixels
can only carry what the simulated 3D sequence carries. This probe skips the
renderer: it reads each 10-frame window of every simulated sequence of a
setting as the positions of a fixed 8 x 8 lattice of points of the cloth
(nearest vertex in uv space, so adaptive meshes work too), summarises the
window (mean and spread of each point over time, mean speed, bounding box) and
fits classifiers to the 54 classes and to the 6 stretching and 9 bending bins.

It is run under both split protocols (``learn.split``):

* ``sequence``: whole simulations on one side; a test of generalisation to new
  simulations, the number a model on renders should be compared with.
* ``subsequence``: the paper's protocol as we read it; windows of one simulation
  on both sides. The 1-nearest-neighbour classifier measures the leak: it is
  right when the closest training window is a neighbour from the same
  simulation, whatever the material.

The classifiers are deliberately plain (multinomial logistic regression, a
two-layer MLP, 1-NN on standardised features), trained full-batch in torch on
CPU (minutes for 2,592 sequences on 2 cores): the figures are a floor on what the geometry tells, not a
ceiling.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

from clothgap import seeding
from clothgap.errors import ConfigError
from clothgap.runs import Run, atomic_write_json, atomic_write_text
from eval import metrics
from sim.classes import class_indices
from sim.lattice import LATTICE, clip_lattice

TARGETS = {"class": 54, "stretching": 6, "bending": 9}
CLASSIFIERS = ("linear", "mlp", "nearest")


def window_features(lattice: np.ndarray) -> np.ndarray:
    """Features of one window (T, P, 3): per-point mean and std over time, mean speed, bounding box."""
    speed = np.linalg.norm(np.diff(lattice, axis=0), axis=-1).mean(axis=0) if len(lattice) > 1 else \
        np.zeros(lattice.shape[1], np.float32)
    box = np.concatenate([lattice.min(axis=(0, 1)), lattice.max(axis=(0, 1))])
    return np.concatenate([lattice.mean(0).ravel(), lattice.std(0).ravel(), speed, box]).astype(np.float32)


PIXEL_SIZE = 16               # side of the frames the pixel probe reads


def pixel_windows(run: Run, variant: str, setting: str, clip_len: int, stride: int, progress: bool = True):
    """Like ``load_windows``, from the rendered frames of a variant: each window's mean and spread
    over time of its frames shrunk to 16 x 16 px (what a model could memorise a clip by: texture,
    background, light), as the same (features, clip ids, starts, classes)."""
    from learn.dataset import build_cache

    cache = build_cache(run, variant, setting, PIXEL_SIZE, progress)
    frames = cache.frames
    feats, clips, starts, labels = [], [], [], []
    for cid, clip in cache.clips.items():
        for s in range(0, clip.num_frames - clip_len + 1, stride):
            window = np.asarray(frames[clip.offset + s: clip.offset + s + clip_len], np.float32) / 255
            feats.append(np.concatenate([window.mean(0).ravel(), window.std(0).ravel()]))
            clips.append(cid)
            starts.append(s)
            labels.append(clip.class_index)
    return np.stack(feats), np.array(clips), np.array(starts), np.array(labels)


def load_windows(run: Run, setting: str, clip_len: int, stride: int, progress: bool = True,
                 folder: Path | None = None, ids: list[str] | None = None):
    """Features (N, D), clip ids (N,), window starts (N,), classes (N,) of every finished sim clip
    (of the setting's folder, or of ``folder``: e.g. the measured fabrics'; or of those ``ids`` there)."""
    folder = folder or run.sim_dir(setting)
    ids = run.done_clips(folder) if ids is None else ids
    if not ids:
        raise ConfigError(f"no finished sim clips in {folder}: run `clothgap sim {run.root}` first")
    feats, clips, starts, labels = [], [], [], []
    for cid in tqdm(ids, desc=f"probe {setting}", unit="clip", disable=not progress):
        lattice = clip_lattice(folder / cid)
        label = int(json.loads((folder / cid / "meta.json").read_text())["class_index"])
        for s in range(0, len(lattice) - clip_len + 1, stride):
            feats.append(window_features(lattice[s:s + clip_len]))
            clips.append(cid)
            starts.append(s)
            labels.append(label)
    return np.stack(feats), np.array(clips), np.array(starts), np.array(labels)


def _targets(labels: np.ndarray) -> dict[str, np.ndarray]:
    pk = np.array([class_indices(int(c)) for c in labels])
    return {"class": labels, "stretching": pk[:, 0], "bending": pk[:, 1]}


def within_one_bin(target: str, pred: np.ndarray, truth: np.ndarray) -> float:
    """Share of predictions at most one bin off (in both stretching and bending for the 54 classes)."""
    if target == "class":
        return float(metrics.within_one_bin(truth, pred).mean())
    return float((np.abs(pred.astype(int) - truth.astype(int)) <= 1).mean())


def fit(kind: str, x_train: np.ndarray, y_train: np.ndarray, classes: int,
        seed: int = 0) -> Callable[[np.ndarray], np.ndarray]:
    """One plain classifier trained on (x_train, y_train): a function from features to class probabilities
    (N, classes); the nearest neighbour's are its label's one-hot."""
    mean, std = x_train.mean(0), x_train.std(0) + 1e-6
    xt = torch.from_numpy((x_train - mean) / std)

    def standardised(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(((x - mean) / std).astype(np.float32))

    if kind == "nearest":
        def nearest(x: np.ndarray) -> np.ndarray:
            out = np.zeros((len(x), classes), np.float32)
            out[np.arange(len(x)), y_train[torch.cdist(standardised(x), xt).argmin(1).numpy()]] = 1
            return out
        return nearest
    torch.manual_seed(seed)
    y = torch.from_numpy(y_train.astype(np.int64))
    if kind == "linear":
        # Multinomial logistic regression with an L2 penalty, solved by L-BFGS.
        model = torch.nn.Linear(xt.shape[1], classes)
        opt = torch.optim.LBFGS(model.parameters(), lr=1.0, max_iter=200, history_size=20,
                                line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            loss = torch.nn.functional.cross_entropy(model(xt), y) + 1e-1 * model.weight.pow(2).sum()
            loss.backward()
            return loss

        opt.step(closure)
    elif kind == "mlp":
        model = torch.nn.Sequential(torch.nn.Linear(xt.shape[1], 256), torch.nn.ReLU(), torch.nn.Dropout(0.3),
                                    torch.nn.Linear(256, 256), torch.nn.ReLU(), torch.nn.Dropout(0.3),
                                    torch.nn.Linear(256, classes))
        opt = torch.optim.AdamW(model.parameters(), lr=3e-3, weight_decay=1e-2)
        for _ in range(300):
            opt.zero_grad()
            torch.nn.functional.cross_entropy(model(xt), y).backward()
            opt.step()
    else:
        raise ValueError(f"unknown classifier {kind!r}; known: {', '.join(CLASSIFIERS)}")
    model.eval()

    def probabilities(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return torch.softmax(model(standardised(x)), 1).numpy()
    return probabilities


def fit_predict(kind: str, x_train: np.ndarray, y_train: np.ndarray, x_test: np.ndarray, classes: int,
                seed: int = 0) -> np.ndarray:
    """Predicted labels of ``x_test`` from one plain classifier trained on (x_train, y_train)."""
    return fit(kind, x_train, y_train, classes, seed)(x_test).argmax(1)


def probe(run: Run, setting: str, clip_len: int = 10, stride: int = 10, test_fraction: float = 1 / 6,
          classifiers: tuple[str, ...] = CLASSIFIERS, progress: bool = True, pixels: str | None = None) -> dict:
    """Test accuracy of each classifier x target under both split protocols, with chance levels.

    ``pixels``: probe the rendered frames of this render variant instead of the geometry.
    """
    from learn.split import parse_item, split_sequences, split_subsequences

    t0 = time.perf_counter()
    if pixels:
        x, clips, starts, labels = pixel_windows(run, pixels, setting, clip_len, stride, progress)
    else:
        x, clips, starts, labels = load_windows(run, setting, clip_len, stride, progress)
    first = {c: int(l) for c, l in zip(clips, labels)}
    seed = run.config.seed
    frames = int(starts.max()) + clip_len
    protocols = {
        "sequence": split_sequences(first, 0.0, test_fraction, seed),
        "subsequence": split_subsequences(first, frames, clip_len, stride, 0.0, test_fraction, seed),
    }
    key = {(c, int(s)): i for i, (c, s) in enumerate(zip(clips, starts))}
    of_clip: dict[str, list[int]] = {}
    for i, c in enumerate(clips):
        of_clip.setdefault(c, []).append(i)
    all_targets = _targets(labels)
    results = []
    for protocol, split in protocols.items():
        rows = {}
        for part in ("train", "test"):
            idx = []
            for item in split[part]:
                clip, start = parse_item(item)
                idx += of_clip[clip] if start is None else [key[(clip, start)]]
            rows[part] = np.array(sorted(idx))
        tr, te = rows["train"], rows["test"]
        for target, classes in TARGETS.items():
            y = all_targets[target]
            for kind in classifiers:
                pred = fit_predict(kind, x[tr], y[tr], x[te], classes, seed)
                right = pred == y[te]
                # per true bin of a factor (its grid index): which stiffnesses the geometry tells apart
                by_bin = ({"accuracy_by_true_bin": {int(b): float(right[y[te] == b].mean())
                                                    for b in np.unique(y[te])}} if target != "class" else {})
                results.append({"protocol": protocol, "target": target, "classifier": kind,
                                "accuracy": float(right.mean()), "chance": 1.0 / classes,
                                "within_one_bin": within_one_bin(target, pred, y[te]),
                                "train_windows": int(len(tr)), "test_windows": int(len(te)), **by_bin})
    return {"setting": setting, "source": f"pixels of {pixels}" if pixels else "geometry",
            "clips": int(len(first)), "windows": int(len(x)), "clip_len": clip_len,
            "stride": stride, "features": int(x.shape[1]), "lattice": LATTICE, "results": results,
            "seconds": round(time.perf_counter() - t0, 1)}


def fit_classes(run: Run, setting: str, clip_len: int = 10, stride: int = 10,
                classifiers: tuple[str, ...] = CLASSIFIERS, progress: bool = True) -> dict:
    """Each classifier trained on the windows of every simulated clip of the setting (the 54 classes): what
    ``probe_measured`` reads measured clips with, fitted once for any number of measured folders."""
    x, clips, _, labels = load_windows(run, setting, clip_len, stride, progress)
    return {"setting": setting, "clip_len": clip_len, "stride": stride, "clips": int(len(set(clips))),
            "train_windows": int(len(x)), "features": int(x.shape[1]),
            "classifiers": {kind: fit(kind, x, labels, TARGETS["class"], run.config.seed) for kind in classifiers}}


def _spearman(frame: pd.DataFrame, a: str, b: str, resamples: int, confidence: float,
              rng: np.random.Generator) -> dict:
    both = frame[[a, b]].dropna()          # a fabric outside Table 2 has no p~, k~
    return (metrics.bootstrap_correlation(both[a], both[b], method="spearman", resamples=resamples,
                                          confidence=confidence, rng=rng).as_dict("spearman")
            | {"fabrics": len(both)})


def probe_measured(run: Run, setting: str, sequences: int | None = None, clip_len: int = 10, stride: int = 10,
                   classifiers: tuple[str, ...] = CLASSIFIERS, progress: bool = True,
                   folder: Path | None = None, fitted: dict | None = None) -> dict:
    """What the geometry of the measured fabrics' clips says their class is: each classifier trained on every
    simulated clip of the setting (``fit_classes``: the 54 classes at the run's class density, the basis fabric's
    unless ``sim.density_range`` draws one per clip) reads the windows
    of the clips simulated with the fabrics' own tables (``run.measured_sim_dir``); a fabric's class is the argmax
    of its clips' mean probabilities, set beside its Table 2 class by ``eval.measured.fabric_table``, as for a
    network's predictions.

    ``sequences``: read clips 0..N-1 of each fabric (``sim.measured.clip_name``); default every finished one.
    ``folder``: the measured clips' folder, if not ``run.measured_sim_dir(setting)``; a clip's density is its
    meta's (a folder simulated at another density reports that one). ``fitted``: ``fit_classes``'s result, to
    read several folders with one fit. What this tells is what the measured-fabric goal meets in the simulation
    itself, read by plain classifiers (a floor on what the geometry carries, like ``probe``).
    """
    from eval import predictions as preds
    from eval.measured import fabric_table, match_table
    from sim.measured import clip_name, table2_fabrics, wanted_clips

    t0 = time.perf_counter()
    folder = folder or run.measured_sim_dir(setting)
    done = run.done_clips(folder)
    if sequences is not None:
        wanted = {clip_name(f, n) for f, n in wanted_clips(table2_fabrics(), sequences)}
        done = [c for c in done if c in wanted]
    if not done:
        raise ConfigError(f"no simulated measured-fabric clips in {folder}"
                          f"{'' if sequences is None else f' among the first {sequences} of each fabric'} "
                          f"(`clothgap eval learnability {run.root} --measured N` simulates N a fabric)")
    fitted = fitted or fit_classes(run, setting, clip_len, stride, classifiers, progress)
    mx, mclips, _, mlabels = load_windows(run, setting, fitted["clip_len"], fitted["stride"], progress,
                                          folder=folder, ids=done)
    metas = {c: json.loads((folder / c / "meta.json").read_text()) for c in done}
    cfg, seed = run.config.eval, run.config.seed
    results = []
    for kind, classify in fitted["classifiers"].items():
        probs = classify(mx)
        # per clip: the mean of its windows' probabilities, as eval.real does for a video's sub-sequences
        per_clip = pd.DataFrame(probs, columns=preds.PROB_COLUMNS).groupby(mclips, sort=True).mean()
        videos = per_clip.assign(video=per_clip.index, pred=per_clip.to_numpy().argmax(1),
                                 fabric=[metas[c]["fabric"] for c in per_clip.index])
        table = fabric_table(videos)
        density = {f: float(np.mean([metas[c]["density"] for c in g.index])) for f, g in videos.groupby("fabric")}
        table["density_kg_m2"] = table["fabric"].map(density)

        def rng_for(*parts: str, kind=kind) -> np.random.Generator:
            return seeding.rng(seed, 0, seeding.EVAL, "learnability-measured", setting, kind, *parts)

        match = match_table(table, resamples=cfg.bootstrap, confidence=cfg.confidence,
                            rng_for=lambda _match, score: rng_for(score))
        scores = {r.score: {"value": r.value, "value_lo": r.value_lo, "value_hi": r.value_hi}
                  for r in match.itertuples() if r.score in ("exact", "within1", "class_dist")}
        correlations = {f"{a}~{b}": _spearman(table, a, b, cfg.bootstrap, cfg.confidence, rng_for(a, b))
                        for a, b in (("pred_k", "bending_N_m"), ("pred_k", "table2_k_est"),
                                     ("pred_p", "stretching_N_m"), ("pred_p", "table2_p_est"),
                                     ("pred_k", "density_kg_m2"))}
        rows = json.loads(table.drop(columns=["class_source"]).to_json(orient="records"))
        results.append({"classifier": kind, "fabrics": rows, "scores": scores, "spearman": correlations,
                        "window_within1": float(metrics.within_one_bin(mlabels, probs.argmax(1)).mean())})
    return {"setting": setting, "source": "geometry", "clips": fitted["clips"],
            "train_windows": fitted["train_windows"], "measured_clips": len(done), "measured_windows": int(len(mx)),
            "clip_len": fitted["clip_len"], "stride": fitted["stride"], "features": fitted["features"],
            "lattice": LATTICE, "results": results, "seconds": round(time.perf_counter() - t0, 1)}


def markdown_measured(report: dict) -> str:
    """Per classifier: each fabric's class from its simulated geometry beside its Table 2 class, and the scores."""
    lines = [f"# What the simulated geometry says the measured fabrics are: {report['setting']}", "",
             f"Classifiers trained on {report['train_windows']} windows of {report['clip_len']} frames of the "
             f"setting's simulated clips (the 54 classes) read {report['measured_windows']} windows of "
             f"{report['measured_clips']} clips simulated with each fabric's own tables; a fabric's class is the "
             "argmax of its windows' mean probabilities. Intervals resample fabrics.", ""]
    for r in report["results"]:
        s, c = r["scores"], r["spearman"]
        lines += [f"## {r['classifier']}", "",
                  "| Fabric | Clips | Geometry says (p, k) | Table 2 (p, k) | Within one bin | Grid steps | "
                  "Bending (N*m) | Stretching (N/m) | Density (kg/m^2) |", "|---|---|---|---|---|---|---|---|---|"]
        lines += [f"| {f['fabric']} | {f['clips']} | ({f['pred_p']:g}, {f['pred_k']:g}) | ({f['table2_p']:g}, "
                  f"{f['table2_k']:g}) | {'yes' if f['within1'] else 'no'} | {f['class_dist']:g} | "
                  f"{f['bending_N_m']:.3g} | {f['stretching_N_m']:.4g} | {f['density_kg_m2']:.3g} |"
                  for f in r["fabrics"]]
        lines += ["", "| Score over fabrics | Value [95% interval] |", "|---|---|"]
        lines += [f"| {name} | {metrics.Estimate(v['value'], v['value_lo'], v['value_hi']).fmt(1.0, 2)} |"
                  for name, v in s.items()]
        lines += [f"| Spearman {pair.replace('~', ' vs ')} | "
                  f"{metrics.Estimate(v['spearman'], v['spearman_lo'], v['spearman_hi']).fmt(1.0, 2)} |"
                  for pair, v in c.items()]
        lines += [f"| windows within one bin of Table 2 | {100 * r['window_within1']:.1f} % |", ""]
    return "\n".join(lines)


def markdown(report: dict) -> str:
    """One table per protocol: targets down, classifiers across, accuracy in percent (chance)."""
    source = report.get("source", "geometry")
    what = (f"an {report['lattice']} x {report['lattice']} lattice" if source == "geometry"
            else f"{PIXEL_SIZE} x {PIXEL_SIZE} px frames")
    title = "What the simulated geometry tells" if source == "geometry" else f"What the {source} tell"
    lines = [f"# {title}: {report['setting']}", "",
             f"{report['clips']} simulated sequences, {report['windows']} windows of {report['clip_len']} frames "
             f"(every {report['stride']}), {report['features']} features from {what}. "
             "Test accuracy, % (at most one bin off, %); chance in brackets.", ""]
    res = report["results"]
    kinds = list(dict.fromkeys(r["classifier"] for r in res))
    for protocol in dict.fromkeys(r["protocol"] for r in res):
        lines += [f"## split by {protocol}", "", "| target | " + " | ".join(kinds) + " |",
                  "|---|" + "---|" * len(kinds)]
        for target in TARGETS:
            cells = {r["classifier"]: r for r in res if r["protocol"] == protocol and r["target"] == target}
            chance = next(iter(cells.values()))["chance"]
            lines.append(f"| {target} ({100 * chance:.1f}) | "
                         + " | ".join(f"{100 * cells[k]['accuracy']:.1f} ({100 * cells[k]['within_one_bin']:.0f})"
                                      for k in kinds) + " |")
        lines.append("")
    return "\n".join(lines)


def run_probe(run: Run, settings: list[str] | None = None, progress: bool = True, pixels: str | None = None,
              **kwargs) -> dict:
    """Probe each simulated setting; write ``eval/learnability.{json,md}`` (``learnability-pixels-<variant>``
    with ``pixels``)."""
    def source(setting: str) -> Path:
        return run.render_dir(pixels, setting) if pixels else run.sim_dir(setting)

    settings = settings or [s for s in run.config.sim.settings() if run.done_clips(source(s))]
    reports = [probe(run, s, progress=progress, pixels=pixels, **kwargs) for s in settings]
    name = f"learnability-pixels-{pixels}" if pixels else "learnability"
    atomic_write_json(run.eval_dir / f"{name}.json", {"settings": reports})
    atomic_write_text(run.eval_dir / f"{name}.md", "\n\n".join(markdown(r) for r in reports))
    return {"settings": settings, "written": str(run.eval_dir / f"{name}.md")}


def measured_reading(result: dict) -> dict:
    """One classifier's reading of the measured fabrics (an item of ``probe_measured``'s ``results``) in short:
    fabrics within one bin of Table 2, of how many, mean grid steps, and the bending rank against the measured
    bending (its estimate with interval)."""
    fabrics = result["fabrics"]
    return {"within1_fabrics": int(sum(f["within1"] for f in fabrics)), "fabrics": len(fabrics),
            "class_dist": result["scores"]["class_dist"]["value"],
            "bending_rank": result["spearman"]["pred_k~bending_N_m"]}


def run_probe_measured(run: Run, sequences: int, settings: list[str] | None = None, progress: bool = True,
                       **kwargs) -> dict:
    """Simulate ``sequences`` clips of each Table 2 fabric under each setting probed (``settings``, default every
    simulated one; finished clips kept), probe each with ``probe_measured``; write
    ``eval/learnability-measured.{json,md}``."""
    from sim.measured import table2_fabrics
    from sim.stage import simulate_measured

    settings = settings or run.simulated_settings()
    simulate_measured(run, table2_fabrics(), sequences, progress, settings=settings)
    reports = []
    for setting in settings:          # written after each setting: a later one's failure keeps the earlier ones
        reports.append(probe_measured(run, setting, sequences, progress=progress, **kwargs))
        atomic_write_json(run.eval_dir / "learnability-measured.json", {"sequences": sequences, "settings": reports})
        atomic_write_text(run.eval_dir / "learnability-measured.md",
                          "\n\n".join(markdown_measured(r) for r in reports))
    return {"settings": settings, "written": str(run.eval_dir / "learnability-measured.md")}
