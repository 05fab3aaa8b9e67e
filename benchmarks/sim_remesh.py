"""A cloth's host remeshing step (``sim.remesh.remesh_cloth``) against the same step at a baseline revision.

    python benchmarks/sim_remesh.py [--baseline REV] [--clips 4] [--frames 8] [--repeats 3] [--out FILE]

An adaptive setting remeshes every cloth after every frame on the host (in the `study` preset's sim stage about
157 s of each four-GPU worker's 379). This simulates ``--clips`` ``paper``-preset wind-adaptive clips on the CPU for
``--frames`` frames and keeps every cloth-frame's remeshing input; then times ``remesh_cloth`` over all of them with
this tree's ``sim`` package and with ``sim`` as it was at ``--baseline`` (``git archive``), each in a fresh process,
alternating, ``--repeats`` times each, and checks that both give the same bytes (the clips must not change).
Writes benchmarks/results/sim_remesh-cpu.json with the command.
"""

from __future__ import annotations

import argparse
import os
import pickle
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, ROOT, either_first, extract_revision, git, tree_label, write_result  # noqa: E402

# Run in a fresh process whose ``sim`` package is either tree's: times remesh_cloth over the inputs, hashes results.
TIMER = r"""
import hashlib, pickle, sys, time
import numpy as np
import sim.remesh as R

def feed(x, h):
    if x is None:
        h.update(b"None")
    elif isinstance(x, np.ndarray):
        h.update(x.dtype.str.encode() + str(x.shape).encode() + np.ascontiguousarray(x).tobytes())
    elif hasattr(x, "__dataclass_fields__"):
        for k in x.__dataclass_fields__:
            feed(getattr(x, k), h)
    elif isinstance(x, dict):
        for k in sorted(x):
            h.update(k.encode()); feed(x[k], h)
    elif isinstance(x, (list, tuple)):
        for y in x:
            feed(y, h)
    else:
        h.update(repr(x).encode())

inputs = pickle.load(open(sys.argv[1], "rb"))
h = hashlib.sha256()
for args in inputs:
    feed(R.remesh_cloth(*args), h)
t0 = time.perf_counter()
for args in inputs:
    R.remesh_cloth(*args)
print(f"{(time.perf_counter() - t0) / len(inputs) * 1e3:.4f} {h.hexdigest()}")
"""


def capture(clips: int, frames: int, workdir: Path) -> Path:
    """Every remeshing input of a small wind-adaptive simulation on the CPU, pickled."""
    import sim.remesh as remesh
    from clothgap.config import preset
    from clothgap.runs import Run
    from clothgap.settings import apply_overrides
    from sim.stage import run_sim

    captured = []
    real = remesh.remesh_cloth

    def spy(q, p, v, angle, c=0):
        captured.append((q, p.copy(), v.copy(), angle, c))
        return real(q, p, v, angle, c)

    cfg = apply_overrides(preset("paper"), ["sim.device=cpu", "sim.remeshing=adaptive", "sim.motions=wind",
                                            "sim.classes=0,53", f"sim.sequences_per_class={max(1, clips // 2)}",
                                            f"sim.batch_size={clips}", f"sim.frames={frames}",
                                            f"train.clip_len={frames}"])
    remesh.remesh_cloth = spy
    try:
        run_sim(Run.create_or_resume(workdir / "run", cfg), progress=False)
    finally:
        remesh.remesh_cloth = real
    path = workdir / "inputs.pkl"
    path.write_bytes(pickle.dumps(captured))
    return path


def time_tree(sim_root: Path, inputs: Path) -> tuple[float, str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(dict.fromkeys([str(sim_root), str(ROOT)]))}
    out = subprocess.run([sys.executable, "-c", TIMER, str(inputs)], capture_output=True, text=True, env=env,
                         cwd=sim_root, check=True).stdout.split()
    return float(out[-2]), out[-1]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default="HEAD", help="git revision whose sim/ is the baseline (default HEAD: "
                    "this tree's uncommitted sim/ against its last commit)")
    ap.add_argument("--clips", type=int, default=4)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS / "sim_remesh-cpu.json")
    args = ap.parse_args(argv)

    baseline_rev = git("rev-parse", "--short", args.baseline)
    tree = tree_label("sim")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        inputs = capture(args.clips, args.frames, tmp)
        base = extract_revision(args.baseline, tmp / "baseline", "sim")
        ms: dict[str, list[float]] = {"baseline": [], "this_tree": []}
        digests: dict[str, set[str]] = {"baseline": set(), "this_tree": set()}
        for name, root in either_first((("baseline", base), ("this_tree", ROOT)), args.repeats):
            t, digest = time_tree(root, inputs)
            ms[name].append(round(t, 3))
            digests[name].add(digest)
            print(f"{name}: {t:.3f} ms a cloth-frame", flush=True)
        count = len(pickle.loads(inputs.read_bytes()))
    median = {k: statistics.median(v) for k, v in ms.items()}
    result = {
        "host": platform.node(), "cpus": os.cpu_count(), "baseline": baseline_rev, "this_tree": tree,
        "cloth_frames": count, "clips": args.clips, "frames": args.frames,
        "ms_per_cloth_frame": ms, "median_ms": median,
        "speedup": round(median["baseline"] / median["this_tree"], 2),
        "same_bytes": digests["baseline"] == digests["this_tree"] and len(digests["baseline"]) == 1,
    }
    write_result("sim_remesh.py", argv, result, args.out)
    if not result["same_bytes"]:
        raise SystemExit("the remeshing step's results differ from the baseline's")


if __name__ == "__main__":
    main()
