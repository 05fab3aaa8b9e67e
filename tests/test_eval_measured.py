"""The measured-fabric test set (eval.measured): end to end on CPU with a tiny trained model, and its
tables against scipy with a stub predictor on clips written here."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from PIL import Image
from scipy import stats

from clothgap.config import preset
from clothgap.errors import ConfigError
from clothgap.runs import Run, mark_done

SETTING = "wind-uniform1"
FABRICS = ("navy-sparkle-sweat", "royal-target")       # the softest and the stiffest of Table 2


def tiny_run(root: Path) -> Run:
    """Synthetic training clips, a tiny lrcn trained on them for real, and a config asking for a tiny
    measured set: 2 fabrics x 1 sequence, 6 frames of 16 px, 1 spp, in the held-out variant."""
    from learn.train import train_one

    run = tiny_untrained_run(root)
    train_one(run, SETTING, "paper", "lrcn", 0, progress=False)
    return run


def tiny_untrained_run(root: Path, measured_variant: str = "heldout") -> Run:
    """``tiny_run`` before its model is trained (its measured set rendered in ``measured_variant``)."""
    from learn.synthetic import synthetic_run

    cfg = preset("smoke")
    cfg = replace(cfg, sim=replace(cfg.sim, sequences_per_class=3, grid_vertices=6, frames=6, settle_s=0.04,
                                   batch_size=4),
                  # No PNGs for the run, as in the paper preset: measured clips are read as image folders,
                  # so they keep theirs.
                  render=replace(cfg.render, resolution=16, spp=1, backend="auto", write_png=False),
                  train=replace(cfg.train, image_size=32, clip_len=4, clip_stride=2, epochs=1, batch_size=8,
                                width=4, fc6=16, hidden=8, val_fraction=0.0, num_threads=2),
                  eval=replace(cfg.eval, bootstrap=50, measured_sequences=1, measured_fabrics=FABRICS,
                               measured_variant=measured_variant))
    return synthetic_run(root, cfg)


@pytest.mark.slow
def test_measured_set_end_to_end_through_the_command(tmp_path):
    from clothgap.cli import cli
    from eval.measured import CORRELATIONS
    from eval.report import write_report
    from sim.measured import measured_index, table2_class

    run = tiny_run(tmp_path / "run")
    # `clothgap eval RUN`: the tables, then the measured set because the config asks for it
    result = CliRunner().invoke(cli, ["eval", str(run.root)])
    assert result.exit_code == 0, (result.output, result.exception)
    summary = json.loads(re.search(r"\[eval\] done in .*?: (\{.*\})", result.output).group(1))["measured"]
    assert (summary["simulated"], summary["rendered"], summary["predicted"]) == (2, 2, 1) and summary["heldout"]
    assert json.loads((run.eval_dir / "summary.json").read_text())["files"]["measured"]["fabrics"] == \
        "eval/measured.csv"

    # sim: the fabric's own tables, seeded per clip; render: the held-out variant, fabric in the meta
    sim_meta = json.loads((run.measured_sim_dir(SETTING) / "royal-target-0" / "meta.json").read_text())
    assert sim_meta["fabric"] == "royal-target" and sim_meta["material"] == "measured" and sim_meta["basis"] is None
    assert sim_meta["index"] == measured_index("royal-target", 0) and sim_meta["class_index"] == 53
    assert "wind_speed_mps" in sim_meta["motion_params"]
    rendered = run.measured_render_dir("heldout", SETTING) / "navy-sparkle-sweat-0"
    meta = json.loads((rendered / "meta.json").read_text())
    assert meta["fabric"] == "navy-sparkle-sweat" and meta["variant"] == "heldout"
    assert meta["render"]["lighting"] == "random" and len(list((rendered / "ldr").glob("*.png"))) == 6

    # one row per fabric, the paper's class beside the prediction
    table = pd.read_csv(run.eval_dir / "measured.csv")
    assert sorted(table["fabric"]) == sorted(FABRICS) and len(table) == 2
    assert dict(zip(table["fabric"], table["table2_class"])) == {f: table2_class(f) for f in FABRICS}
    assert table["pred"].between(0, 53).all() and set(table["exact"]) <= {0.0, 1.0}
    assert (table["checkpoint"] == "train/wind-uniform1/paper/lrcn/s0/checkpoint.pt").all()
    # at most one bin off in each factor, from the classes' grid indices
    from eval.classes import k_index, p_index
    truth, pred = table["table2_class"].to_numpy(), table["pred"].to_numpy()
    off = (abs(p_index(truth) - p_index(pred)) <= 1) & (abs(k_index(truth) - k_index(pred)) <= 1)
    assert (table["within1"] == off.astype(float)).all() and (table["within1"] >= table["exact"]).all()
    for column in ("table2_p", "table2_k", "p_match", "k_match", "within1", "class_dist", "bending_N_m", "stretching_N_m",
                   "density_kg_m2", "pred_bending_N_m", "pred_stretching_N_m"):
        assert table[column].notna().all(), column
    corr = pd.read_csv(run.eval_dir / "measured_correlations.csv")
    assert len(corr) == len(CORRELATIONS) and {"pearson", "pearson_lo", "spearman", "spearman_hi"} <= set(corr)
    assert (corr.loc[corr.unit == "clip", "n"] == 2).all()     # computed (two points: r is undefined, NaN)
    md = (run.eval_dir / "measured.md").read_text()
    assert all(f in md for f in FABRICS) and "Table 2 (p, k)" in md and "Spearman" in md
    info = json.loads((run.eval_dir / "measured.json").read_text())
    assert info["heldout"] and info["fabrics"] == list(FABRICS) and info["models"][0]["clips"] == 2
    rows = info["models"][0]["per_fabric"]          # measured.csv's rows as numbers, for programs
    assert [r["fabric"] for r in rows] == list(table["fabric"])
    for row, (_, csv_row) in zip(rows, table.iterrows()):
        assert row["pred"] == csv_row["pred"] and row["table2_class"] == csv_row["table2_class"]
        assert row["bending_N_m"] == pytest.approx(csv_row["bending_N_m"], rel=1e-5)
        assert row["pred_bending_N_m"] == pytest.approx(csv_row["pred_bending_N_m"], rel=1e-5)
    folder = run.root / info["models"][0]["folder"]       # the real-video path's own outputs
    assert (folder / "table4.csv").is_file() and (folder / "videos.csv").is_file() and (folder / "DONE").is_file()

    # resumable, and on its own as `clothgap eval measured`: nothing simulated, rendered or predicted again
    again = CliRunner().invoke(cli, ["eval", "measured", str(run.root), "--model",
                                     str(run.train_dir(SETTING, "paper", "lrcn", 0))])
    assert again.exit_code == 0, (again.output, again.exception)
    second = json.loads(re.search(r"\[eval measured\] done in .*?: (\{.*\})", again.output).group(1))
    assert (second["simulated"], second["rendered"], second["predicted"], second["reused"]) == (0, 0, 0, 1)

    doc = write_report(run).read_text()
    assert "Measured fabrics" in doc and "royal-target" in doc
    assert 'alt="measured fabrics, all models"' in doc        # predicted vs measured, per training variant
    assert 'href="../train/wind-uniform1/paper/lrcn/s0/checkpoint.pt"' in doc


def fake_measured_clips(run: Run, fabrics: list[str], sequences: int, frames: int = 10) -> None:
    """Finished sim and render folders of the measured set (no simulation, blank frames)."""
    from sim.measured import clip_name, fabric_labels

    for fabric in fabrics:
        for n in range(sequences):
            name = clip_name(fabric, n)
            sim_dir = run.measured_sim_dir(SETTING) / name
            sim_dir.mkdir(parents=True)
            mark_done(sim_dir)
            folder = run.measured_render_dir("heldout", SETTING) / name
            (folder / "ldr").mkdir(parents=True)
            for t in range(frames):
                Image.fromarray(np.full((8, 8, 3), 20 * t, np.uint8)).save(folder / "ldr" / f"{t:04d}.png")
            (folder / "meta.json").write_text(json.dumps({"clip_id": name, **fabric_labels(fabric),
                                                          "variant": "heldout"}))
            mark_done(folder)


def test_measured_tables_against_table2_and_scipy(tmp_path):
    from eval import classes
    from eval.measured import run_measured
    from eval.stage import TrainedModel
    from sim.measured import basis_values, measured_values, table2_class, table2_fabrics
    from tests.test_eval_real import fresh_model

    train_dir = fresh_model(tmp_path / "run")
    run = Run.open(tmp_path / "run")
    fabrics = table2_fabrics()
    fake_measured_clips(run, fabrics, sequences=2)
    off = fabrics[0]                      # predicted one k step too stiff in its first clip only

    def stub(train_dir, clip_dirs):
        rows = []
        for d in clip_dirs:
            name = json.loads((d / "meta.json").read_text())["clip_id"]
            fabric, n = name.rsplit("-", 1)
            cls = table2_class(fabric) + (1 if (fabric == off and n == "0") else 0)
            probs = np.full(54, 0.2 / 53)
            probs[cls] = 0.8
            rows += [{"clip_id": name, "start": 0, "class_index": -1, "pred": cls, "probs": probs}]
        return pd.DataFrame(rows)

    model = TrainedModel(SETTING, "paper", "lrcn", 0, train_dir)
    out = run_measured(run, models=[model], sequences=2, predictor=stub, progress=False, activations=0)
    assert out["simulated"] == 0 and out["rendered"] == 0 and out["exact"]["wind-uniform1/paper/lrcn/s0"] == 1.0

    table = pd.read_csv(run.eval_dir / "measured.csv").set_index("fabric")
    assert list(table.index) == sorted(fabrics) and (table["clips"] == 2).all()
    assert (table["pred"] == table["table2_class"]).all()       # the mean probabilities outvote one wrong clip
    assert table.loc[off, "vote_share"] == 0.5
    # the diagnostic class of the fabric's own tables: the basis fabric is (1, 1) there, (1, 0.5) in Table 2
    basis = basis_values()
    for fabric in fabrics:
        v = measured_values(fabric)
        assert table.loc[fabric, "tables_class"] == classes.nearest_class(
            v["stretching_N_m"] / basis["stretching_N_m"], v["bending_N_m"] / basis["bending_N_m"])
    assert tuple(table.loc["camel-ponte-roma", ["tables_p", "tables_k", "table2_p", "table2_k"]]) == (1, 1, 1, 0.5)
    assert table.loc["camel-ponte-roma", "within1_tables"] == table.loc["camel-ponte-roma", "k_within1_tables"] == 1
    k_steps = np.abs(classes.k_index(table["tables_class"].to_numpy()) - classes.k_index(table["pred"].to_numpy()))
    assert (table["k_within1_tables"] == (k_steps <= 1)).all()

    # the per-clip correlations are scipy's on the clip values; intervals hold the point
    clip_pred = {f"{f}-{n}": table2_class(f) + (1 if (f == off and n == 0) else 0) for f in fabrics for n in (0, 1)}
    names = sorted(clip_pred)
    bending = np.array([classes.k_value(clip_pred[v]) for v in names]) * basis_values()["bending_N_m"]
    measured = np.array([measured_values(v.rsplit("-", 1)[0])["bending_N_m"] for v in names])
    density = np.array([measured_values(v.rsplit("-", 1)[0])["density_kg_m2"] for v in names])
    corr = pd.read_csv(run.eval_dir / "measured_correlations.csv")
    row = corr[(corr.unit == "clip") & (corr.score == "pred_bending_N_m") & (corr.target == "bending_N_m")].iloc[0]
    assert row["n"] == 20 and row["fabrics"] == 10
    assert row["pearson"] == pytest.approx(stats.pearsonr(bending, measured).statistic, rel=1e-4)
    assert row["spearman"] == pytest.approx(stats.spearmanr(bending, measured).statistic, rel=1e-4)
    assert row["spearman_lo"] <= row["spearman"] <= row["spearman_hi"]
    dens = corr[(corr.unit == "clip") & (corr.score == "pred_bending_N_m") & (corr.target == "density_kg_m2")]
    assert dens["pearson"].item() == pytest.approx(stats.pearsonr(bending, density).statistic, rel=1e-4)
    # the weight-alone baseline: the same for every model, scipy's over the fabrics, 0.59 on the ten of Table 2
    alone = corr[(corr.unit == "fabric") & (corr.score == "density_kg_m2") & (corr.target == "bending_N_m")]
    weights = [measured_values(f)["density_kg_m2"] for f in sorted(fabrics)]
    bendings = [measured_values(f)["bending_N_m"] for f in sorted(fabrics)]
    assert len(alone) == 1 and alone["fabrics"].item() == 10
    assert alone["spearman"].item() == pytest.approx(stats.spearmanr(weights, bendings).statistic, rel=1e-4)
    assert round(alone["spearman"].item(), 2) == 0.59
    k_row = corr[(corr.unit == "fabric") & (corr.score == "pred_k")].iloc[0]
    paper_k = [table.loc[f, "table2_k_est"] for f in sorted(fabrics)]
    assert k_row["spearman"] == pytest.approx(stats.spearmanr(table["pred_k"], paper_k).statistic, rel=1e-4)

    # the same clips went through the real-video path: its Table 4 agrees on the bending row
    folder = run.eval_dir / "measured" / "heldout" / SETTING / "paper" / "lrcn" / "s0"
    table4 = pd.read_csv(folder / "table4.csv")
    bending_row = table4.score.str.startswith("k x")
    assert table4.loc[bending_row, "stiffness_pearson"].item() == pytest.approx(row["pearson"], rel=1e-4)
    assert "| 11oz-black-denim | 2 |" in (run.eval_dir / "measured.md").read_text()


def test_measured_config_errors_are_named(tmp_path):
    from clothgap.config import ConfigError
    from eval.measured import resolve
    from sim.measured import measured_index, table2_fabrics
    from tests.test_eval_real import fresh_model

    fresh_model(tmp_path / "run")
    run = Run.open(tmp_path / "run")
    assert resolve(run) == (2, table2_fabrics(), "heldout")          # smoke: off in eval, defaults here
    with pytest.raises(ConfigError, match="unknown measured fabric.*known: 11oz"):
        resolve(run, fabrics=["velvet"])
    with pytest.raises(ConfigError, match="unknown render variant 'nope'"):
        resolve(run, variant="nope")
    # seeds: every (fabric, sequence) has its own index, far from any training clip's
    indices = {measured_index(f, n) for f in table2_fabrics() for n in range(5)}
    assert len(indices) == 50 and min(indices) > 10 ** 8


def test_a_recipes_models_are_scored_where_they_are_and_new_weights_are_predicted_again(tmp_path):
    import shutil

    import torch

    from clothgap.config import ConfigError
    from eval.measured import model_from_dir, run_measured
    from sim.measured import table2_class, table2_fabrics
    from tests.test_eval_real import fresh_model

    train_dir = fresh_model(tmp_path / "run")
    mark_done(train_dir)
    run = Run.open(tmp_path / "run")
    fabrics = table2_fabrics()[:2]
    fake_measured_clips(run, fabrics, sequences=1)
    recipe_dir = run.ablation_dir("best+clip_len=4") / SETTING / "paper" / "lrcn" / "s0"
    shutil.copytree(train_dir, recipe_dir)

    def stub(train_dir, clip_dirs):
        names = [json.loads((d / "meta.json").read_text())["clip_id"] for d in clip_dirs]
        return pd.DataFrame([{"clip_id": n, "start": 0, "class_index": -1, "pred": table2_class(n.rsplit("-", 1)[0]),
                              "probs": np.eye(54)[table2_class(n.rsplit("-", 1)[0])]} for n in names])

    model = model_from_dir(run, recipe_dir)
    assert (model.recipe, model.setting, model.model, model.seed, model.folder) == \
        ("best+clip_len=4", SETTING, "lrcn", 0, recipe_dir)
    own_before = sorted(p.relative_to(run.train_root) for p in run.train_root.rglob("*"))

    def measured():
        return run_measured(run, models=[model], sequences=1, fabrics=fabrics, predictor=stub, progress=False,
                            activations=0)

    assert measured()["predicted"] == 1
    folder = run.eval_dir / "measured" / "heldout" / "ablation" / "best+clip_len=4" / SETTING / "paper" / "lrcn" / "s0"
    assert (folder / "DONE").is_file()
    entry = json.loads((run.eval_dir / "measured.json").read_text())["models"][0]
    assert entry["recipe"] == "best+clip_len=4" and entry["checkpoint"].startswith("ablation/best+clip_len=4/")
    assert sorted(p.relative_to(run.train_root) for p in run.train_root.rglob("*")) == own_before

    assert (measured()["predicted"], measured()["reused"]) == (0, 1)     # same weights: kept
    state = torch.load(recipe_dir / "checkpoint.pt", weights_only=False)
    first = next(iter(state["model"]))
    state["model"][first] = state["model"][first] + 1.0
    torch.save(state, recipe_dir / "checkpoint.pt")                       # retrained in place
    assert measured()["predicted"] == 1

    own = model_from_dir(run, train_dir)
    assert own.recipe == "" and own.folder == train_dir
    with pytest.raises(ConfigError, match="two models named wind-uniform1/paper/lrcn/0"):
        run_measured(run, models=[own, model], sequences=1, fabrics=fabrics, predictor=stub, progress=False)
    with pytest.raises(ConfigError, match="ablation/<recipe>"):
        model_from_dir(run, run.root / "ablation" / "lrcn")


def test_measured_clips_are_simulated_for_the_settings_asked_only(tmp_path):
    from sim.stage import simulate_measured

    cfg = preset("smoke")
    cfg = replace(cfg, sim=replace(cfg.sim, motions=("wind", "arm"), grid_vertices=6, frames=3, settle_s=0.04,
                                   batch_size=2, device="cpu"), train=replace(cfg.train, clip_len=2, clip_stride=1))
    run = Run.create_or_resume(tmp_path / "run", cfg)
    summary = simulate_measured(run, ["royal-target"], 1, progress=False, settings=["wind-uniform1"])
    assert summary["simulated"] == 1
    assert run.done_clips(run.measured_sim_dir("wind-uniform1")) == ["royal-target-0"]
    assert run.done_clips(run.measured_sim_dir("arm-uniform1")) == []

    # the same fabric at another density (scripts/measured_density.py): its own folder, the density in the meta
    # and in the simulation (the same draws and tables, another weight: another motion)
    from sim.clip import SimClip

    with pytest.raises(ConfigError, match="folder of their own"):
        simulate_measured(run, ["royal-target"], 1, progress=False, settings=["wind-uniform1"], density=0.05)
    light = tmp_path / "light"
    simulate_measured(run, ["royal-target"], 1, progress=False, settings=["wind-uniform1"], density=0.05,
                      folder_of=lambda s: light / s)
    own = SimClip.load(run.measured_sim_dir("wind-uniform1") / "royal-target-0")
    other = SimClip.load(light / "wind-uniform1" / "royal-target-0")
    assert other.meta["density"] == 0.05 and other.meta["density_own"] == own.meta["density"] != 0.05
    assert other.meta["motion_params"] == own.meta["motion_params"]
    assert not np.allclose(other.positions, own.positions)


def test_models_scored_in_a_pool_give_the_same_tables(tmp_path, capsys):
    """A study scores dozens of models on the measured clips; in a spawned pool (the real network, figures and
    bootstraps in each process) the tables and each model's per-clip predictions are those of one process."""
    import shutil

    import torch

    from eval.measured import run_measured
    from eval.stage import TrainedModel
    from tests.test_eval_real import fresh_model

    train_dir = fresh_model(tmp_path / "run")
    run = Run.open(tmp_path / "run")
    other = train_dir.parent / "s1"                   # a second model with other weights
    other.mkdir()
    ckpt = torch.load(train_dir / "checkpoint.pt", weights_only=False)
    ckpt["model"] = {k: v + 0.05 if v.is_floating_point() else v for k, v in ckpt["model"].items()}
    torch.save({**ckpt, "seed": 1}, other / "checkpoint.pt")
    fake_measured_clips(run, list(FABRICS), sequences=2)
    models = [TrainedModel(SETTING, "paper", "lrcn", seed, folder) for seed, folder in ((0, train_dir), (1, other))]
    outputs = {}
    for processes in (0, 2):
        shutil.rmtree(run.eval_dir / "measured", ignore_errors=True)
        out = run_measured(run, models=models, sequences=2, fabrics=FABRICS, progress=True, activations=1,
                           processes=processes)
        assert (out["predicted"], out["reused"]) == (2, 0)
        said = capsys.readouterr().out
        assert ("(one of 2 processes)" in said) == (processes == 2), said
        outputs[processes] = {name: (run.eval_dir / name).read_text()
                              for name in ("measured.csv", "measured_correlations.csv", "measured_ensembles.csv")}
        for seed in (0, 1):
            folder = run.eval_dir / "measured" / "heldout" / SETTING / "paper" / "lrcn" / f"s{seed}"
            outputs[processes][seed] = (folder / "videos.csv").read_text()
            assert (folder / "activations.png").is_file() and (folder / "DONE").is_file()
    assert outputs[2] == outputs[0]
    assert outputs[0][0] != outputs[0][1]             # the two models' predictions are their own
    assert len(outputs[0]["measured.csv"].splitlines()) == 1 + 2 * len(FABRICS)      # a row per model and fabric


def test_seeds_are_also_scored_as_their_ensemble(tmp_path):
    """Models that differ only in their seed are scored as their ensemble too: per clip the mean of their
    probabilities. A fabric each seed reads wrong (each its own wrong class, the true class second for both) is
    read right by the ensemble; a model of another recipe joins none; measured.csv keeps one row per model and
    fabric (what the report and `clothgap combine` read), the ensembles go to their own table."""
    import shutil

    from eval.measured import model_folder, run_measured
    from eval.report import _section_measured
    from eval.stage import TrainedModel
    from sim.measured import table2_class, table2_fabrics
    from tests.test_eval_real import fresh_model

    train_dir = fresh_model(tmp_path / "run")
    run = Run.open(tmp_path / "run")
    for seed in (1, 2):
        shutil.copytree(train_dir, train_dir.parent / f"s{seed}")
    fabrics = table2_fabrics()
    fake_measured_clips(run, fabrics, sequences=2)
    hard = fabrics[0]
    truth = table2_class(hard)
    wrong = {"s0": (truth + 1) % 54, "s1": (truth + 2) % 54}

    def stub(folder, clip_dirs):
        rows = []
        for d in clip_dirs:
            name = json.loads((d / "meta.json").read_text())["clip_id"]
            cls = table2_class(name.rsplit("-", 1)[0])
            probs = np.full(54, 0.2 / 52)
            probs[cls] = 0.8
            if name.startswith(hard + "-") and folder.name in wrong:
                probs = np.full(54, 0.15 / 52)
                probs[cls], probs[wrong[folder.name]] = 0.40, 0.45
            rows.append({"clip_id": name, "start": 0, "class_index": -1, "pred": int(probs.argmax()), "probs": probs})
        return pd.DataFrame(rows)

    models = [TrainedModel(SETTING, "paper", "lrcn", 0, train_dir),
              TrainedModel(SETTING, "paper", "lrcn", 1, train_dir.parent / "s1", "baseline+seeds=1"),
              TrainedModel(SETTING, "paper", "lrcn", 2, train_dir.parent / "s2", "camera")]
    out = run_measured(run, models=models, sequences=2, fabrics=fabrics, predictor=stub, progress=False,
                       activations=0)
    exact = out["exact"]
    assert exact[f"{SETTING}/paper/lrcn/s0"] == exact[f"{SETTING}/paper/lrcn/s1"] == 0.9
    assert exact[f"{SETTING}/paper/lrcn/s0+1"] == 1.0 and exact[f"{SETTING}/paper/lrcn/s2"] == 1.0
    assert len(exact) == 4                                       # the camera model joins no ensemble

    members = [pd.read_csv(model_folder(run, m, "heldout") / "videos.csv").set_index("video") for m in models[:2]]
    folder = run.eval_dir / "measured" / "heldout" / SETTING / "paper" / "lrcn" / "ensemble-s0+1"
    ensemble = pd.read_csv(folder / "videos.csv").set_index("video")
    clip = f"{hard}-0"
    for c in (f"prob_{truth:02d}", f"prob_{wrong['s0']:02d}", f"prob_{wrong['s1']:02d}"):
        assert ensemble.loc[clip, c] == pytest.approx((members[0].loc[clip, c] + members[1].loc[clip, c]) / 2,
                                                      rel=1e-5)
    assert ensemble.loc[clip, "pred"] == truth

    made = json.loads((folder / "ensemble.json").read_text())
    assert [m["seed"] for m in made["members"]] == [0, 1] and all(len(m["checkpoint_sha256"]) == 64
                                                                  for m in made["members"])

    summary = json.loads((run.eval_dir / "measured.json").read_text())
    assert [e["seed"] for e in summary["models"]] == [0, 1, 2]
    (entry,) = summary["ensembles"]
    assert entry["ensemble_of"] == [0, 1] and entry["seed"] == "0+1" and entry["clips"] == 2 * len(fabrics)
    assert [r["exact"] for r in entry["per_fabric"]] == [1.0] * len(fabrics)
    table = pd.read_csv(run.eval_dir / "measured.csv")
    assert table["seed"].dtype.kind == "i" and table.groupby("seed")["exact"].mean().to_dict() == {0: 0.9, 1: 0.9,
                                                                                                   2: 1.0}
    ensembles = pd.read_csv(run.eval_dir / "measured_ensembles.csv")
    assert set(ensembles["seed"]) == {"0+1"} and ensembles["exact"].mean() == 1.0
    assert "seeds 0+1, their ensemble" in (run.eval_dir / "measured.md").read_text()
    html = _section_measured(run)
    assert html.count("Match over fabrics") == 3                       # the report's three models
    ensembles = html.split("Seeds' ensembles")[1]                     # and a row for their ensemble
    assert "0 + 1" in ensembles and '1.00 <span class="ci">[1.00, 1.00]</span>' in ensembles     # exact: 10 of 10

    # scored again without a second seed: no ensemble, and the earlier one's table is not left beside the new tables
    run_measured(run, models=models[:1], sequences=2, fabrics=fabrics, predictor=stub, progress=False, activations=0)
    assert not (run.eval_dir / "measured_ensembles.csv").exists()
    assert json.loads((run.eval_dir / "measured.json").read_text())["ensembles"] == []


@pytest.mark.slow
def test_measured_clips_made_in_shards_are_those_of_one_process(tmp_path):
    """`clothgap eval --executor process` makes the measured clips in shards of (setting, fabric, sequence) before
    the eval: the same files as in one process, and a second call makes none again."""
    from clothgap.executor import ExecutorOptions, run_stage
    from eval.measured import generation_units, make_measured_clips

    one, pooled = (tiny_untrained_run(tmp_path / name, measured_variant="paper") for name in ("one", "pooled"))
    units = generation_units(one)
    assert len(units) == len(one.config.sim.settings()) * len(FABRICS)
    made = make_measured_clips(one, progress=False)
    assert (made["sim"]["simulated"], made["render"]["rendered"]) == (len(units), len(units))
    options = ExecutorOptions("process", workers=2)
    summary = run_stage(pooled, "measured", options)
    assert (summary["sim"]["simulated"], summary["render"]["rendered"]) == (len(units), len(units))
    assert summary["executor"]["shards"] == 2

    def timeless(value):
        """A meta without what it took: seconds, and scene builds (one process reuses a scene across clips)."""
        if isinstance(value, dict):
            return {k: timeless(v) for k, v in value.items() if k not in ("seconds", "scene_builds")}
        return value

    def files(run: Run) -> dict[str, object]:
        """Each file's bytes; a meta's content; a frame's pixels, HDR and PNG."""
        from render.exr import read_exr

        root = run.root / "measured"
        out: dict[str, object] = {}
        for f in sorted(root.rglob("*")):
            if f.name == "meta.json":
                out[str(f.relative_to(root))] = timeless(json.loads(f.read_text()))
            elif f.suffix == ".exr":
                out[str(f.relative_to(root))] = np.asarray(read_exr(f), dtype=np.float64)
            elif f.suffix == ".png":
                out[str(f.relative_to(root))] = np.asarray(Image.open(f), dtype=np.float64) / 255
            elif f.is_file():
                out[str(f.relative_to(root))] = f.read_bytes()
        return out

    def alike(a: np.ndarray, b: np.ndarray) -> bool:
        """Frames equal but for rounding and a rare single path: a clip rendered in a reused scene differs from a
        fresh build's in the last float bits (5e-7 at most seen), and Mitsuba's parallel BVH builds may break
        ties between coincident triangle edges differently, which moves one sample of a pixel (as in
        test_render_output's pooled-scene test)."""
        if a.shape != b.shape:
            return False
        off = np.abs(a - b).reshape(a.shape[0], a.shape[1], -1).max(axis=-1) > 1e-5
        return off.mean() <= 0.01

    made_once, made_in_shards = files(one), files(pooled)
    assert made_in_shards.keys() == made_once.keys()
    for name, value in made_once.items():
        other = made_in_shards[name]
        assert alike(other, value) if isinstance(value, np.ndarray) else other == value, name
    assert any(name.endswith(".png") for name in made_once) and any(name.startswith("sim/") for name in made_once)
    again = run_stage(pooled, "measured", options)
    assert (again["sim"]["simulated"], again["render"]["rendered"]) == (0, 0)
    assert again["sim"]["skipped"] == len(units) and again["render"]["skipped"] == len(units)
