"""GPU: the render threads a session's later renders use, from ``benchmarks/render_throughput.py --write-threads``.

    python3 scripts/gpu/render_threads.py BENCHMARK.json      ->  "--set render.threads=N" or nothing

Prints the setting for the thread count with the highest frames/s when it is at least ``--gain`` times one
thread's and its frames match one thread's (at most ``--moved`` of the pixels differ by more than one code: a
tie in a BVH build may move a rare sample), else nothing (one thread, the default); says why on stderr.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("benchmark", type=Path)
    ap.add_argument("--gain", type=float, default=1.15, help="the least speed-up over one thread worth taking")
    ap.add_argument("--moved", type=float, default=0.01, help="the largest share of pixels that may differ from "
                    "one thread's by more than one code (a tie in a BVH build moves a rare sample)")
    args = ap.parse_args()
    try:
        rows = json.loads(args.benchmark.read_text())["rounds"][0].get("with_output", {})
    except (OSError, ValueError, KeyError, IndexError, AttributeError) as e:
        print(f"render threads: no benchmark to choose from ({e!r}): one thread", file=sys.stderr)
        return
    best = None
    for name, row in rows.items():
        found = re.fullmatch(r"npy_threads_(\d+)", name)
        if not found:
            continue
        gain, moved = row.get("over_one_thread") or 0.0, row.get("share_moved_vs_one_thread")
        ok = moved is not None and moved <= args.moved and gain >= args.gain
        print(f"render threads: {found.group(1)}: {gain}x one thread, {moved} of the pixels moved by more than one "
              f"code{'' if ok else ' (not taken)'}", file=sys.stderr)
        if ok and (best is None or row["over_one_thread"] > best[1]):
            best = (int(found.group(1)), row["over_one_thread"])
    if best:
        print(f"--set render.threads={best[0]}")


if __name__ == "__main__":
    main()
