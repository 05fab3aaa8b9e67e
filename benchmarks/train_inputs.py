"""What training builds before its first epoch, in one process against a process pool: a setting's frame cache and
its clips' lattices (``learn.stage.prepare_shared_inputs``).

    python benchmarks/train_inputs.py [--clips 2592] [--frames 40] [--size 112] [--vertices 1700]
                                      [--processes N] [--workdir /tmp] [--out FILE]

The `paper` and `study` presets' regressor reads each frame's simulated 8 x 8 lattice, and every training reads a
(variant, setting)'s frames packed into one array; both are built once by the train stage's driver before any
model starts. On an adaptive setting each clip needs a lattice index per frame (its mesh changes every frame).
This writes a stand-in setting in the run layout (random frames as each clip's ``frames.npy``; adaptive-like sim
clips of about ``--vertices`` vertices a frame, a different mesh each frame), then times, in one process and in a
pool of ``--processes`` (default: every CPU of this host):

* ``lattice``: ``learn.geometry.clip_lattices`` over every clip, and the lattice index as it was computed
  before (one (points, vertices, 2) temporary a frame) over the first 256 clips, per clip;
* ``cache``: ``learn.dataset.build_cache`` at ``--size`` (the render resolution: clips copied as they are),
  each way three times, alternating, the frames in the page cache (each build ends by syncing its array to disk).

Writes benchmarks/results/train_inputs-<host>-n<clips>.json with the command. The stand-in folder is removed.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, frame_set_arguments, write_result  # noqa: E402  (benchmarks/common.py)
from clothgap.config import preset  # noqa: E402
from clothgap.parallel import host_processes  # noqa: E402
from clothgap.runs import Run, atomic_write_json, clip_id, mark_done  # noqa: E402
from clothgap.settings import apply_overrides  # noqa: E402
from learn.dataset import build_cache  # noqa: E402
from learn.geometry import clip_lattices  # noqa: E402
from render.frames import write_frames  # noqa: E402
from sim.clip import SimClip  # noqa: E402
from sim.lattice import LATTICE  # noqa: E402

SETTING, VARIANT = "wind-adaptive", "paper"


def lattice_index_before(uv: np.ndarray, n: int = LATTICE) -> np.ndarray:
    """``sim.lattice.lattice_vertices`` as it was: the same indices through a (points, vertices, 2) temporary."""
    grid = (np.arange(n) + 0.5) / n
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    pts = lo + np.stack(np.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2) * (hi - lo)
    return np.argmin(((uv[None, :, :] - pts[:, None, :]) ** 2).sum(-1), axis=1)


def write_setting(run: Run, clips: int, frames: int, size: int, vertices: int) -> None:
    """Stand-in render and sim folders of ``clips`` clips, each finished (DONE)."""
    rng = np.random.default_rng(0)
    for index in range(clips):
        cid = clip_id(index)
        folder = run.render_dir(VARIANT, SETTING) / cid
        folder.mkdir(parents=True, exist_ok=True)
        write_frames(folder, rng.integers(0, 256, size=(frames, size, size, 3), dtype=np.uint8))
        atomic_write_json(folder / "meta.json", {"clip_id": cid, "class_index": index % 54, "num_frames": frames,
                                                 "status": "ok"})
        mark_done(folder)
        counts = rng.integers(int(vertices * 0.8), int(vertices * 1.2), frames)
        mesh = [(rng.normal(size=(n, 3)).astype(np.float32), np.array([[0, 1, n - 1]], np.int32),
                 rng.uniform([0.0, 0.0], [1.0, 1.0], size=(n, 2)).astype(np.float32)) for n in counts]
        sim_folder = run.sim_dir(SETTING) / cid
        SimClip.from_frames({"class_index": index % 54}, mesh).save(sim_folder)
        mark_done(sim_folder)


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return round(time.perf_counter() - t0, 3)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    frame_set_arguments(ap)
    ap.add_argument("--vertices", type=int, default=1700, help="mean vertices of a stand-in adaptive frame")
    ap.add_argument("--processes", type=int, default=None, help="the pool's processes (default: every CPU)")
    args = ap.parse_args(argv)
    processes = args.processes or host_processes()
    if processes < 2:
        ap.error("a pool needs at least 2 processes")
    need = 2 * args.clips * args.frames * args.size ** 2 * 3
    if shutil.disk_usage(args.workdir).free < 1.2 * need:
        ap.error(f"{args.workdir} needs about {need / 2**30:.1f} GiB free (the frames and their cache)")
    root = Path(tempfile.mkdtemp(prefix="train_inputs-", dir=args.workdir))
    try:
        config = apply_overrides(preset("paper"), ["sim.motions=wind", "sim.remeshing=adaptive",
                                                   f"sim.sequences_per_class={max(1, args.clips // 54)}"])
        run = Run.create_or_resume(root / "run", config)
        t_write = timed(lambda: write_setting(run, args.clips, args.frames, args.size, args.vertices))
        ids = run.done_clips(run.render_dir(VARIANT, SETTING))
        lattice_path = run.lattice_cache_path(SETTING, LATTICE)

        def lattices(p: int) -> None:
            lattice_path.unlink(missing_ok=True)
            clip_lattices(run, SETTING, ids, progress=False, processes=p)

        sample = ids[:256]

        def lattices_before() -> None:
            for cid in sample:
                clip = SimClip.load(run.sim_dir(SETTING) / cid)
                np.stack([pos[lattice_index_before(uv)] for pos, _, uv in clip.frames()])

        lattice = {"one_process_s": timed(lambda: lattices(0)), "pool_s": timed(lambda: lattices(processes)),
                   "before_one_process_s_per_clip": round(timed(lattices_before) / len(sample), 5)}
        lattice["one_process_s_per_clip"] = round(lattice["one_process_s"] / len(ids), 5)
        lattice["pool_ratio"] = round(lattice["one_process_s"] / lattice["pool_s"], 2)
        lattice["index_ratio_per_clip"] = round(lattice["before_one_process_s_per_clip"]
                                                / lattice["one_process_s_per_clip"], 2)

        def cache(p: int) -> None:
            path = run.frame_cache_path(VARIANT, SETTING, args.size)
            path.with_suffix(".json").unlink(missing_ok=True)
            build_cache(run, VARIANT, SETTING, args.size, progress=False, processes=p)

        cache(0)                                      # the frames into the page cache once, untimed
        one, pool = [], []
        for _ in range(3):
            one.append(timed(lambda: cache(0)))
            pool.append(timed(lambda: cache(processes)))
        cache_times = {"one_process_s": one, "pool_s": pool,
                       "pool_ratio_of_medians": round(float(np.median(one)) / float(np.median(pool)), 2),
                       "gib": round(args.clips * args.frames * args.size ** 2 * 3 / 2**30, 2)}
    finally:
        shutil.rmtree(root, ignore_errors=True)
    result = {"host": platform.node(), "cpus": os.cpu_count(), "processes": processes, "clips": args.clips,
              "frames": args.frames, "size": args.size, "vertices": args.vertices,
              "stand_in_written_s": t_write, "lattice": lattice, "cache": cache_times}
    print(result)
    out = args.out or RESULTS / f"train_inputs-{os.cpu_count()}cpu-n{args.clips}.json"
    write_result("train_inputs.py", argv, result, out)


if __name__ == "__main__":
    main()
