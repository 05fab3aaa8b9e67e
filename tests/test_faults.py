"""Fault injection at smoke size on CPU: each bad input gives its exit code and message and no result from it.

Cases of issue 16: stale predictions behind a changed or corrupt checkpoint, test clips dropped from
the numbers, colliding real-video inputs, failed clips, a full or read-only disk, NaN/inf and
inconsistent settings, garbled run files. The CLI is run as a subprocess where the exit status and
the absence of a traceback are the point; the rest runs in-process.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from clothgap import checks
from clothgap.config import ConfigError, apply_overrides, preset, problems
from clothgap.errors import InputError, MissingInputError
from clothgap.runs import Run, atomic_write_text, clip_id, mark_done
from tests.test_eval_stage import make_fake_run, stub_predictor

SETTING = "wind-uniform1"


def clothgap(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "clothgap", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env)


def clothgap_here(capsys, monkeypatch, *args: str) -> subprocess.CompletedProcess:
    """The ``clothgap`` entry point in this process (torch and the rest are imported once for the module);
    a traceback would escape as an exception and fail the test."""
    from clothgap.cli import main

    monkeypatch.setattr(sys, "argv", ["clothgap", *map(str, args)])
    capsys.readouterr()
    try:
        main()
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    out = capsys.readouterr()
    return subprocess.CompletedProcess(args, code, out.out, out.err)


def assert_error(r: subprocess.CompletedProcess, code: int, *phrases: str) -> None:
    """Exit ``code``, an ``error:`` line naming each phrase on stderr, and no traceback."""
    out = r.stdout + r.stderr
    assert r.returncode == code, out
    assert "Traceback" not in out, out
    assert "error:" in r.stderr, out
    for phrase in phrases:
        assert phrase in r.stderr, (phrase, out)


def temp_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if ".tmp" in p.name]


def can_mount_tmpfs() -> bool:
    if shutil.which("unshare") is None:
        return False
    r = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c",
                        "mount -t tmpfs -o size=64k tmpfs /mnt"], capture_output=True)
    return r.returncode == 0


def in_tmpfs(mount: Path, size: str, script: str, read_only: bool = False) -> subprocess.CompletedProcess:
    """Run a shell ``script`` with a private tmpfs of ``size`` on ``mount`` (a real full / read-only disk)."""
    ro = f"mount -o remount,ro {mount} && " if read_only else ""
    return subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c",
                           f"mount -t tmpfs -o size={size} tmpfs {mount} && {ro}{script}"],
                          capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})


def real_checkpoints(run: Run, image_size: int = 32) -> None:
    """Replace every train folder's stub checkpoint with an untrained lrcn in the checkpoint contract."""
    import dataclasses

    import torch

    from learn.models import build_model, model_args

    train = dataclasses.replace(run.config.train, width=4, fc6=16, hidden=8, image_size=image_size)
    args = model_args(train)
    for ckpt in run.root.glob("train/*/*/*/s*/checkpoint.pt"):
        torch.manual_seed(0)
        torch.save({"model": build_model("lrcn", **args).state_dict(), "model_name": "lrcn", "model_args": args,
                    "num_classes": 54, "setting": SETTING, "variant": ckpt.parts[-4], "seed": 0,
                    "config": {"train": dataclasses.asdict(train)}}, ckpt)


# ------------------------------------------------------------------ config validation (item 8, 9, 10)

@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_nan_and_inf_settings_are_refused(value):
    for key in ("sim.fps", "train.lr", "eval.confidence", "sim.settle_s"):
        with pytest.raises(ConfigError, match="finite"):
            apply_overrides(preset("smoke"), [f"{key}={value}"])
    assert checks.number("x", float(value), 0) and checks.number("x", float(value))       # open or unbounded ends


def test_nan_on_the_command_line_is_one_error_line_and_starts_no_run(tmp_path):
    r = clothgap("sim", "--preset", "smoke", "--set", "sim.fps=nan", "--out", tmp_path / "r")
    assert_error(r, 2, "sim.fps", "finite")
    assert not (tmp_path / "r").exists()


def test_frames_shorter_than_clip_len_is_refused_before_any_work(tmp_path):
    cfg = apply_overrides(preset("smoke"), ["sim.frames=5"])
    assert any("sim.frames=5" in p and "train.clip_len=10" in p for p in problems(cfg))
    assert not problems(apply_overrides(preset("smoke"), ["sim.frames=10"]))
    r = clothgap("sim", "--preset", "smoke", "--set", "sim.frames=5", "--out", tmp_path / "r")
    assert_error(r, 2, "sim.frames=5", "train.clip_len=10")
    assert not (tmp_path / "r" / "config.json").exists()


def test_garbled_config_json_and_out_that_is_a_file(tmp_path):
    run = tmp_path / "r"
    run.mkdir()
    (run / "config.json").write_bytes(bytes(range(256)) * 4)
    assert_error(clothgap("render", run), 2, "config.json", "not valid JSON")
    (run / "config.json").write_text('{"sim": {"frames": [1, 2]}}')
    assert_error(clothgap("render", run), 2, "sim.frames")

    afile = tmp_path / "afile"
    afile.write_text("keep me")
    assert_error(clothgap("sim", "--preset", "smoke", "--out", afile), 2, "is a file")
    assert_error(clothgap("sim", "--preset", "smoke", "--out", afile / "run"), 2, str(afile))
    assert afile.read_text() == "keep me"
    assert_error(clothgap("render", run, "--out", tmp_path / "other"), 2, "RUN_DIR", "--out")


def test_config_json_with_unknown_or_missing_settings_is_never_silently_defaulted(tmp_path, capsys, monkeypatch):
    run = Run.create_or_resume(tmp_path / "r", preset("smoke"))
    path = run.root / "config.json"
    full = json.loads(path.read_text())

    def write(edit) -> None:
        data = json.loads(json.dumps(full))
        edit(data)
        path.write_text(json.dumps(data))

    write(lambda d: d["sim"].update(gravity=3) or d.update(colour="red"))
    assert_error(clothgap_here(capsys, monkeypatch, "render", run.root), 2, str(path), "colour, sim.gravity",
                 "another version")

    # Nothing finished yet: the defaults are taken, with a warning, and recorded in the file.
    write(lambda d: d["sim"].pop("substeps") and d["train"].pop("lr"))
    with pytest.warns(UserWarning, match="lacks setting.*sim.substeps, train.lr.*taking the defaults"):
        assert Run.open(run.root).config == apply_overrides(preset("smoke"), ["train.lr=0.001"])  # the code's default
    recorded = json.loads(path.read_text())
    assert recorded["train"]["lr"] == 0.001 and recorded["sim"]["substeps"] == 8

    # Finished sim work: a missing sim setting is an error naming it and its default; missing
    # train, eval and execution settings still take their defaults.
    folder = run.sim_dir(SETTING) / clip_id(0)
    folder.mkdir(parents=True)
    mark_done(folder)
    write(lambda d: d["sim"].pop("substeps") and d["train"].pop("lr"))
    r = clothgap_here(capsys, monkeypatch, "render", run.root)
    assert_error(r, 2, str(path), "sim.substeps (default 8; sim work is done)", "the value the run was made with")
    assert "train.lr" not in r.stderr          # no finished work depends on it yet
    with pytest.raises(ConfigError, match="sim.substeps"):
        Run.create_or_resume(run.root, preset("smoke"))
    write(lambda d: d["eval"].pop("bootstrap") and d["sim"].pop("device"))
    with pytest.warns(UserWarning, match="sim.device, eval.bootstrap"):
        assert Run.open(run.root).config.sim.device == "auto"
    # A run made before a setting existed whose default is the old behaviour opens (an older clothgap's run).
    write(lambda d: d["sim"].pop("self_collision") is False and d["train"].pop("bottleneck"))
    with pytest.warns(UserWarning, match="sim.self_collision, train.bottleneck"):
        assert Run.open(run.root).config.sim.self_collision is False
    assert json.loads(path.read_text())["sim"]["self_collision"] is False
    write(lambda d: d["sim"].pop("arm_view_zoom"))             # runs before it framed arm by its camera box alone
    with pytest.warns(UserWarning, match="sim.arm_view_zoom"):
        assert Run.open(run.root).config.sim.arm_view_zoom == 1.0
    write(lambda d: d["sim"].pop("density_range"))            # runs before it made every class at the basis's
    with pytest.warns(UserWarning, match="sim.density_range"):
        assert Run.open(run.root).config.sim.density_range == ()
    write(lambda d: d["sim"].pop("table_spread"))             # runs before it scaled the basis's tables alone
    with pytest.warns(UserWarning, match="sim.table_spread"):
        assert Run.open(run.root).config.sim.table_spread == 0.0
    write(lambda d: d["sim"].pop("table_shape"))
    with pytest.warns(UserWarning, match="sim.table_shape"):
        assert Run.open(run.root).config.sim.table_shape == "entries"


@pytest.mark.skipif(not can_mount_tmpfs(), reason="needs unshare and tmpfs for a real read-only folder")
def test_read_only_out_is_one_error_line(tmp_path):
    mount = tmp_path / "ro"
    mount.mkdir()
    r = in_tmpfs(mount, "1m", f"{sys.executable} -m clothgap sim --preset smoke --out {mount}/run",
                 read_only=True)
    assert_error(r, 2, f"{mount}/run", "Read-only file system")


# ------------------------------------------------------------------ run files at split and eval time (item 9)

def test_missing_meta_json_at_split_time_names_it(tmp_path):
    from learn.split import get_or_make_split

    run = Run.create_or_resume(tmp_path / "r", preset("smoke"))
    for i in range(4):
        folder = run.sim_dir(SETTING) / clip_id(i)
        folder.mkdir(parents=True)
        if i != 2:
            (folder / "meta.json").write_text(json.dumps({"class_index": 0}))
        mark_done(folder)
    with pytest.raises(MissingInputError, match=r"c00002/meta.json is missing.*clothgap sim"):
        get_or_make_split(run, SETTING)
    (run.sim_dir(SETTING) / "c00002" / "meta.json").write_bytes(b"\xff\xfe{garbled")
    with pytest.raises(InputError, match=r"c00002/meta.json is not valid JSON"):
        get_or_make_split(run, SETTING)
    assert not run.split_path(SETTING).exists()


# ------------------------------------------------------------------ stale predictions (item 3)

def test_predictions_are_recomputed_when_the_checkpoint_changes(tmp_path):
    from eval.stage import run_eval, stale_checkpoints

    run = make_fake_run(tmp_path / "run", variants=("paper",))
    assert run_eval(run, progress=False, predictor=stub_predictor)["predicted"] == 1
    assert run_eval(run, progress=False, predictor=stub_predictor)["reused"] == 1
    ckpt = run.train_dir(SETTING, "paper", "lrcn", 0) / "checkpoint.pt"
    record = json.loads(next(run.eval_dir.glob("predictions/**/paper.json")).read_text())
    assert record["checkpoint_sha256"] and len(record["clips"]) == 8 and record["left_out"] == []
    ckpt.write_bytes(b"another model")
    assert stale_checkpoints(run) == [str(ckpt.relative_to(run.root))]
    out = run_eval(run, progress=False, predictor=stub_predictor)
    assert out["predicted"] == 1 and out["reused"] == 0
    assert stale_checkpoints(run) == []


def test_garbage_checkpoint_is_an_error_not_the_old_accuracy(tmp_path, capsys, monkeypatch):
    from eval.stage import run_eval

    run = make_fake_run(tmp_path / "run", variants=("paper",))
    run_eval(run, progress=False, predictor=stub_predictor)          # old, good numbers
    ckpt = run.train_dir(SETTING, "paper", "lrcn", 0) / "checkpoint.pt"
    ckpt.write_bytes(b"\x80\x04garbage, not a checkpoint" * 10)
    r = clothgap_here(capsys, monkeypatch, "eval", run.root)
    assert_error(r, 2, "checkpoint", str(ckpt), "clothgap train")
    assert "weights_only" not in r.stderr
    assert not list(run.eval_dir.glob("predictions/**/*.csv"))    # the old predictions are not left to reuse
    assert_error(clothgap_here(capsys, monkeypatch, "report", run.root), 2, "stale", "clothgap eval")
    assert not (run.report_dir / "report.html").exists()


# ------------------------------------------------------------------ dropped test clips (item 4)

def test_dropped_test_clips_are_counted_reported_and_fail_the_stage(tmp_path, capsys, monkeypatch):
    run = make_fake_run(tmp_path / "run", variants=("paper",), frames=10)
    real_checkpoints(run)
    test = json.loads(run.split_path(SETTING).read_text())["test"]
    folder = run.render_dir("paper", SETTING)
    (folder / test[1] / "ldr" / "0003.png").write_bytes(b"not a png")
    (folder / test[2] / "meta.json").unlink()
    (folder / test[3] / "DONE").unlink()

    r = clothgap_here(capsys, monkeypatch, "eval", run.root)
    assert_error(r, 1, "3 test clip(s) left out", test[1], test[2], test[3], "--allow-failures")
    assert f"5 of {len(test)} test clips" in r.stdout, r.stdout
    summary = json.loads((run.eval_dir / "summary.json").read_text())
    reasons = {x["clip_id"]: x["reason"] for x in summary["left_out"]}
    assert set(reasons) == {test[1], test[2], test[3]}
    assert "0003.png" in reasons[test[1]] and "meta.json is missing" in reasons[test[2]]
    assert "no DONE" in reasons[test[3]]
    predicted = pd.read_csv(next(run.eval_dir.glob("predictions/**/paper.csv")), dtype={"clip_id": str})
    assert set(predicted["clip_id"]) == set(test) - set(reasons)

    r = clothgap_here(capsys, monkeypatch, "eval", run.root, "--allow-failures")
    assert r.returncode == 0 and "warning: eval: 3 test clip(s) left out" in r.stderr, r.stdout + r.stderr
    assert "Traceback" not in r.stderr


# ------------------------------------------------------------------ eval real (item 5, 10)

def test_eval_real_refuses_colliding_inputs_and_duplicate_or_inf_truth(tmp_path, capsys, monkeypatch):
    from eval.real import read_truth
    from tests.test_eval_real import fresh_model, write_video

    videos = tmp_path / "videos"
    (videos / "x").mkdir(parents=True)
    write_video(videos / "x.mp4")
    for t in range(12):
        Image.fromarray(np.full((32, 32, 3), 10 * t, np.uint8)).save(videos / "x" / f"{t:03d}.png")
    truth = tmp_path / "truth.csv"
    pd.DataFrame({"video": ["x.mp4", "x"], "bending_N_m2": [1e-5, 2e-5],
                  "area_weight_kg_m2": [0.1, 0.2]}).to_csv(truth, index=False)
    model = fresh_model(tmp_path / "run")
    r = clothgap_here(capsys, monkeypatch, "eval", "real", videos, "--truth", truth, "--model", model, "--out", tmp_path / "out")
    assert_error(r, 2, "x and x.mp4 would both be clips/x")
    assert not (tmp_path / "out" / "clips").exists() and not (tmp_path / "out" / "table4.csv").exists()

    pd.DataFrame({"video": ["a", "a"], "bending_N_m2": [1e-5, 2e-5],
                  "area_weight_kg_m2": [0.1, 0.2]}).to_csv(truth, index=False)
    with pytest.raises(InputError, match="listed more than once: a"):
        read_truth(truth)
    pd.DataFrame({"video": ["a", "b"], "bending_N_m2": [1e-5, np.inf],
                  "area_weight_kg_m2": [0.1, 0.2]}).to_csv(truth, index=False)
    with pytest.raises(InputError, match="infinite.*b"):
        read_truth(truth)


# ------------------------------------------------------------------ failed clips, full disk (item 7)

def fake_sim_run(root: Path, clips: int = 2) -> Run:
    run = Run.create_or_resume(root, apply_overrides(preset("smoke"), ["render.variants=paper"]))
    for i in range(clips):
        folder = run.sim_dir(SETTING) / clip_id(i)
        folder.mkdir(parents=True)
        (folder / "clip.npz").write_bytes(b"not an npz")
        (folder / "meta.json").write_text(json.dumps({"clip_id": clip_id(i), "index": i, "class_index": 0}))
        mark_done(folder)
    return run


def test_render_with_failed_clips_exits_1_naming_them(tmp_path, capsys, monkeypatch):
    run = fake_sim_run(tmp_path / "r")
    r = clothgap_here(capsys, monkeypatch, "render", run.root)
    assert_error(r, 1, "render: 2 clip(s) failed", f"paper/{SETTING}/c00000", f"paper/{SETTING}/c00001",
                 "--allow-failures")
    assert '"rendered": 0' in r.stdout
    for i in range(2):
        folder = run.render_dir("paper", SETTING) / clip_id(i)
        assert (folder / "FAILED").is_file() and not (folder / "DONE").exists()


def test_failed_marker_on_a_full_disk_is_reported_not_a_traceback(tmp_path, monkeypatch):
    from render import stage

    run = fake_sim_run(tmp_path / "r", clips=1)
    write = stage.atomic_write_json

    def full_disk(path, data):
        if path.name == stage.FAILED:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return write(path, data)

    monkeypatch.setattr(stage, "atomic_write_json", full_disk)
    summary = stage.run_render(run, progress=False)
    (failed,) = summary["failed"]
    assert failed["clip_id"] == "c00000" and "FAILED marker could not be written: No space left" in failed["error"]
    assert not (run.render_dir("paper", SETTING) / "c00000" / "DONE").exists()


def test_frame_writes_on_a_full_disk_stop_with_the_path_and_leave_no_partial_clip(tmp_path, monkeypatch):
    from render import stage
    from clothgap.errors import StorageError

    run = fake_sim_run(tmp_path / "r", clips=2)

    def full_disk(clip, variant, out_dir, **kwargs):
        (out_dir / "ldr").mkdir(parents=True, exist_ok=True)
        (out_dir / "ldr" / "0000.png").write_bytes(b"half")
        raise OSError(errno.ENOSPC, "No space left on device", str(out_dir / "ldr" / "0001.png"))

    monkeypatch.setattr(stage, "render_clip", full_disk)
    monkeypatch.setattr(stage.SimClip, "load", staticmethod(lambda folder: None))
    monkeypatch.setattr(stage, "clip_index_of", lambda clip, folder: 0)
    with pytest.raises(StorageError, match=r"c00000/ldr/0001.png: No space left on device"):
        stage.run_render(run, progress=False)
    assert not (run.render_dir("paper", SETTING) / "c00000").exists()
    assert not temp_files(run.root)


def test_atomic_write_leaves_no_temporary_file_on_a_full_disk(tmp_path, monkeypatch):
    target = tmp_path / "summary.json"
    target.write_text("old")

    def full(self, text, *a, **k):
        Path.write_bytes(self, text[:3].encode())
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    monkeypatch.setattr(Path, "write_text", full)
    with pytest.raises(OSError):
        atomic_write_text(target, "new contents")
    monkeypatch.undo()
    assert target.read_text() == "old" and not temp_files(tmp_path)


@pytest.mark.skipif(not can_mount_tmpfs(), reason="needs unshare and tmpfs for a real full disk")
def test_sim_on_a_real_full_disk_is_one_error_line_and_resumable(tmp_path):
    mount = tmp_path / "disk"
    mount.mkdir()
    run = mount / "run"
    # A 160 KiB disk: config.json fits, the 16 clips of the smoke preset do not.
    r = in_tmpfs(mount, "160k", f"{sys.executable} -m clothgap sim --preset smoke "
                 f"--set sim.frames=10 --set train.clip_len=10 --out {run}; echo rc=$? >&2; "
                 f"find {run} -name '*.tmp*' >&2; "
                 f"for d in {run}/sim/{SETTING}/*/; do [ -d $d ] || continue; [ -e $d/DONE ] || echo PARTIAL $d >&2; "
                 f"done")          # no clip folder at all (the first one could not be made) leaves the glob as is
    err = r.stderr
    assert "rc=2" in err and "error: cannot write" in err and "No space left on device" in err, err
    assert "Traceback" not in err and ".tmp" not in err.split("rc=2")[1] and "PARTIAL" not in err, err


def test_sim_failed_clips_are_named_and_fail_the_command(tmp_path, monkeypatch):
    from clothgap.cli import StageFailures, check_failures
    from sim import stage

    run = Run.create_or_resume(tmp_path / "r", apply_overrides(preset("smoke"), [
        "sim.classes=0", "sim.sequences_per_class=2", "sim.frames=10", "sim.grid_vertices=4"]))
    real = stage.simulate_scenes

    def explode_first(scenes, **kw):
        results = real(scenes, **kw)
        results[0] = stage.ClipResult(None, "frame 3: non-finite positions")
        return results

    monkeypatch.setattr(stage, "simulate_scenes", explode_first)
    summary = stage.run_sim(run, progress=False)
    assert summary["failed"] == 1 and summary["failed_clips"][0]["clip_id"] == "c00000"
    with pytest.raises(StageFailures, match=rf"sim: 1 clip\(s\) failed: {SETTING}/c00000: frame 3.*allow-failures"):
        check_failures("sim", summary, allow_failures=False)
    check_failures("sim", summary, allow_failures=True)


def test_variant_file_named_dots_is_refused(tmp_path, monkeypatch):
    from render.variants import USER_VARIANTS_ENV, VariantError, get_variant

    (tmp_path / "...toml").write_text('description = "escapes the run folder as render/.."\n')
    monkeypatch.setenv(USER_VARIANTS_ENV, str(tmp_path))
    with pytest.raises(VariantError, match=r"\.\.\.toml: a variant file's name must be"):
        get_variant("paper")
    (tmp_path / "...toml").rename(tmp_path / "binary.toml")
    (tmp_path / "binary.toml").write_bytes(b"\xff\xfe\x00garbled")
    with pytest.raises(VariantError, match="binary.toml: not valid TOML"):
        get_variant("binary")
