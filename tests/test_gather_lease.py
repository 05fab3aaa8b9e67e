"""scripts/gather_lease.py: a lease's returned lanes gathered into one results file, by kind, nothing lost."""
from __future__ import annotations

import importlib.util
import io
import json
import tarfile
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "gather_lease", Path(__file__).resolve().parents[1] / "scripts" / "gather_lease.py")
gather_lease = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(gather_lease)

TABLE = {"run": "/tmp/r", "recipes": [{"recipe": "baseline", "model": "lrcn", "acc": 0.5, "curves": {"s0": []}}]}
PAIRED = {"a": "paper:baseline@0", "b": "paper:baseline@0", "acc_a_minus_b": 0.02}
MEASURED = {"variant": "heldout", "fabrics": ["denim"], "models": [{"seed": 0, "match": []}]}
TIMINGS = {"command": "python3 benchmarks/study.py --timings RUN", "timings": {"stages": {}}}
MEASURED_MD = """# Measured fabrics

## lrcn trained on paper (wind-uniform1, seed 0)

| Fabric | Clips | Predicted (p, k) | Table 2 (p, k) |
|---|---|---|---|
| 11oz-black-denim | 4 | (1, 2) | (3, 3) |
| royal-target | 4 | (2, 5) | (20, 20) |

| Score (over fabrics) | Value [95% interval] |
|---|---|
| within1 | 0.50 [0.20, 0.80] |
"""


def _tarball(path: Path, files: dict[str, bytes]) -> None:
    with tarfile.open(path, "w:gz") as tar:
        for name, data in files.items():
            info = tarfile.TarInfo(f"./{name}")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))


def _json(doc) -> bytes:
    return json.dumps(doc).encode()


def _lane(folder: Path, files: dict[str, bytes], log: str | None = None) -> Path:
    folder.mkdir(parents=True)
    _tarball(folder / "queue.tgz", files)
    if log is not None:
        (folder / "queue.log").write_text(log)
    return folder


def _run(tmp_path: Path, *args: str) -> dict:
    out = tmp_path / "results.json"
    gather_lease.main([str(out), *args, "--command", "bash scripts/gpu/detached.sh P", "--code", "abc1234",
                       "--device", "nvidia-h100-x4"])
    return json.loads(out.read_text())


def test_each_file_goes_in_by_what_it_is_with_the_step_times_and_the_fabric_tables(tmp_path):
    log = "== a-data (100 s left):  cmd\n== a-data: exit 0 after 383 s\n== a-train: exit 1 after 5 s\n"
    lane = _lane(tmp_path / "lane1", {
        "a-train/transfer-paper.json": _json(TABLE), "a-cmp/pooled.json": _json(PAIRED),
        "a-measured/measured.json": _json(MEASURED), "a-measured/measured.md": MEASURED_MD.encode(),
        "a-data/study-timings.json": _json(TIMINGS), "a-data/notes.json": _json([1, 2]),
        "a-data/stage_log.txt": b"not gathered"}, log)
    result = _run(tmp_path, f"arm={lane}", "--name", "transfer-paper=arm-paper", "--fact", "held_s=1570.1",
                  "--fact", "note=two lanes")
    assert result["tables"] == {"arm-paper": TABLE}
    assert result["paired"] == {"pooled": PAIRED}
    assert result["measured"] == {"measured": MEASURED}
    assert result["gpu_timings"] == {"study-timings": TIMINGS}
    assert result["other"] == {"notes": [1, 2]}
    rows = result["measured_fabrics"]["measured"]["lrcn trained on paper (wind-uniform1, seed 0)"]
    assert [r["Fabric"] for r in rows] == ["11oz-black-denim", "royal-target"]      # not the scores' table
    assert rows[1]["Table 2 (p, k)"] == "(20, 20)"
    assert result["queue_step_seconds"] == {"arm": {"a-data": 383.0}}            # the failed step has no time
    assert result["facts"] == {"held_s": 1570.1, "note": "two lanes"}
    assert result["gathered_by"]["inputs"] == {"arm": ["queue.log", "queue.tgz"]}
    assert str(tmp_path) not in json.dumps(result)                                # no machine's paths


def test_one_stem_from_two_steps_is_kept_once_when_the_same_and_under_each_step_when_not(tmp_path):
    other = dict(TABLE, run="/tmp/other")
    lane1 = _lane(tmp_path / "lane1", {"t-train/transfer.json": _json(TABLE), "t-heldout/transfer.json": _json(TABLE),
                                       "t-data/study-timings.json": _json(TIMINGS)})
    tarball = tmp_path / "queue-2.tgz"
    _tarball(tarball, {"w-data/study-timings.json": _json(dict(TIMINGS, command="other"))})
    result = _run(tmp_path, str(lane1), str(tarball))
    assert result["tables"] == {"transfer": TABLE}
    assert set(result["gpu_timings"]) == {"t-data/study-timings", "w-data/study-timings"}
    _tarball(tarball, {"w-train/transfer.json": _json(other)})
    result = _run(tmp_path, str(lane1), str(tarball))
    assert result["tables"] == {"t-train/transfer": TABLE, "w-train/transfer": other}
    # two lanes' measured fabrics of one name: each keeps its own step's per-fabric tables
    wind_md = MEASURED_MD.replace("royal-target | 4 | (2, 5)", "royal-target | 4 | (20, 10)")
    _tarball(tarball, {"w-measured/measured.json": _json(dict(MEASURED, variant="paper")),
                       "w-measured/measured.md": wind_md.encode()})
    arm = _lane(tmp_path / "lane3", {"a-measured/measured.json": _json(MEASURED),
                                     "a-measured/measured.md": MEASURED_MD.encode()})
    result = _run(tmp_path, str(arm), str(tarball))
    royal = {key: next(r["Predicted (p, k)"] for r in tables[next(iter(tables))] if r["Fabric"] == "royal-target")
             for key, tables in result["measured_fabrics"].items()}
    assert royal == {"a-measured/measured": "(2, 5)", "w-measured/measured": "(20, 10)"}


def test_bad_inputs_are_named(tmp_path):
    lane = _lane(tmp_path / "lane1", {"s/broken.json": b"{not json"})
    with pytest.raises(SystemExit, match=r"s/broken.json is not JSON"):
        _run(tmp_path, str(lane))
    with pytest.raises(SystemExit, match="no such lane folder or tarball"):
        _run(tmp_path, str(tmp_path / "missing"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match="neither queue.log nor"):
        _run(tmp_path, str(tmp_path / "empty"))
    (tmp_path / "cut.tgz").write_bytes(b"\x1f\x8b truncated")
    with pytest.raises(SystemExit, match="cannot read"):
        _run(tmp_path, str(tmp_path / "cut.tgz"))
    with pytest.raises(SystemExit, match="KEY=VALUE"):
        _run(tmp_path, str(tmp_path / "lane1"), "--name", "no-equals")


def test_a_path_into_the_steps_own_output_folder_is_written_as_out(tmp_path):
    timings = {"command": "python3 benchmarks/study.py --timings /tmp/arm384t --out "
                          "/tmp/queue/lane1/out/a4-data/study-timings.json", "run": "/tmp/arm384t",
               "timings": {"log": "/tmp/queue/out/a4-data/x.txt", "other": "/tmp/queue/out/a4-train/y.txt"},
               "kept": ["lane1/out/a4-data/x", "/tmp/my dir/out/a4-data/x", "https://h/out/a4-data/x"]}
    lane = _lane(tmp_path / "lane1", {"a4-data/study-timings.json": _json(timings)})
    got = _run(tmp_path, str(lane))["gpu_timings"]["study-timings"]
    assert got["command"] == "python3 benchmarks/study.py --timings /tmp/arm384t --out $OUT/study-timings.json"
    assert got["run"] == "/tmp/arm384t"                          # the run the plan names is not a machine's folder
    assert got["timings"] == {"log": "$OUT/x.txt", "other": "/tmp/queue/out/a4-train/y.txt"}   # another step's stays
    assert got["kept"] == timings["kept"]            # not an absolute path from its start: a relative one, a URL


def test_a_measured_file_with_its_rows_as_numbers_needs_no_markdown(tmp_path):
    rows = [{"fabric": "royal-target", "pred": 44, "table2_class": 53, "bending_N_m": 0.000171}]
    doc = dict(MEASURED, models=[{"seed": 0, "match": [], "per_fabric": rows}])
    lane = _lane(tmp_path / "lane1", {"m/measured.json": _json(doc), "m/measured.md": MEASURED_MD.encode()})
    result = _run(tmp_path, str(lane))
    assert result["measured"]["measured"]["models"][0]["per_fabric"] == rows
    assert "measured_fabrics" not in result                  # the text tables only for files without the rows


def test_a_file_that_is_not_utf8_is_named(tmp_path):
    lane = _lane(tmp_path / "lane1", {"a-data/bad.json": b'{"x": "\xff"}'})
    with pytest.raises(SystemExit, match="a-data/bad.json is not JSON"):
        _run(tmp_path, str(lane))
