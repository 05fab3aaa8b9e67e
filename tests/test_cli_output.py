"""What a user sees: short help that is not cut mid-sentence, Warp's banner off stdout, progress of long analyses."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import click
import numpy as np

from clothgap.cli import cli

ROOT = Path(__file__).resolve().parent.parent


def commands(group: click.Group, path: tuple[str, ...] = ()):
    for name, cmd in group.commands.items():
        yield path + (name,), cmd
        if isinstance(cmd, click.Group):
            yield from commands(cmd, path + (name,))


def test_short_help_is_a_whole_sentence_or_elided():
    # click cuts the short help at the first '.' followed by a capital or digit: "(the paper's Fig." was the result
    for path, cmd in commands(cli):
        short = cmd.get_short_help_str(limit=200)
        assert short.count("(") == short.count(")") and short.count("`") % 2 == 0, (path, short)


def test_warp_banner_and_module_loads_go_to_stderr():
    code = ("import numpy as np, warp as wp, sim.solver\n"
            "wp.init()\n"
            "wp.array(np.zeros(3, np.float32), device='cpu')\n"
            "print('only this')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr
    assert r.stdout == "only this\n"
    assert "Warp" in r.stderr and "initialized" in r.stderr


def test_material_analyses_show_solver_progress(capsys):
    from sim.analysis import Setup, deformations
    from sim.materials import load_material

    basis = load_material("camel-ponte-roma")
    setup = Setup(hang_vertices=4, strip_vertices=5, strip_rows=2, seconds=0.05, average_seconds=0.02, samples=2)
    D, C = deformations([basis.stretching], [basis.bending], setup=setup)
    assert D.shape == C.shape == (2, 1) and np.isfinite(D).all() and np.isfinite(C).all()
    err = capsys.readouterr().err
    assert "2 hanging cloths" in err and "2 folding strips" in err and "step" in err
