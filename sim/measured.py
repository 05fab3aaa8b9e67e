"""The measured-fabric test set, sim side: the Wang et al. 2011 fabrics with their OWN full tables.

Training clips use the basis fabric scaled by a class's (p, k) (the paper's
sub-space). The measured set instead simulates each named fabric of
``assets/materials`` with its measured stretching and bending tables and its own
density, so the cloth is *not* on the sub-space: the network has to place a real
material on the grid, which is what the paper's Table 2 does by hand.

Clips: ``RUN/measured/sim/<setting>/<fabric>-<n>/`` for every setting of the run
(its motions and remeshing levels) and n = 0 .. sequences - 1, in the sim clip
contract (``clip.npz``, ``meta.json``, ``DONE``). Their random draws (pose,
gathering, wind speed and direction; arm speed and placement) come from the sim
stage's motion stream of the clip index ``measured_index(fabric, n)``, a number
far above any training clip's index, so the draws differ between sequences of a
fabric (different wind) and from every training clip, are the same under every
remeshing level, and are reproducible from the run seed.

Labels in ``meta.json`` (besides the usual sim keys): ``material: "measured"``,
``fabric``, ``class_index``/``p_class``/``k_class`` = the class the paper's
Table 2 gives the fabric (for a fabric not in Table 2, the nearest class to its
estimated ratios), ``p``/``k`` = the estimated ratios p~, k~ of its tables to the
basis (``sim.analysis.estimate_ratios``; nothing was scaled), ``basis: null``,
``density`` (kg/m^2) and ``measured`` (``measured_values``).

Measured stiffness, from the tables (what predictions are correlated with):

* ``stretching_N_m``: ``sim.materials.stretching_summary``, the mean of the
  low-strain (at-rest) row's direct entries k0 (warp), k2 (weft), k3 (shear), N/m.
  A class's prediction is p times the basis's value.
* ``bending_N_m``: ``sim.materials.bending_summary``, the mean of all 15 bending
  entries (3 directions x 5 curvatures), N*m, the same statistic as
  ``eval.classes.BASIS_MEAN_BENDING_N_M``, so a class's prediction is k times the
  basis's value.
* ``density_kg_m2``: the area density.
"""

from __future__ import annotations

from collections.abc import Sequence

from clothgap.errors import ConfigError
from clothgap.seeding import stream_id
from sim import classes
from sim.analysis import BASIS, PAPER_TABLE2, estimate_ratios
from sim.materials import bending_summary, list_materials, load_material, stretching_summary

MEASURED_INDEX_BASE = 1_000_000_000
MAX_SEQUENCES = 1000


def measured_index(fabric: str, n: int) -> int:
    """The seed index of sequence ``n`` of ``fabric``: stable per name, never a training clip's."""
    if not 0 <= n < MAX_SEQUENCES:
        raise ValueError(f"sequence number {n} outside 0..{MAX_SEQUENCES - 1}")
    return MEASURED_INDEX_BASE + (stream_id(fabric) % 1_000_000) * MAX_SEQUENCES + n


def clip_name(fabric: str, n: int) -> str:
    return f"{fabric}-{n}"


def table2_fabrics() -> list[str]:
    """The ten fabrics of the paper's Table 2, in the paper's order."""
    return list(PAPER_TABLE2)


def check_fabrics(fabrics: Sequence[str]) -> list[str]:
    known = set(list_materials())
    unknown = [f for f in fabrics if f not in known]
    if unknown:
        raise ConfigError(f"unknown measured fabric(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    if len(set(fabrics)) != len(fabrics):
        raise ConfigError(f"measured fabrics listed twice: {', '.join(fabrics)}")
    return list(fabrics)


def table2_class(fabric: str) -> int:
    """The paper's Table 2 class of a fabric; for one not in Table 2, the nearest class to p~, k~."""
    if fabric in PAPER_TABLE2:
        _, p, _, k = PAPER_TABLE2[fabric]
        return classes.class_index(classes.P_VALUES.index(float(p)), classes.K_VALUES.index(float(k)))
    return classes.nearest_class(*estimate_ratios(fabric))


def measured_values(fabric: str) -> dict[str, float]:
    """Stretching (N/m) and bending (N*m) stiffness and area density (kg/m^2) from the fabric's tables."""
    m = load_material(fabric)
    return {"stretching_N_m": stretching_summary(m.stretching), "bending_N_m": bending_summary(m.bending),
            "density_kg_m2": float(m.density)}


def basis_values() -> dict[str, float]:
    """``measured_values`` of the basis fabric: a class (p, k) predicts p and k times these."""
    return measured_values(BASIS)


def table_ratios(fabric: str) -> tuple[float, float]:
    """The fabric's stretching and bending over the basis's: the (p, k) its own tables stand for."""
    v, b = measured_values(fabric), basis_values()
    return v["stretching_N_m"] / b["stretching_N_m"], v["bending_N_m"] / b["bending_N_m"]


def over_weight_ratios(fabric: str) -> tuple[float, float]:
    """``table_ratios`` over the fabric's area density relative to the basis's: the (p, k) a motion that shows
    S / w and B / w alone stands for (gravity and inertia scale with the weight, and the classes are made at the
    basis's unless ``sim.density_range`` draws theirs)."""
    w = measured_values(fabric)["density_kg_m2"] / basis_values()["density_kg_m2"]
    s, b = table_ratios(fabric)
    return s / w, b / w


def tables_class(fabric: str) -> int:
    """The class nearest (in log ratio) to ``table_ratios``: where a reader of the fabric's tables would put it
    (Table 2's class comes from hanging and folding tests instead)."""
    return classes.nearest_class(*table_ratios(fabric))


def over_weight_class(fabric: str) -> int:
    """The class nearest to ``over_weight_ratios``: where a reader of S / w and B / w would put the fabric."""
    return classes.nearest_class(*over_weight_ratios(fabric))


def reference_classes() -> dict[str, dict[str, int]]:
    """{reference: {fabric: class index}} for the Table 2 fabrics, in the paper's order: Table 2's own class, the
    tables' (``tables_class``) and the tables' over the weight (``over_weight_class``): what goal 3 counts against,
    and where two readers that look at no clip would put each fabric."""
    fabrics = table2_fabrics()
    return {"table2": {f: table2_class(f) for f in fabrics}, "tables": {f: tables_class(f) for f in fabrics},
            "over_weight": {f: over_weight_class(f) for f in fabrics}}


def fabric_labels(fabric: str) -> dict:
    """The label part of a measured clip's meta (see the module docstring)."""
    m = load_material(fabric)
    class_index = table2_class(fabric)
    p_class, k_class = classes.class_values(class_index)
    p_est, k_est = estimate_ratios(fabric)
    return {"material": "measured", "fabric": fabric, "class_index": class_index, "p_class": p_class,
            "k_class": k_class, "class_source": "paper Table 2" if fabric in PAPER_TABLE2 else "nearest class",
            "p": p_est, "k": k_est, "basis": None, "density": m.density, "measured": measured_values(fabric)}


def wanted_clips(fabrics: Sequence[str], sequences: int) -> list[tuple[str, int]]:
    return [(f, n) for f in fabrics for n in range(sequences)]
