"""eval.stage / eval.tables on a fake run: rendered clips, splits and train folders on disk,
and a stub predictor instead of a trained network (fast, and independent of learn/)."""

import json
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image
from scipy import stats

from clothgap.config import preset
from clothgap.runs import Run, clip_id, mark_done
from eval import classes, tables
from eval import predictions as preds
from eval.stage import predict_all, run_eval
from eval.trained import finished_models

CLASSES = (0, 8, 45, 53)
VARIANT_SETTINGS = {  # two render axes: texture and tonemap
    "paper": {"texture": "random", "tonemap": "srgb_clip"},
    "grid": {"texture": "grid", "tonemap": "srgb_clip"},
    "reinhard": {"texture": "random", "tonemap": "reinhard"},
}
# How often the stub is right: in-domain 0.9, otherwise lower by how many axes differ.
HIT_RATE = {0: 0.9, 1: 0.5, 2: 0.2}
SETTING = "wind-uniform1"


def make_fake_run(root: Path, variants=("paper", "grid"), models=("lrcn",), seeds=(0,), per_class=4,
                  frames=4, **eval_settings) -> Run:
    cfg = preset("smoke")
    cfg = replace(cfg, render=replace(cfg.render, variants=tuple(variants)),
                  train=replace(cfg.train, models=tuple(models), seeds=tuple(seeds)),
                  eval=replace(cfg.eval, bootstrap=100, **eval_settings))
    run = Run.create_or_resume(root, cfg)
    setting = cfg.sim.settings()[0]
    ids = []
    for i, cls in enumerate(np.repeat(CLASSES, per_class)):
        cid = clip_id(i)
        ids.append(cid)
        for v in variants:
            folder = run.render_dir(v, setting) / cid
            (folder / "ldr").mkdir(parents=True)
            for f in range(frames):
                img = np.full((16, 16, 3), (40 * f + 10 * i) % 255, np.uint8)
                img[:, :, ["paper", "grid", "reinhard"].index(v)] = 200
                Image.fromarray(img).save(folder / "ldr" / f"{f:04d}.png")
            meta = {"clip_id": cid, "index": i, "setting": setting, "motion": "wind", "remeshing": "uniform1",
                    "class_index": int(cls), "variant": v,
                    "render": {**VARIANT_SETTINGS[v], "resolution": 16, "spp": 1, "sampler_seed": i,
                               "draws": {"texture": {"tile_m": 0.1 + i}}}}
            (folder / "meta.json").write_text(json.dumps(meta))
            mark_done(folder)
    test = ids[::2]
    run.split_path(setting).parent.mkdir(parents=True, exist_ok=True)
    run.split_path(setting).write_text(json.dumps({"by": "sequence", "seed": 0, "train": ids[1::2], "val": [],
                                                   "test": test}))
    for v in variants:
        for m in models:
            for s in seeds:
                folder = run.train_dir(setting, v, m, s)
                folder.mkdir(parents=True)
                (folder / "checkpoint.pt").write_bytes(b"stub")
                pd.DataFrame({"epoch": [1, 2, 3], "train_loss": [3.0, 2.0, 1.5], "train_acc": [0.2, 0.4, 0.6],
                              "val_loss": [np.nan] * 3, "val_acc": [np.nan] * 3, "lr": [1e-3] * 3,
                              "seconds": [1.0] * 3}).to_csv(folder / "metrics.csv", index=False)
                mark_done(folder)
    return run


def stub_predictor(train_dir: Path, clip_dirs: list[Path]) -> pd.DataFrame:
    """Three sub-sequences per clip; right with a rate set by how far train and test variants differ."""
    train_variant = train_dir.parts[-3]
    rows = []
    for d in clip_dirs:
        meta = json.loads((d / "meta.json").read_text())
        axes = sum(VARIANT_SETTINGS[train_variant][k] != VARIANT_SETTINGS[meta["variant"]][k]
                   for k in VARIANT_SETTINGS["paper"])
        rng = np.random.default_rng(zlib.crc32("/".join(train_dir.parts[-3:] + d.parts[-3:]).encode()))
        for start in (0, 5, 10):
            truth = meta["class_index"]
            pred = truth if rng.random() < HIT_RATE[axes] else int(rng.choice([c for c in CLASSES if c != truth]))
            probs = np.full(54, 0.1 / 53)
            probs[pred] = 0.9
            rows.append({"clip_id": meta["clip_id"], "start": start, "class_index": truth, "pred": pred,
                         "probs": probs})
    return pd.DataFrame(rows)


def test_run_eval_writes_tables_and_resumes(tmp_path):
    run = make_fake_run(tmp_path / "run", models=("lrcn", "base1"), seeds=(0, 1))
    out = run_eval(run, progress=False, predictor=stub_predictor)
    assert out["cells"] == 2 * 2 * 2 and out["predicted"] == 2 * 2 * 2 * 2
    assert set(out["seconds"]) == {"predict", "tables_and_figures"} and min(out["seconds"].values()) >= 0
    assert "seconds" not in json.loads((run.eval_dir / "summary.json").read_text())    # a rerun rewrites it as is

    ev = run.eval_dir
    pred_csv = ev / "predictions" / "wind-uniform1" / "paper" / "lrcn" / "s1" / "grid.csv"
    frame = pd.read_csv(pred_csv)
    assert len(frame) == 8 * 3 and "prob_53" in frame

    table3 = pd.read_csv(ev / "table3.csv")
    assert list(table3["texture"]) == ["grid", "random"]          # texture family from the rendered meta
    assert {"base1_acc", "lrcn_acc", "lrcn_acc_lo", "lrcn_top3", "lrcn_bend_acc", "lrcn_class_dist",
            "lrcn_seq_acc", "lrcn_checkpoints"} <= set(table3.columns)
    assert table3.columns.get_loc("base1_acc") < table3.columns.get_loc("lrcn_acc")   # paper's column order
    assert (table3["lrcn_acc_lo"] <= table3["lrcn_acc"]).all() and (table3["lrcn_acc"] <= table3["lrcn_acc_hi"]).all()
    md = (ev / "table3.md").read_text()
    assert "CNN+LSTM" in md and "train/wind-uniform1/paper/lrcn/s0/checkpoint.pt" in md

    gap = pd.read_csv(ev / "domain_gap.csv")
    assert len(gap) == 8
    off = gap[(gap.train_variant == "paper") & (gap.test_variant == "grid") & (gap.model == "lrcn")].iloc[0]
    on = gap[(gap.train_variant == "paper") & (gap.test_variant == "paper") & (gap.model == "lrcn")].iloc[0]
    assert off["drop"] == pytest.approx(on["acc"] - off["acc"])
    assert off["drop"] > 0 and off["drop_lo"] <= off["drop"] <= off["drop_hi"]
    assert on["drop"] == 0
    # gain: what training on a variant buys over the run's first (paper) on the same test variant, paired
    grid_on_paper = gap[(gap.train_variant == "grid") & (gap.test_variant == "paper") & (gap.model == "lrcn")].iloc[0]
    assert grid_on_paper["gain"] == pytest.approx(grid_on_paper["acc"] - on["acc"])
    assert grid_on_paper["gain"] < 0 and grid_on_paper["gain_lo"] <= grid_on_paper["gain"] <= grid_on_paper["gain_hi"]
    assert on["gain"] == 0 and off["gain"] == 0
    # in_domain_gain: a variant read in its own look against paper read in its own; only on in-domain rows
    grid_on_grid = gap[(gap.train_variant == "grid") & (gap.test_variant == "grid") & (gap.model == "lrcn")].iloc[0]
    assert grid_on_grid["in_domain_gain"] == pytest.approx(grid_on_grid["acc"] - on["acc"])
    assert grid_on_grid["in_domain_gain_lo"] <= grid_on_grid["in_domain_gain"] <= grid_on_grid["in_domain_gain_hi"]
    assert on["in_domain_gain"] == 0 and np.isnan(off["in_domain_gain"]) and np.isnan(grid_on_paper["in_domain_gain"])
    # correlation of predicted with true stiffness coefficients, beside accuracy, per (train, test) pair
    for column in tables.CORRELATION_COLUMNS:
        assert {column, f"{column}_lo", f"{column}_hi"} <= set(gap.columns)
    assert on["k_spearman"] > off["k_spearman"]
    lo, hi = on["k_spearman_lo"], on["k_spearman_hi"]      # none where many resamples of few sequences lack a rank
    assert (np.isnan(lo) and np.isnan(hi)) or lo <= on["k_spearman"] <= hi
    seq = pd.concat([preds.per_sequence(preds.load(ev / "predictions" / "wind-uniform1" / "paper" / "lrcn" /
                                                   f"s{s}" / "grid.csv")) for s in (0, 1)])
    assert off["p_spearman"] == pytest.approx(stats.spearmanr(classes.p_value(seq["pred"]),
                                                              classes.p_value(seq["class_index"])).statistic, rel=1e-4)
    assert off["k_pearson"] == pytest.approx(stats.pearsonr(np.log(classes.k_value(seq["pred"])),
                                                            np.log(classes.k_value(seq["class_index"]))).statistic,
                                             rel=1e-4)

    summary = json.loads((ev / "summary.json").read_text())
    assert summary["variant_axes"] == ["texture"]          # per-clip draws and seeds are not axes
    assert summary["files"]["figures"]["confusion"] and (run.root / summary["files"]["figures"]["confusion"][0]).is_file()

    again = run_eval(run, progress=False, predictor=stub_predictor)     # resumable: nothing predicted again
    assert again["predicted"] == 0 and again["reused"] == 16


def test_every_model_of_a_setting_predicts_a_test_variant_in_a_row(tmp_path):
    """So that a caching predictor reads each test variant's frames once; the cells keep the models' order."""
    run = make_fake_run(tmp_path / "run", models=("lrcn", "base1"), seeds=(0, 1))
    calls = []

    def recording(train_dir: Path, clip_dirs: list[Path]) -> pd.DataFrame:
        calls.append((train_dir.relative_to(run.root).parts[1:], clip_dirs[0].parts[-3]))
        return stub_predictor(train_dir, clip_dirs)

    cells, counts, _ = predict_all(run, finished_models(run), recording, progress=False)
    assert [v for _, v in calls] == ["paper"] * 8 + ["grid"] * 8 and counts["predicted"] == 16
    assert [c[0] for c in calls[:8]] == [c[0] for c in calls[8:]]
    assert list(cells) == [(SETTING, train, model, test) for train in ("paper", "grid") for model in ("lrcn", "base1")
                           for test in ("paper", "grid")]
    for key, cell in cells.items():
        assert cell.frame["seed"].tolist() == [0] * 24 + [1] * 24
        assert cell.sources == [f"train/{SETTING}/{key[1]}/{key[2]}/s{s}/checkpoint.pt" for s in (0, 1)]


@pytest.mark.slow
def test_a_seed_ensemble_is_scored_as_one_model_beside_the_seeds_pooled(tmp_path):
    run = make_fake_run(tmp_path / "run", variants=("paper",), seeds=(0, 1, 2), seed_ensemble=True)
    run_eval(run, progress=False, predictor=stub_predictor)
    results = pd.read_csv(run.eval_dir / "results.csv")
    row = results[results.model == "lrcn-avg3"].iloc[0]
    assert row["seeds"] == "0 1 2" and row["in_domain"]
    # The ensemble by hand: each window's probabilities averaged over the three seeds' saved predictions.
    folder = run.eval_dir / "predictions" / "wind-uniform1" / "paper" / "lrcn"
    frames = [preds.load(folder / f"s{s}" / "paper.csv").sort_values(["clip_id", "start"]) for s in (0, 1, 2)]
    mean = np.mean([preds.probs_of(f) for f in frames], axis=0)
    expected = (mean.argmax(axis=1) == frames[0]["class_index"].to_numpy()).mean()
    assert row["acc"] == pytest.approx(expected)
    # Three seeds right 90 % of the time each, independently: the majority is right more often than one seed.
    pooled = results[results.model == "lrcn"].iloc[0]
    assert row["acc"] > pooled["acc"]
    table3 = pd.read_csv(run.eval_dir / "table3.csv")
    assert table3.columns.get_loc("lrcn_acc") < table3.columns.get_loc("lrcn-avg3_acc")
    assert table3["lrcn-avg3_seeds"].iloc[0] == "0 1 2"
    assert "CNN+LSTM (RGB-V), 3 seeds averaged" in (run.eval_dir / "table3.md").read_text()
    off = make_fake_run(tmp_path / "off", variants=("paper",), seeds=(0, 1))     # the default: no ensemble
    run_eval(off, progress=False, predictor=stub_predictor)
    assert set(pd.read_csv(off.eval_dir / "results.csv").model) == {"lrcn"}


def test_confusion_figures_drawn_in_the_pool_are_the_bytes_drawn_here(tmp_path, monkeypatch):
    from eval import stage

    run = make_fake_run(tmp_path / "run", variants=("paper", "grid", "reinhard"))
    run_eval(run, progress=False, predictor=stub_predictor)         # 9 figures: too few for a pool
    folder = run.eval_dir / "figures" / "confusion"
    here = {p: p.read_bytes() for p in folder.rglob("*.png")}
    assert len(here) == 9
    for p in here:
        p.unlink()
    pools = []
    monkeypatch.setattr(stage, "pool_size", lambda items, min_items, min_cpus: 2)
    monkeypatch.setattr(stage, "spawn_pool", lambda n, spawn=stage.spawn_pool: pools.append(n) or spawn(n))
    run_eval(run, progress=False, predictor=stub_predictor)
    assert pools == [2]
    assert {p: p.read_bytes() for p in folder.rglob("*.png")} == here


def test_axis_ranking_prefers_the_axis_that_closes_the_gap():
    settings = VARIANT_SETTINGS
    # Tested on "grid": training on grid itself 0.9; changing texture (paper->grid) closes a lot,
    # the tonemap does not matter for a grid target.
    acc = {("paper", "grid"): 0.5, ("grid", "grid"): 0.9, ("reinhard", "grid"): 0.2}
    rows = [{"setting": "s", "model": "lrcn", "train_variant": a, "test_variant": t, "acc": v}
            for (a, t), v in acc.items()]
    ranking = tables.rank_axes(pd.DataFrame(rows), settings)
    assert list(ranking["axis"]) == ["texture", "tonemap"]
    top = ranking.iloc[0]
    assert top["clean"] and top["mean_gain"] == pytest.approx(0.4) and top["mean_share"] == pytest.approx(1.0)


def test_settings_that_the_variants_only_change_together_are_one_axis():
    # a camera variant changes noise and vignetting at once: no pair of variants can tell them apart
    settings = {"paper": {"texture": "random", "noise": 0.0, "vignetting": 0.0},
                "grid": {"texture": "grid", "noise": 0.0, "vignetting": 0.0},
                "camera": {"texture": "random", "noise": 0.01, "vignetting": 0.3}}
    assert tables.axis_groups(settings) == {"noise+vignetting": ["noise", "vignetting"], "texture": ["texture"]}
    acc = {("paper", "camera"): 0.2, ("camera", "camera"): 0.5, ("grid", "camera"): 0.1}
    rows = [{"setting": "s", "model": "lrcn", "train_variant": a, "test_variant": t, "acc": v}
            for (a, t), v in acc.items()]
    ranking = tables.rank_axes(pd.DataFrame(rows), settings)
    camera = ranking.set_index("axis").loc["noise+vignetting"]
    assert camera["clean"] and camera["pairs"] == 1 and camera["mean_gain"] == pytest.approx(0.3)   # paper->camera
    assert "noise" not in set(ranking["axis"]) and "vignetting" not in set(ranking["axis"])


def test_missing_split_is_named(tmp_path):
    run = make_fake_run(tmp_path / "run")
    run.split_path("wind-uniform1").unlink()
    with pytest.raises(Exception, match="splits/wind-uniform1.json"):
        run_eval(run, progress=False, predictor=stub_predictor)


def test_report_is_self_contained(tmp_path, monkeypatch):
    import re

    from eval.report import write_report
    from sim import analysis

    from tests.conftest import coarse_analysis_setup

    # The real Table 2 on a coarse strip: this test reads what the report shows of it; its accuracy is
    # tests/test_sim_analysis.py's (the same coarse set-up there).
    coarse = coarse_analysis_setup()
    full_table2 = analysis.table2
    monkeypatch.setattr(analysis, "table2", lambda out, device="cpu": full_table2(out, device=device, setup=coarse))
    run = make_fake_run(tmp_path / "run", variants=("paper", "grid"), models=("lrcn",), sim_analysis=("table2",))
    out = run_eval(run, progress=False, predictor=stub_predictor)      # eval.sim_analysis runs `sim table2`
    assert out["sim_analysis"] == {"table2": "sim_analysis/table2.csv"}
    assert "royal-target" in (run.root / "sim_analysis" / "table2.csv").read_text()
    path = write_report(run)
    doc = path.read_text()
    assert path == run.root / "report" / "report.html"
    for section in ("Table 3", "Confusion matrices", "Learning curves", "Sample frames", "Domain gap", "table2.csv",
                    "k_spearman"):
        assert section in doc
    # figures are embedded; the run's files (config, checkpoints, tables) are relative links that resolve
    assert 'href="../train/wind-uniform1/paper/lrcn/s0/checkpoint.pt"' in doc
    assert 'href="../config.json"' in doc
    refs = re.findall(r'(?:src|href)\s*=\s*"([^"]*)"', doc)
    assert refs and any(r.startswith("data:image/png;base64,") for r in refs)
    for ref in refs:
        assert ref.startswith(("data:image/png;base64,", "data:image/jpeg;base64,", "#")) or \
            (path.parent / ref).exists(), ref
    assert all(r.startswith("data:") for r in re.findall(r'src\s*=\s*"([^"]*)"', doc))
    assert "<link" not in doc and "@import" not in doc and "url(" not in doc


def test_the_sim_analyses_simulate_on_the_runs_sim_device_and_are_kept_once_written(tmp_path, monkeypatch):
    from eval.stage import run_sim_analysis
    from sim import analysis

    run = make_fake_run(tmp_path / "run", sim_analysis=("table2", "sensitivity"))
    calls = []

    def fake(name, last):
        def write(out, device="cpu", **_):
            calls.append((name, device))
            (out / last).parent.mkdir(parents=True, exist_ok=True)
            (out / last).write_text("x")
        return write

    monkeypatch.setattr(analysis, "table2", fake("table2", "table2.csv"))
    monkeypatch.setattr(analysis, "sensitivity", fake("sensitivity", "sensitivity.png"))
    from sim import solver

    # the device the run's sim.device resolves to, here one a CPU machine would never pick by default
    monkeypatch.setattr(solver, "resolve_device", lambda device: "cuda:7")
    done = run_sim_analysis(run, progress=False)
    assert calls == [("table2", "cuda:7"), ("sensitivity", "cuda:7")]   # Table 2 too: on a GPU run, on the GPU
    assert done == {"table2": "sim_analysis/table2.csv", "sensitivity": "sim_analysis/sensitivity.png"}
    run_sim_analysis(run, progress=False)
    assert len(calls) == 2                                              # written files are kept
