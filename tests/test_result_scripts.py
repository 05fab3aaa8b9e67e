"""scripts/epoch_seconds.py, stage_summaries.py, host_samples.py, bending_over_weight.py, reading_bias.py and
fabric_classes.py: figures
read from what a run leaves (metrics.csv, the stages' summary lines, the host's memory samples, the measured-fabric
readings), and nothing written from a file that does not hold them."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


epoch_seconds = _script("epoch_seconds")
stage_summaries = _script("stage_summaries")
host_samples = _script("host_samples")


def _model(run: Path, recipe: str, seed: int, seconds: list[float], windows: int = 100, done: bool = True) -> Path:
    folder = run / "ablation" / recipe / "arm-uniform1" / "paper" / "lrcn" / f"s{seed}"
    folder.mkdir(parents=True)
    rows = ["epoch,train_loss,train_acc,val_loss,val_acc,lr,seconds"]
    rows += [f"{i},1.0,0.5,1.0,{0.1 * (i + 1):.2f},0.001,{s}" for i, s in enumerate(seconds)]
    (folder / "metrics.csv").write_text("\n".join(rows) + "\n")
    (folder / "config.json").write_text(json.dumps({"train_subsequences": windows, "train": {"clip_len": 40}}))
    if done:
        (folder / "DONE").write_text("{}")
    return folder


def test_epoch_seconds_leaves_out_the_compiling_epoch_and_gives_the_ratio(tmp_path, capsys):
    for seed in (0, 1):
        _model(tmp_path, f"eager{seed}", seed, [30.0, 9.0, 8.0, 7.0])     # with the first epoch the median is 8.5
        _model(tmp_path, f"graphs{seed}", seed, [60.0, 7.0, 6.0, 5.0])
    _model(tmp_path, "graphs9", 9, [1.0, 1.0, 1.0, 1.0], done=False)      # unfinished: not counted
    out = tmp_path / "e.json"
    epoch_seconds.main([str(tmp_path), "--a", "eager*", "--b", "graphs*", "--epochs", "1-3", "--out", str(out)])
    result = json.loads(out.read_text())
    assert result["a"]["median_epoch_s"] == 8.0 and result["b"]["median_epoch_s"] == 6.0
    assert result["ratio_a_over_b"] == pytest.approx(8.0 / 6.0, abs=1e-3)
    assert len(result["b"]["models"]) == 2
    model = result["a"]["models"]["eager0/arm-uniform1/paper/lrcn/s0"]
    assert model["epochs"] == 4 and model["first_epoch_s"] == 30.0 and model["best_val_acc"] == 0.4
    assert result["a"]["frames_per_s_per_gpu"] == round(2 * 100 * 40 / 8.0)
    assert json.loads(capsys.readouterr().out) == result


def test_epoch_seconds_names_what_it_cannot_measure(tmp_path):
    _model(tmp_path, "eager", 0, [30.0, 8.0, 8.0])
    _model(tmp_path, "graphs", 0, [60.0, 6.0, 6.0])
    _model(tmp_path, "graphs-small", 1, [60.0, 3.0, 3.0], windows=50)
    with pytest.raises(SystemExit, match="has 2 of epochs 1-3"):
        epoch_seconds.main([str(tmp_path), "--a", "eager", "--b", "graphs", "--epochs", "1-3"])
    with pytest.raises(SystemExit, match="no finished model"):
        epoch_seconds.main([str(tmp_path), "--a", "nothing*", "--b", "graphs"])
    with pytest.raises(SystemExit, match="different data"):
        epoch_seconds.main([str(tmp_path), "--a", "eager", "--b", "graphs*", "--epochs", "1-2"])
    with pytest.raises(SystemExit, match="different data.*not comparable"):
        epoch_seconds.main([str(tmp_path), "--a", "eager", "--b", "graphs-small", "--epochs", "1-2"])
    with pytest.raises(SystemExit, match="1 finished models, expected 4"):
        epoch_seconds.main([str(tmp_path), "--a", "eager", "--b", "graphs", "--epochs", "1-2", "--expect", "4"])
    with pytest.raises(SystemExit, match="the same models"):
        epoch_seconds.main([str(tmp_path), "--a", "g*s", "--b", "graphs", "--epochs", "1-2"])
    with pytest.raises(SystemExit, match="FIRST-LAST"):
        epoch_seconds.main([str(tmp_path), "--a", "eager", "--b", "graphs", "--epochs", "two"])


def test_stage_summaries_reads_the_line_the_cli_prints(tmp_path, capsys):
    from clothgap.cli import _echo_summary

    _echo_summary("render", {"rendered": 3, "frames": 120, "seconds": 2.0}, 9.0)    # a killed try's line first
    _echo_summary("render", {"rendered": 4, "frames": 160, "seconds": 2.5}, 3.04)
    log = tmp_path / "render.log"
    log.write_text("render (process x4): 100%|##########| 4/4\n" + capsys.readouterr().out)
    out = tmp_path / "stage.json"
    stage_summaries.main([f"mps={log}", "--out", str(out)])
    row = json.loads(out.read_text())["mps"]
    assert row == {"stage": "render", "wall_s": 3.0, "rendered": 4, "frames": 160, "seconds": 2.5, "frames_per_s": 64.0}


def test_stage_summaries_writes_null_where_the_cli_printed_nan(tmp_path):
    log = tmp_path / "train.log"
    log.write_text('[eval] done in 2.0 s: {"acc": NaN, "seconds": 1.5}\n')
    out = tmp_path / "stage.json"
    stage_summaries.main([f"eval={log}", "--out", str(out)])
    assert json.loads(out.read_text())["eval"]["acc"] is None


def test_stage_summaries_names_a_log_without_a_summary_and_writes_nothing(tmp_path):
    good, cut = tmp_path / "good.log", tmp_path / "cut.log"
    good.write_text('[sim] done in 1.0 s: {"simulated": 2, "seconds": 0.9}\n')
    cut.write_text("render (process x4):  25%|##        | 1/4\n")
    out = tmp_path / "stage.json"
    with pytest.raises(SystemExit, match="cut.log has no"):
        stage_summaries.main([f"a={good}", f"b={cut}", "--out", str(out)])
    assert not out.exists()
    with pytest.raises(SystemExit, match="LABEL=LOG"):
        stage_summaries.main([str(good)])


def test_bending_over_weight_sets_a_reading_beside_the_weight_alone(tmp_path):
    bending_over_weight = _script("bending_over_weight")
    weight = [0.1, 0.2, 0.3, 0.15, 0.25, 0.12]
    bending = [1.0, 5.0, 3.3, 2.0, 4.0, 2.6]
    per_weight = [b / w for b, w in zip(bending, weight)]

    def fabrics(pred_k):
        return [{"pred_k": k, "bending_N_m": b, "density_kg_m2": w} for k, b, w in zip(pred_k, bending, weight)]

    constant = [2.0] * 6                                    # knows nothing: times the weight it is the weight
    follows_bending_over_weight = [float(r + 1) for r in np.argsort(np.argsort(per_weight))]    # its ranks
    report = {"settings": [{"setting": "arm-uniform1", "results": [
        {"classifier": "constant", "fabrics": fabrics(constant)},
        {"classifier": "per_weight", "fabrics": fabrics(follows_bending_over_weight)}]}]}
    path = tmp_path / "learnability-measured.json"
    path.write_text(json.dumps(report))
    out = tmp_path / "ranks.json"
    bending_over_weight.main([str(path), "--out", str(out)])
    result = json.loads(out.read_text())["arm-uniform1"]
    alone, constant_ranks = result["weight_alone~bending"], result["classifiers"]["constant"]
    # the same resamples for every column: a constant reading times the weight is the weight, interval and all
    assert constant_ranks["pred_k_times_weight~bending"] == alone and alone["lo"] < alone["spearman"] < alone["hi"]
    assert constant_ranks["pred_k~bending"] == {"spearman": None, "lo": None, "hi": None}
    ranked = result["classifiers"]["per_weight"]
    assert ranked["pred_k~bending_over_weight"]["spearman"] == pytest.approx(1.0)
    difference = ranked["pred_k~bending_over_weight minus pred_k~bending"]
    assert difference["spearman"] == pytest.approx(1.0 - ranked["pred_k~bending"]["spearman"])
    assert difference["lo"] <= difference["spearman"] <= difference["hi"]
    assert result["fabrics"] == 6
    # a perfect reader of B / w: the per_weight classifier reads exactly its ranks, so it scores the same, interval too
    assert result["bending_over_weight_alone~bending"] == ranked["pred_k~bending"]
    from scipy.stats import spearmanr
    from sim.measured import measured_values, table2_fabrics
    tables = tmp_path / "tables.json"
    bending_over_weight.main(["--tables", "--out", str(tables)])
    ten = json.loads(tables.read_text())["table2_fabrics"]
    values = [measured_values(f) for f in table2_fabrics()]
    b, w = (np.array([v[key] for v in values]) for key in ("bending_N_m", "density_kg_m2"))
    assert ten["fabrics"] == 10 and ten["weight_alone~bending"]["spearman"] == pytest.approx(spearmanr(w, b)[0])
    assert ten["bending_over_weight_alone~bending"]["spearman"] == pytest.approx(spearmanr(b / w, b)[0])
    # goal 3's count for readers that look at no clip: each reader's count is that of the classes it lists
    from sim.classes import K_VALUES, P_VALUES, class_values
    from sim.measured import table2_class
    for name, reader in ten["perfect_readers"].items():
        steps = [(abs(P_VALUES.index(p) - P_VALUES.index(class_values(table2_class(f))[0])),
                  abs(K_VALUES.index(k) - K_VALUES.index(class_values(table2_class(f))[1])))
                 for f, (p, k) in reader["classes"].items()]
        assert reader["within_one_bin"] == sum(max(d) <= 1 for d in steps), name
        assert reader["exact"] == sum(max(d) == 0 for d in steps) <= reader["within_one_bin"], name
        assert reader["classes"]["camel-ponte-roma"] == [1.0, 1.0], name     # the basis, at its own weight
    assert all(c == [1.0, 1.0] for c in ten["perfect_readers"]["constant_1_1"]["classes"].values())
    basis = measured_values("camel-ponte-roma")["density_kg_m2"]
    lighter = [f for f, v in zip(table2_fabrics(), values) if v["density_kg_m2"] < basis]
    rises = [K_VALUES.index(ten["perfect_readers"]["over_weight"]["classes"][f][1])
             - K_VALUES.index(ten["perfect_readers"]["tables"]["classes"][f][1]) for f in lighter]
    assert min(rises) >= 0 and max(rises) > 0          # a lighter fabric moves stiffer than its tables say
    with pytest.raises(SystemExit):
        bending_over_weight.main(["--tables", str(path)])          # one or the other
    path.write_text("{}")
    with pytest.raises(SystemExit, match="not a learnability-measured.json"):
        bending_over_weight.main([str(path)])
    path.write_text(json.dumps({"settings": [{"setting": "arm-uniform1", "results": [{"classifier": "mlp"}]}]}))
    with pytest.raises(SystemExit, match="lacks the per-fabric rows"):
        bending_over_weight.main([str(path)])


def test_bending_over_weight_against_another_run_pairs_each_classifier_by_fabric(tmp_path):
    from scipy.stats import spearmanr

    bending_over_weight = _script("bending_over_weight")
    weight = [0.1, 0.2, 0.3, 0.15, 0.25, 0.12]
    bending = [1.0, 5.0, 3.3, 2.0, 4.0, 2.6]
    names = [f"f{i}" for i in range(6)]

    def report(pred_k, within1, order=names):
        rows = [{"fabric": n, "pred_k": k, "bending_N_m": b, "density_kg_m2": w, "within1": c}
                for n, k, b, w, c in zip(order, pred_k, bending, weight, within1)]
        return {"settings": [{"setting": "arm-uniform1", "results": [{"classifier": "mlp", "fabrics": rows}]}]}

    muddled = [3.0, 1.0, 2.0, 5.0, 4.0, 6.0]                 # ranks bending at some value below 1
    paths = {name: tmp_path / f"{name}.json" for name in ("base", "new", "other")}
    paths["base"].write_text(json.dumps(report(muddled, [1, 0, 0, 1, 0, 0])))
    paths["new"].write_text(json.dumps(report(bending, [1, 1, 1, 1, 0, 1])))     # reads bending's order exactly
    paths["other"].write_text(json.dumps(report(bending, [1] * 6, order=names[::-1])))
    out = tmp_path / "paired.json"
    bending_over_weight.main([str(paths["new"]), "--against", str(paths["base"]), "--out", str(out)])
    result = json.loads(out.read_text())
    assert result["command"].startswith("python3 scripts/bending_over_weight.py")
    paired = result["arm-uniform1"]["against_base"]["mlp"]
    rank = paired["pred_k~bending minus base"]
    assert rank["spearman"] == pytest.approx(1.0 - spearmanr(muddled, bending)[0]) and rank["lo"] <= rank["spearman"]
    count = paired["within_one_bin_count minus base"]
    assert count["count"] == 3 and count["lo"] <= 3 <= count["hi"]
    with pytest.raises(SystemExit, match="different fabrics"):
        bending_over_weight.main([str(paths["other"]), "--against", str(paths["base"])])


def test_reading_bias_measures_readings_from_what_s_and_b_over_w_tell(tmp_path):
    from sim.measured import basis_values, measured_values, table2_fabrics

    reading_bias = _script("reading_bias")
    base = basis_values()
    over_w = {}
    for f in table2_fabrics():
        v = measured_values(f)
        w = v["density_kg_m2"] / base["density_kg_m2"]
        over_w[f] = (v["stretching_N_m"] / base["stretching_N_m"] / w, v["bending_N_m"] / base["bending_N_m"] / w)
    # k read half a log low for every fabric, and k read right for half of them and a log high for the others
    low = {f: (p, k * np.exp(-0.5)) for f, (p, k) in over_w.items()}
    mixed = {f: (p, k * np.e ** (i % 2)) for i, (f, (p, k)) in enumerate(over_w.items())}

    def probe(reading):
        return [{"fabric": f, "pred_p": p, "pred_k": k} for f, (p, k) in reading.items()]

    report = {"settings": [{"setting": "arm-uniform1", "results": [{"classifier": "exact", "fabrics": probe(over_w)},
                                                                  {"classifier": "low", "fabrics": probe(low)}]}]}
    other = {"settings": [{"setting": "arm-uniform1", "results": [{"classifier": "exact", "fabrics": probe(mixed)}]}]}
    lrcn = "lrcn trained on lighting-random (arm-uniform1, seed 0)"
    look = {lrcn: [{"Fabric": f, "Predicted (p, k)": f"({p:.6f}, {k:.6f})"} for f, (p, k) in low.items()]}
    # the same reading as `clothgap eval measured` writes it, named as its Markdown section is, so the two pair
    model = {"model": "lrcn", "train_variant": "lighting-random", "setting": "arm-uniform1", "seed": 0}
    measured = {"fabrics": sorted(low), "settings": ["arm-uniform1"],
                "models": [{**model, "status": "predicted", "per_fabric": probe(low)},
                           {**model, "seed": 1, "status": "no rendered measured clips"}],     # unscored: left out
                "ensembles": [{**model, "seed": "0+1", "per_fabric": probe(over_w)}]}
    path = tmp_path / "readings.json"
    path.write_text(json.dumps({"a": report, "b": other, "measured_fabrics": {"arm-heldout": look},
                                "measured": {"arm-heldout": measured}}))
    out = tmp_path / "bias.json"
    a, b, tables, as_json = (f"{path}:a", f"{path}:b", f"{path}:measured_fabrics/arm-heldout",
                             f"{path}:measured/arm-heldout")
    reading_bias.main([a, b, tables, as_json, "--pair", f"{a},{b}", "--pair", f"{tables},{as_json}",
                       "--out", str(out)])
    result = json.loads(out.read_text())
    found = result["readings"]
    exact, half_low = found[f"{a} arm-uniform1 exact"], found[f"{a} arm-uniform1 low"]
    assert exact["fabrics"] == 10
    for key in ("p_bias", "p_mean_abs", "k_bias", "k_mean_abs"):
        assert all(abs(exact[key][x]) < 1e-9 for x in ("value", "lo", "hi")), key
    assert half_low["k_bias"]["value"] == pytest.approx(-0.5) and half_low["k_mean_abs"]["value"] == pytest.approx(0.5)
    assert half_low["k_bias"]["lo"] == pytest.approx(-0.5) and abs(half_low["p_bias"]["value"]) < 1e-9
    assert found[f"{tables} {lrcn}"]["k_bias"]["value"] == pytest.approx(-0.5, abs=1e-5)     # the tables parse alike
    assert found[f"{as_json} {lrcn}"]["k_bias"]["value"] == pytest.approx(-0.5)
    ensemble = ("lrcn trained on lighting-random (arm-uniform1, seeds 0+1, their ensemble: mean probabilities "
                "per clip)")
    assert abs(found[f"{as_json} {ensemble}"]["k_bias"]["value"]) < 1e-9
    assert not any("seed 1)" in k for k in found)
    assert abs(result["pairs"][f"{as_json} minus {tables}: {lrcn}"]["k_bias"]["value"]) < 1e-5
    mixed_bias = found[f"{b} arm-uniform1 exact"]["k_bias"]
    assert mixed_bias["value"] == pytest.approx(0.5) and mixed_bias["lo"] < 0.5 < mixed_bias["hi"]    # resampled
    pair = result["pairs"][f"{b} minus {a}: arm-uniform1 exact"]
    assert pair["fabrics"] == 10                                     # minus a reading that is 0 everywhere
    assert pair["k_bias"] == pytest.approx(mixed_bias)
    bad_rows = [("unknown", {"settings": [{"results": [{"classifier": "x", "fabrics": [
                    {"fabric": "no-such-fabric", "pred_p": 1, "pred_k": 1}]}]}]}, "no-such-fabric"),
                ("zero", {"settings": [{"results": [{"classifier": "x",
                                                      "fabrics": probe({**low, "royal-target": (1, 0)})}]}]},
                 "not positive"),
                ("twice", {"settings": [{"results": [{"classifier": "x", "fabrics": probe(low) * 2}]}]}, "twice")]
    for name, doc, says in bad_rows:
        (tmp_path / f"{name}.json").write_text(json.dumps(doc))
    (tmp_path / "old.json").write_text(json.dumps({"fabrics": 10, "models": [model]}))     # no per-fabric rows
    (tmp_path / "none.json").write_text(json.dumps({"fabrics": 10, "models": [], "ensembles": []}))
    for args, says in [([f"{path}:a/settings"], "neither"),
                       ([str(tmp_path / "old.json")], r"seed 0\): no per-fabric"),
                       ([str(tmp_path / "none.json")], "no reading"),
                       ([a, tables, "--pair", f"{a},{tables}"], "no reading of the second"),
                       ([f"{path}:nothing"], "nothing"),
                       ([f"{tmp_path}/absent.json"], "absent.json"), ([a, "--pair", f"{a},{path}:c"], "two of the")] + [
                      ([str(tmp_path / f"{name}.json")], says) for name, _, says in bad_rows]:
        out.unlink(missing_ok=True)
        with pytest.raises(SystemExit, match=says):
            reading_bias.main([*args, "--out", str(out)])
        assert not out.exists()


def _reader_output(classes_by_fabric: dict[str, int], seed: int = 0) -> dict:
    """scripts/reader_ceiling.py's output with a class index per measured fabric."""
    return {"setting": "arm-uniform1", "clips": 10368, "reader": "frames", "seed": seed,
            "measured": {"rows": [{"fabric": f, "pred": c} for f, c in classes_by_fabric.items()]}}


def test_reading_bias_reads_the_reader_on_true_lattices(tmp_path):
    # a reader that names each fabric's S / w, B / w class: its log ratios are the classes' rounding alone
    from sim.measured import over_weight_class, over_weight_ratios, table2_fabrics

    from eval import classes

    fabrics = table2_fabrics()
    path = tmp_path / "reader.json"
    path.write_text(json.dumps(_reader_output({f: over_weight_class(f) for f in fabrics}, seed=1)))
    _script("reading_bias").main([str(path), "--out", str(tmp_path / "bias.json")])
    result = json.loads((tmp_path / "bias.json").read_text())
    (name, reading), = result["readings"].items()
    assert name == f"{path} frames reader on true lattices (arm-uniform1, 10368 clips, seed 1)"
    expected = np.mean([np.log(classes.k_value(over_weight_class(f)) / over_weight_ratios(f)[1]) for f in fabrics])
    assert reading["fabrics"] == 10 and reading["k_bias"]["value"] == pytest.approx(expected)
    assert reading["k_mean_abs"]["value"] < np.log(2)            # rounding to the classes: under a bin on average


def test_fabric_classes_sets_readings_beside_table2_and_beside_each_other(tmp_path, capsys):
    from sim.measured import table2_class, table2_fabrics, tables_class

    from eval import classes

    fabric_classes = _script("fabric_classes")
    fabrics = table2_fabrics()
    on_table2 = {f: table2_class(f) for f in fabrics}
    on_tables = {f: tables_class(f) for f in fabrics}
    def shifted(c: int, dp: int, dk: int) -> int:        # dp, dk bins from class c, kept on the grid
        return classes.class_of(int(np.clip(classes.p_index(c) + dp, 0, classes.NUM_P - 1)),
                                int(np.clip(classes.k_index(c) + dk, 0, classes.NUM_K - 1)))

    # two bins of k from Table 2 for the first three fabrics (up, or down at the grid's top), on it for the rest
    moved = {f: shifted(c, 0, 2 if classes.k_index(c) < classes.NUM_K - 2 else -2) if i < 3 else c
             for i, (f, c) in enumerate(on_table2.items())}
    # one bin of p and one of k from Table 2 for every fabric: within one bin, none exact
    diagonal = {f: shifted(c, 1 if classes.p_index(c) < classes.NUM_P - 1 else -1,
                           1 if classes.k_index(c) < classes.NUM_K - 1 else -1) for f, c in on_table2.items()}
    path = tmp_path / "readers.json"
    path.write_text(json.dumps({"t2": _reader_output(on_table2), "tables": _reader_output(on_tables),
                                "moved": _reader_output(moved, seed=1), "diagonal": _reader_output(diagonal)}))
    keys = ("t2", "tables", "moved", "diagonal")
    result = fabric_classes.main([*(f"{path}:{k}" for k in keys), "--out", str(tmp_path / "c.json")])
    assert json.loads((tmp_path / "c.json").read_text()) == result
    name = {key: next(n for n in result["readings"] if n.startswith(f"{path}:{key} ")) for key in keys}
    t2, tables, moved_reading, diagonal_reading = (result["readings"][name[k]] for k in keys)
    assert t2["within_one_bin"]["table2"] == t2["exact_table2"] == 10
    assert tables["within_one_bin"]["tables"] == 10
    assert tables["within_one_bin"]["table2"] == t2["within_one_bin"]["tables"]        # the same count, both ways
    assert moved_reading["within_one_bin"]["table2"] == 7 and moved_reading["exact_table2"] == 7
    assert diagonal_reading["within_one_bin"]["table2"] == 10 and diagonal_reading["exact_table2"] == 0
    agreement = result["agreement_within_one_bin"]
    assert agreement[name["t2"]][name["moved"]] == agreement[name["moved"]][name["t2"]] == 7
    assert agreement[name["diagonal"]][name["t2"]] == agreement[name["diagonal"]][name["moved"]] == 10   # a bin apart
    assert name["t2"] not in agreement[name["t2"]]
    assert result["references"]["table2"] == {f: fabric_classes._label(c) for f, c in on_table2.items()}
    # a reading without every fabric is named, and nothing is written
    (tmp_path / "c.json").unlink()
    path.write_text(json.dumps({"short": _reader_output({f: on_table2[f] for f in fabrics[:-1]})}))
    with pytest.raises(SystemExit, match=f"no reading of {fabrics[-1]}"):
        fabric_classes.main([f"{path}:short", "--out", str(tmp_path / "c.json")])
    assert not (tmp_path / "c.json").exists()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the sampler reads /proc")
def test_host_samples_sums_what_the_sampler_takes_and_names_a_file_without_samples(tmp_path):
    # The sampler paper_study.sh runs every half second, with a Python process of ours holding 64 MiB counted in it
    # (pytest's own process is named after its script, not python, and others may come and go meanwhile).
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; x = bytearray(64 << 20); x[::4096] = "
                               "b'1' * len(x[::4096]); print('ready', flush=True); time.sleep(60)"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "ready"
        line = subprocess.run(["bash", str(ROOT / "scripts" / "gpu" / "host_sample.sh")], capture_output=True,
                              text=True, check=True).stdout.split()
    finally:
        holder.kill()
        holder.wait()
    assert len(line) == 5 and all(x.isdigit() for x in line)
    used, _shmem, anon, pythons, _mps = map(int, line)
    assert used > 0 and anon >= 64 and pythons >= 1
    # a rise of 100 MiB half-way and a Python process more; a sample whose process columns did not come, run into
    # the next; a line cut off when the sampler was stopped
    rows = [f"{1000 + 100 * (i >= 8)} 10 {500 + 100 * (i >= 8)} {2 + (i >= 8)} 7" for i in range(16)] + ["1100 10"]
    rows[3] = "999 10 " + rows[3]
    (tmp_path / "render.txt").write_text("\n".join(rows) + "\n")
    out = tmp_path / "h.json"
    host_samples.main([f"render={tmp_path / 'render.txt'}", "--out", str(out)])
    written = json.loads(out.read_text())
    got = written["samples"]["render"]
    assert written["command"].startswith("python3 scripts/host_samples.py render=")
    assert (got["samples"], got["used_mib_at_start"], got["peak_used_mib_over_start"]) == (16, 1000, 100)
    assert got["last_quarter_used_mib_over_start"] == [100, 100] and got["peak_python_processes"] == 3
    assert got["samples_cut_short"] == 2
    assert got["max_by_sixteenth"]["python_anon_mib"] == [500] * 8 + [600] * 8
    (tmp_path / "empty.txt").write_text("")
    with pytest.raises(SystemExit, match="empty.txt has no samples"):
        host_samples.main([f"e={tmp_path / 'empty.txt'}", "--out", str(tmp_path / "e.json")])
    assert not (tmp_path / "e.json").exists()
