"""The host memory samples that scripts/gpu/paper_study.sh takes while a stage runs, summed up as one JSON.

    python3 scripts/host_samples.py one=host_samples_mr1_render.txt six=host_samples_mr6_render.txt --out h.json

The result: ``command`` (as run) and ``samples``, by label. A samples file has a line every half second
(scripts/gpu/host_sample.sh): the machine's memory in use (MemTotal - MemAvailable), its Shmem, the Python
processes' anonymous resident memory summed, how many Python processes there are, and the MPS
server's anonymous resident memory, all in MiB (older files have the first two columns alone). For each
``LABEL=FILE``: the number of samples, the memory in use at the start, its peak over the start and its range over
the last quarter of the samples (where a stage settles), the same for the Python processes' memory (peak and last
quarter, absolute: the stage's processes start after the first sample), and each column's maximum over each
sixteenth of the samples, so that a rise from dataset to dataset shows; ``samples_cut_short`` counts the lines
that were not a whole sample (a sample whose process columns did not come is left out, the line it ran into
kept). A file without a sample is named and nothing is written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from clothgap.files import print_json, script_command  # noqa: E402

COLUMNS = ("used_mib", "shmem_mib", "python_anon_mib", "python_processes", "mps_anon_mib")
PARTS = 16


def read_samples(path: Path) -> tuple[list[list[int]], int]:
    """The file's whole samples, and how many were cut short. A sample whose process columns did not come (the
    sampler's second half failed) runs into the next line's sample: that line's last five numbers are kept."""
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as e:
        raise SystemExit(f"host_samples: cannot read {path}: {e}") from e
    numbers = [[int(x) for x in line.split()] for line in lines
               if line.split() and all(x.isdigit() for x in line.split())]
    width = len(COLUMNS) if any(len(r) >= len(COLUMNS) for r in numbers) else 2     # older files: two columns
    kept = [r for r in numbers if len(r) >= width and (len(r) - width) % 2 == 0]
    if not kept:
        raise SystemExit(f"host_samples: {path} has no samples of 2 or {len(COLUMNS)} whole numbers a line")
    cut = sum((len(r) - width) // 2 for r in kept) + len(lines) - len(kept)
    return [r[len(r) - width:] for r in kept], cut


def summary(rows: list[list[int]]) -> dict:
    n = len(rows)
    columns = {name: [r[i] for r in rows] for i, name in enumerate(COLUMNS[:len(rows[0])])}
    used = columns["used_mib"]
    last = used[n - max(1, n // 4):]
    parts = [(k * n // PARTS, (k + 1) * n // PARTS) for k in range(PARTS)]
    out = {"samples": n, "used_mib_at_start": used[0], "peak_used_mib_over_start": max(used) - used[0],
           "last_quarter_used_mib_over_start": [min(last) - used[0], max(last) - used[0]]}
    if "python_anon_mib" in columns:
        anon = columns["python_anon_mib"]
        tail = anon[n - max(1, n // 4):]
        out.update(peak_python_anon_mib=max(anon), last_quarter_python_anon_mib=[min(tail), max(tail)],
                   peak_python_processes=max(columns["python_processes"]),
                   peak_mps_anon_mib=max(columns["mps_anon_mib"]))
    out["max_by_sixteenth"] = {name: [max(values[a:b]) for a, b in parts if b > a]
                               for name, values in columns.items()}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", metavar="LABEL=FILE")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    result = {}
    for spec in args.files:
        label, sep, path = spec.partition("=")
        if not sep or not label:
            raise SystemExit(f"host_samples: expected LABEL=FILE, got {spec!r}")
        rows, cut = read_samples(Path(path))
        result[label] = {**summary(rows), "samples_cut_short": cut}
    print_json({"command": script_command(__file__, argv), "samples": result}, args.out)


if __name__ == "__main__":
    main()
