"""Writing a file so that it is never seen half-written: the project's one atomic writer.

Every file a stage, a run folder or a cache writes goes through ``atomic_path``: the writer fills a temporary
file beside the target, which then replaces the target in one step (``os.replace``). A reader sees the old file
or the whole new one; an error or interrupt deletes the temporary (a full disk leaves nothing behind); a
``kill -9`` leaves ``<name>.tmp<pid>``, which the next write of the same file removes.
"""

from __future__ import annotations

import contextlib
import fnmatch
import glob
import json
import os
import shlex
import signal
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any


@contextlib.contextmanager
def atomic_path(path: Path | str, keep_suffix: bool = False) -> Iterator[Path]:
    """A temporary path to write ``path``'s new content to; it replaces ``path`` when the block ends without error.

    The temporary is ``<name>.tmp<pid>``, or ``<stem>.tmp<pid><suffix>`` with ``keep_suffix`` (for writers that
    choose the format by the extension, or add one: ``np.savez``, ``savefig``). Its folder is created if needed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    prefix, suffix = (f"{path.stem}.tmp", path.suffix) if keep_suffix else (f"{path.name}.tmp", "")
    remove_stale_temps(path.parent, prefix, suffix)
    tmp = path.with_name(f"{prefix}{os.getpid()}{suffix}")
    try:
        yield tmp
        kill_point(path)
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_json(path: Path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, default=_json_default) + "\n")


def script_command(script: str, argv: list[str] | None) -> str:
    """The command a script's result records: ``python3 FOLDER/NAME`` (``script`` is its ``__file__``) and its
    arguments (``argv``, else the process's), shell-quoted."""
    path = Path(script)
    return shlex.join(["python3", f"{path.parent.name}/{path.name}", *(argv if argv is not None else sys.argv[1:])])


def print_json(data: Any, out: Path | None = None) -> None:
    """A script's result: printed as JSON, and written to ``out`` (atomically) when given."""
    print(json.dumps(data, indent=2, default=_json_default, allow_nan=False))
    if out is not None:
        atomic_write_json(out, data)


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def remove_stale_temps(folder: Path, prefix: str, suffix: str = "") -> None:
    """Delete the files ``<prefix><pid><suffix>`` in ``folder`` whose process is gone: temporaries a killed
    writer left (``kill -9`` runs no cleanup), e.g. a multi-GB frame cache being built."""
    for old in Path(folder).glob(glob.escape(prefix) + "*" + glob.escape(suffix)):
        pid = old.name[len(prefix):len(old.name) - len(suffix)]
        if pid.isdigit() and int(pid) != os.getpid() and not process_alive(int(pid)):
            old.unlink(missing_ok=True)


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` runs: it exists (perhaps owned by someone else) and is not a zombie waiting for
    its parent to reap it."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True     # exists, owned by someone else
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True     # no /proc here: existing is all we know


# Test-only fault injection (tests/test_kill_resume.py); never set in normal use.
KILL_AT_ENV = "CLOTHGAP_KILL_AT"
_kill_count = 0


def kill_point(path: Path) -> None:
    """Test only: with ``$CLOTHGAP_KILL_AT=GLOB:N`` the process SIGKILLs itself at the N-th atomic write of a
    file whose path matches GLOB (fnmatch, e.g. ``*/render/*/DONE:3``), its temporary file written and not yet
    in place: the worst moment for a ``kill -9``, reached at the same point of the work on every run."""
    spec = os.environ.get(KILL_AT_ENV)
    if not spec:
        return
    pattern, _, count = spec.rpartition(":")
    if fnmatch.fnmatch(str(path), pattern):
        global _kill_count
        _kill_count += 1
        if _kill_count >= int(count):
            os.kill(os.getpid(), signal.SIGKILL)
