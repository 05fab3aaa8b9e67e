"""GPU: the render threads a session's later renders use, from ``benchmarks/render_throughput.py --write-threads``.

    python3 scripts/gpu/render_threads.py BENCHMARK.json      ->  "--set render.threads=N" or nothing

Prints the setting for the thread count with the highest frames/s when it is at least ``--gain`` times one
thread's and its frames match one thread's (a code difference of at most 1, as a BVH tie may move a sample),
else nothing (one thread, the default); says why on stderr.
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
    args = ap.parse_args()
    try:
        rounds = json.loads(args.benchmark.read_text())["rounds"]
    except (OSError, ValueError, KeyError) as e:
        print(f"render threads: no benchmark to choose from ({e}): one thread", file=sys.stderr)
        return
    best = None
    for name, row in rounds[0].get("with_output", {}).items():
        found = re.fullmatch(r"npy_threads_(\d+)", name)
        if not found:
            continue
        ok = row.get("max_code_difference_vs_one_thread", 99) <= 1 and row.get("over_one_thread", 0) >= args.gain
        print(f"render threads: {found.group(1)}: {row.get('over_one_thread')}x one thread, frames differ by at "
              f"most {row.get('max_code_difference_vs_one_thread')}{'' if ok else ' (not taken)'}", file=sys.stderr)
        if ok and (best is None or row["over_one_thread"] > best[1]):
            best = (int(found.group(1)), row["over_one_thread"])
    if best:
        print(f"--set render.threads={best[0]}")


if __name__ == "__main__":
    main()
