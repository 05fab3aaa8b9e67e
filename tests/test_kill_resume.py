"""kill -9 in the middle of each stage, then the same command again: the results are those of an uninterrupted run.

Each case copies the inputs of one stage from a reference run (every stage run once, uninterrupted, same config),
runs that stage's real command in a subprocess that SIGKILLs itself at a fixed point of its work
(``$CLOTHGAP_KILL_AT``, ``clothgap.files.kill_point``: at the N-th atomic write of a matching file, its temporary
file written and not yet in place), resumes with the same command, and compares a digest of every file the stage
wrote with the reference's, and finds no temporary file left. A tiny study (2 classes x 4 sequences, 10 frames,
32 px, one variant, 2 epochs) keeps the module to a few seconds per stage on 2 cores.

Every result must be byte-identical but one: the linear HDR frames (``hdr/*.exr``) agree to 1e-5. Mitsuba gives
a clip a few 1-ulp different radiances depending on whether its scene was built fresh or retargeted from the
previous clip (``render.reuse_scenes``; with it off, renders are bit-identical), and a resumed run builds a fresh
scene at its first unfinished clip; once in a full suite run on a loaded CPU a frame differed by more than 1e-6
(the same family as two renders of one frame on LLVM, tests/test_render_tonemap_device.py). A failure names the
largest difference. The 8-bit frames the network reads (``frames.npy``, PNG) are compared exactly.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from clothgap.files import KILL_AT_ENV

SETTINGS = ["sim.classes=0,53", "sim.sequences_per_class=4", "sim.frames=10", "sim.grid_vertices=8",
            "render.variants=paper", "train.epochs=2", "train.num_threads=1"]

# stage: (kill point, folders it writes, folders it reads from the reference)
CASES = {
    "sim": ("*/sim/*/DONE:3", ["sim"], []),
    "render": ("*/render/*/DONE:3", ["render"], ["sim"]),
    # the 2nd epoch's metrics.csv: last.pt holds epoch 0, so the resumed run restores it and trains epoch 1
    "train": ("*/train/*/metrics.csv:2", ["splits", "cache", "train"], ["sim", "render"]),
    "eval": ("*/eval/predictions/*.json:1", ["eval"], ["sim", "render", "splits", "cache", "train"]),
}

# JSON keys whose values differ between two identical runs: wall-clock times (also any "*_seconds"), the cache
# index's DONE modification times, the run folder's own path.
# scene_builds (a render meta): whether a clip built its scene or took a pooled one follows what its process
# rendered before it (a resumed render's first clip builds), not the clip.
VOLATILE_KEYS = {"seconds", "signature", "run", "scene_builds"}


def clothgap_in_process(*args: object) -> int:
    """The ``clothgap`` command in this process (no second import of torch, Warp and Mitsuba)."""
    from clothgap.cli import main

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sys, "argv", ["clothgap", *map(str, args)])
        mp.delenv(KILL_AT_ENV, raising=False)
        try:
            main()
        except SystemExit as e:
            return e.code if isinstance(e.code, int) else 1
    return 0


def temp_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if ".tmp" in p.name]


def _canonical(value: object) -> object:
    """Plain data with tensors and arrays as digests and the volatile keys left out."""
    import torch

    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        return f"{value.dtype}{value.shape}:{hashlib.sha256(np.ascontiguousarray(value).tobytes()).hexdigest()}"
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))
                if k not in VOLATILE_KEYS and not str(k).endswith("_seconds")}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    return value


def content_digest(path: Path, root: Path) -> str | np.ndarray:
    """A file's result, independent of when and in which folder it was computed (an EXR: its pixels)."""
    import torch

    if path.suffix == ".exr":
        from render.exr import read_exr

        return read_exr(path)
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:    # zip entries carry timestamps; the arrays do not
            data: object = {k: z[k] for k in z.files}
    elif path.name == "last.pt":                        # its metrics carry each epoch's seconds
        data = torch.load(path, map_location="cpu", weights_only=True)
    elif path.suffix == ".json" or path.name == "DONE":
        data = json.loads(path.read_text())
    elif path.name == "metrics.csv":
        rows = [line.split(",") for line in path.read_text().splitlines()]
        keep = [i for i, name in enumerate(rows[0]) if name != "seconds"]
        data = [[row[i] for i in keep] for row in rows]
    elif path.suffix in (".md", ".csv"):
        data = path.read_text().replace(str(root), "<run>")
    else:
        return hashlib.sha256(path.read_bytes()).hexdigest()    # frames.npy, PNG, EXR, checkpoint.pt, ...
    return hashlib.sha256(json.dumps(_canonical(data), sort_keys=True).encode()).hexdigest()


def mismatches(got: dict, expected: dict) -> list[str]:
    """The files missing, extra or different in ``got`` (EXR pixels: within 1e-6, see the module's docstring)."""
    def same(a: object, b: object) -> bool:
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.shape == b.shape
                    and np.allclose(a, b, rtol=1e-5, atol=1e-5))
        return a == b

    def named(path: str) -> str:
        a, b = got[path], expected[path]
        if isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.shape == b.shape:
            return f"{path} (largest difference {float(np.abs(a - b).max()):.3g})"
        return path

    both = sorted(set(got) & set(expected))
    return sorted(set(got) ^ set(expected)) + [named(p) for p in both if not same(got[p], expected[p])]


def digest(root: Path, folders: list[str]) -> dict[str, str | np.ndarray]:
    """``{relative path: content digest}`` of every file under ``folders`` (TensorBoard logs left out: their
    names and records carry the host and the time)."""
    out = {}
    for folder in folders:
        for path in sorted((root / folder).rglob("*")):
            rel = path.relative_to(root)
            if path.is_file() and "tb" not in rel.parts:
                try:
                    out[str(rel)] = content_digest(path, root)
                except Exception as e:   # noqa: BLE001 - a file cut short by the kill
                    out[str(rel)] = f"unreadable: {e}"

    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The study run once, uninterrupted, stage by stage (torch's thread count restored afterwards)."""
    import torch

    threads = torch.get_num_threads()
    root = tmp_path_factory.mktemp("kill") / "reference"
    sets = [arg for s in SETTINGS for arg in ("--set", s)]
    assert clothgap_in_process("sim", "--preset", "smoke", *sets, "--out", root) == 0
    for stage in ("render", "train", "eval"):
        assert clothgap_in_process(stage, root) == 0
    yield root
    torch.set_num_threads(threads)


@pytest.mark.parametrize("stage", list(CASES))
def test_killed_stage_resumes_to_the_uninterrupted_result(stage, reference, tmp_path):
    point, writes, reads = CASES[stage]
    root = tmp_path / "run"
    root.mkdir()
    shutil.copy2(reference / "config.json", root / "config.json")
    for folder in reads:
        shutil.copytree(reference / folder, root / folder)

    env = {**os.environ, "OMP_NUM_THREADS": "1", KILL_AT_ENV: point}
    r = subprocess.run([sys.executable, "-m", "clothgap", stage, str(root)], capture_output=True, text=True, env=env)
    assert r.returncode == -signal.SIGKILL, r.stdout[-2000:] + r.stderr[-2000:]
    expected = digest(reference, writes)
    assert mismatches(digest(root, writes), expected) and temp_files(root), \
        "the kill came after the stage's work, not in the middle of it"

    assert clothgap_in_process(stage, root) == 0
    assert mismatches(digest(root, writes), expected) == []
    assert temp_files(root) == []
