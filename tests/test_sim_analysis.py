"""The material analyses (sim.analysis): Table 2 and the Fig. 3 sensitivity curves, on small meshes."""

import csv
import math

import numpy as np
import pytest

from sim import classes
from sim.analysis import PAPER_TABLE2, Setup, invert_curve, match_counts, sensitivity, table2
from sim.materials import list_materials
from tests.conftest import coarse_analysis_setup

CHEAP = coarse_analysis_setup()


@pytest.fixture(scope="module")
def table2_rows(tmp_path_factory):
    out = tmp_path_factory.mktemp("table2")
    path = table2(out, setup=CHEAP)
    return path, {r["material"]: r for r in csv.DictReader(path.open())}


def test_table2_writes_csv_and_png_for_every_fabric(table2_rows):
    path, rows = table2_rows
    assert sorted(rows) == list_materials() and len(rows) == 10
    png = path.with_suffix(".png")
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for name, r in rows.items():
        p, k = float(r["p_est"]), float(r["k_est"])
        assert p > 0 and k > 0
        assert int(r["class_index"]) == classes.nearest_class(p, k)
        assert (float(r["p_class"]), float(r["k_class"])) == classes.class_values(int(r["class_index"]))
        assert float(r["paper_p_est"]) == PAPER_TABLE2[name][0]
        assert r["p_match"] == str(int(float(r["p_class"]) == PAPER_TABLE2[name][1]))
        assert r["k_table_match"] in ("0", "1") and float(r["p_table"]) > 0
    assert all(v.count("/") == 1 and v.endswith("/10") for v in match_counts(list(rows.values())).values())


def test_basis_estimates_itself(table2_rows):
    # The basis's own table is the sweep point 1/r = 1, so inverting its curves gives 1.
    basis = table2_rows[1]["camel-ponte-roma"]
    for col in ("p_est", "k_est", "p_est_u", "p_est_v", "k_est_u", "k_est_v"):
        assert abs(math.log(float(basis[col]))) < 0.05, (col, basis[col])
    assert float(basis["p_table"]) == 1.0


def test_stiffer_stretching_table_gives_larger_p(table2_rows):
    rows = table2_rows[1]
    soft = float(rows["navy-sparkle-sweat"]["p_est"])
    for stiff in ("royal-target", "white-dots-on-blk"):
        assert float(rows[stiff]["p_est"]) > 5 * soft
        assert float(rows[stiff]["D_u_m"]) < float(rows["navy-sparkle-sweat"]["D_u_m"])


def test_invert_curve_recovers_a_power_law_and_flags_jumps():
    inv = np.geomspace(1 / 64, 4, 17)
    curve = 0.01 * inv ** 0.8
    for r in (0.3, 1.0, 7.0, 100.0):          # 100 is outside the sweep: extrapolated
        est, jump = invert_curve(inv, curve, 0.01 * (1 / r) ** 0.8)
        assert est == pytest.approx(r, rel=1e-6) and not jump
    snapped = np.where(inv > 0.2, 5 * curve, curve)
    _, jump = invert_curve(inv, snapped, float(np.sqrt(snapped[7] * snapped[8])))
    assert jump and snapped[8] / snapped[7] > 2


def test_sensitivity_writes_curves_and_plot(tmp_path):
    path = sensitivity(tmp_path, setup=CHEAP)
    rows = list(csv.DictReader(path.open()))
    assert len(rows) == len(CHEAP.sweep) and (tmp_path / "sensitivity.png").is_file()
    d = [float(r["D_hanging_v_m"]) for r in rows]
    assert d[-1] > 10 * d[0], "a softer cloth (larger 1/p) sags further"
