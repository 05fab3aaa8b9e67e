"""The paper's material analyses (Section 4.2.2): Fig. 3 sensitivity curves and Table 2.

``sensitivity(out_dir)`` simulates, for a sweep of coefficients scaling the basis:
  D(M) = max_u |u - u0| (eq. 2) of a square cloth hanging from its top edge under
  gravity, against 1/p (bending at the basis value), and
  C(M) = max over interior edges of |e0| arccos(n1.n2) / (A1 + A2) (eq. 3) of a
  strip clamped at one end and folding under gravity, against 1/k (stretching at
  p = 20 so the strip bends rather than stretches),
and marks the ten Wang fabrics at their estimated 1/p~, 1/k~.

``table2(out_dir)`` estimates each fabric's (p~, k~) as the ratio of the mean
magnitude of its stretching (resp. bending) table to the basis material's, and
maps it to the nearest class, beside the paper's Table 2 values.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from sim import classes
from sim.materials import list_materials, load_material
from sim.mesh import ClothMesh, hinges_of, square_cloth
from sim.motions import hanging_positions
from sim.solver import BatchSolver, ClothSpec, SolverParams

BASIS = "camel-ponte-roma"
# The paper's Table 2: (p~, p, k~, k)
PAPER_TABLE2 = {
    "ivory-rib-knit": (1.3817, 1, 2.3, 2), "pink-ribbon-brown": (2.9343, 3, 12, 10),
    "camel-ponte-roma": (1, 1, 0.52, 0.5), "white-dots-on-blk": (15.8108, 20, 3.5, 4),
    "navy-sparkle-sweat": (0.5613, 0.5, 1.7, 2), "gray-interlock": (1.0164, 1, 1.6, 2),
    "11oz-black-denim": (3.6079, 3, 3, 3), "white-swim-solid": (1.9126, 2, 2.9, 3),
    "tango-red-jet-set": (1.9784, 2, 1.9, 2), "royal-target": (22.2857, 20, 19, 20),
}


def estimate_ratios(name: str) -> tuple[float, float]:
    """(p~, k~): mean |entry| of the fabric's stretching and bending tables over the basis material's."""
    m, b = load_material(name), load_material(BASIS)
    return (float(np.abs(m.stretching).mean() / np.abs(b.stretching).mean()),
            float(np.abs(m.bending).mean() / np.abs(b.bending).mean()))


def table2(out_dir: Path | str) -> Path:
    """Write ``table2.csv``: each fabric's estimated (p~, k~), its nearest class, and the paper's values."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "table2.csv"
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["material", "p_est", "k_est", "p_class", "k_class", "class_index",
                    "paper_p_est", "paper_p", "paper_k_est", "paper_k"])
        for name in list_materials():
            p, k = estimate_ratios(name)
            c = classes.nearest_class(p, k)
            pc, kc = classes.class_values(c)
            w.writerow([name, f"{p:.4f}", f"{k:.4f}", pc, kc, c, *PAPER_TABLE2.get(name, ("",) * 4)])
    return path


def _strip(k: float, length: float = 0.24, width: float = 0.04, nu: int = 13, nv: int = 3) -> ClothSpec:
    """A strip clamped horizontally at u = 0 (first two columns pinned), free to fold under gravity."""
    uu, vv = np.meshgrid(np.linspace(0, length, nu), np.linspace(0, width, nv))
    uv = np.stack([uu.ravel(), vv.ravel()], 1)
    faces = []
    for j in range(nv - 1):
        for i in range(nu - 1):
            a, b, c, d = j * nu + i, j * nu + i + 1, (j + 1) * nu + i, (j + 1) * nu + i + 1
            faces += [(a, b, d), (a, d, c)] if (i + j) % 2 == 0 else [(a, b, c), (b, d, c)]
    faces = np.array(faces, np.int32)
    m = load_material(BASIS).scaled(20.0, k)
    pos = np.stack([uv[:, 0], uv[:, 1], np.zeros(len(uv))], 1)
    return ClothSpec(ClothMesh(uv, faces, hinges_of(faces)), pos, m.stretching, m.bending, m.density,
                     pinned=np.flatnonzero(uv[:, 0] <= length / (nu - 1) + 1e-9))


def max_curvature(mesh: ClothMesh, x: np.ndarray) -> float:
    """C(M) of the paper's eq. (3), with current face areas."""
    h = mesh.hinges
    na = np.cross(x[h[:, 1]] - x[h[:, 0]], x[h[:, 2]] - x[h[:, 0]])
    nb = np.cross(x[h[:, 3]] - x[h[:, 0]], x[h[:, 1]] - x[h[:, 0]])
    la, lb = np.linalg.norm(na, axis=1), np.linalg.norm(nb, axis=1)
    ang = np.arccos(np.clip(np.einsum("ij,ij->i", na, nb) / (la * lb), -1, 1))
    e = np.linalg.norm(x[h[:, 1]] - x[h[:, 0]], axis=1)
    return float((e * ang / (0.5 * (la + lb))).max())


def sensitivity(out_dir: Path | str, device: str = "cpu", seconds: float = 1.5) -> Path:
    """Write ``sensitivity.csv`` and ``sensitivity.png`` (the paper's Fig. 3); returns the CSV path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    inv = np.geomspace(1 / 25, 1 / 0.4, 16)          # 1/p and 1/k sweep
    basis = load_material(BASIS)
    mesh = square_cloth(0.5, 12)
    pos, top = hanging_positions(mesh, 0.5)
    hang = [ClothSpec(mesh, pos, basis.stretching / r, basis.bending, basis.density, pinned=top) for r in inv]
    strips = [_strip(1.0 / r) for r in inv]
    params = SolverParams()
    steps = int(round(seconds / params.dt))
    hs = BatchSolver(hang, params, device)
    hs.step(steps)
    ss = BatchSolver(strips, params, device)
    ss.step(steps)
    D = [float(np.linalg.norm(x - s.positions, axis=1).max()) for x, s in zip(hs.positions(), hang)]
    C = [max_curvature(s.mesh, x) for x, s in zip(ss.positions(), strips)]
    path = out / "sensitivity.csv"
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["inverse_ratio", "D_hanging_m", "C_folded_per_m"])
        w.writerows([[f"{r:.5f}", f"{d:.6f}", f"{c:.4f}"] for r, d, c in zip(inv, D, C)])
    fig, axes = plt.subplots(2, 1, figsize=(7, 7))
    for ax, y, label, which in ((axes[0], D, "D(M), m (hanging, gravity)", 0),
                                (axes[1], C, "C(M), 1/m (folded strip)", 1)):
        ax.semilogx(inv, y, "-o", color="tab:cyan", ms=3)
        for i, name in enumerate(list_materials()):
            ratio = estimate_ratios(name)[which]
            ax.axvline(1.0 / ratio, color=plt.cm.tab10(i), lw=1, label=name)
        ax.set_ylabel(label)
    axes[0].set_xlabel("1 / p (stretching ratio to camel-ponte-roma)")
    axes[1].set_xlabel("1 / k (bending ratio to camel-ponte-roma)")
    axes[0].legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "sensitivity.png", dpi=100)
    plt.close(fig)
    return path
