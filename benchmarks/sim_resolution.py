"""The resolution and time-step study of docs/simulation.md: what each mesh level resolves, and how much a
folding clip depends on the time step compared with how much it depends on the bending class.

    python benchmarks/sim_resolution.py --device cpu                          # both parts (CPU: ~30 min)
    python benchmarks/sim_resolution.py --device cpu --parts cantilever
    python benchmarks/sim_resolution.py --device cpu --parts dt,floor --settings uniform1,uniform2

``cantilever``: the ASTM D1388 test of ``clothgap sim cantilever`` (``sim.cantilever.measure``) on the basis
fabric scaled to the bending classes k = 1, 5, 20 (p = 1; classes 10, 13, 17), at one fixed overhang per
class near its 41.5 deg overhang (1.67, 3.33, 6.67 cm: whole edges of the level-2, -1, -1 meshes), on the
uniform levels 1..3 of the stage's mesh and the finer levels 4..6 (edge 4.2, 2.1, 1.0 mm), with the
class's table as simulated (ke softens or stiffens with curvature) and with each bending row held at its
zero-curvature value (``constant``: the discretisation alone). The bending length c is the heavy-elastica
inversion of the tip's chord angle; the error is c's against level 6's. A level whose edge does not divide
the overhang cannot hold the test (``null``).

``dt``: two folding scenes on each setting's mesh (the stage's 16-vertex 0.5 m cloth; ``adaptive`` remeshes
every frame as the stage does): ``drop``, the cloth lying flat and held at one corner, 1 s after release;
``wind``, clip 0's draw of the wind motion (the ``corners`` pose: two top corners pinned, gathered, wind
on after the 0.4 s settle), 1 s after the wind starts. Material: the basis at p = 1 and k = 1, 2, 4, 5
(two pairs of neighbouring bending classes; 4 and 5 are the closest in the class grid). Each scene is run at
the stage's dt = 1/200 s (8 substeps at 25 fps) and at half of it with self-collision off, and at 1/200,
1/400 and 1/800 s with it on. Shapes are compared on the 16 x 16 base-grid vertices, which every mesh level
and every adaptive mesh holds: ``dt_shift`` = mean (and max) distance between the shapes of one material at
two successive time steps, averaged over the four materials (and per material); ``class_step`` = the same
between neighbouring classes (1 vs 2, 4 vs 5) at the finest time step of the series.

``floor``: the same scenes at the stage's dt, once as built and once with every vertex's start moved by
about 1 um and 100 um (normal, seeded): how far a perturbation grows in 1 s, the floor under ``dt_shift``.
A dt shift at that floor is the folding's sensitivity (chaos), not an integration error that a smaller dt
would remove.

Writes ``benchmarks/results/sim_resolution-<device>.json`` (``--out``), rewritten after each piece; a run of
one part replaces that part only. Each part's command is in ``commands``; one line per measurement printed.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np

from clothgap import seeding
from sim.cantilever import level_edge, material_of, measure
from sim.config import SimConfig
from sim.materials import Material, load_material
from sim.motions import ClipScene, wind_scene
from sim.solver import ClothSpec, resolve_device
from sim.stage import parse_setting, setting_simulator

CANTILEVER = {10: 0.0167, 13: 0.0333, 17: 0.0667}      # class -> overhang (m)
CANTILEVER_LEVELS = (1, 2, 3, 4, 5, 6)
DT_K = (1.0, 2.0, 4.0, 5.0)
NEIGHBOURS = ((1.0, 2.0), (4.0, 5.0))
WIND_CLIP = 0                                           # its motion draw: the corners pose
NUDGES_M = (1.0e-6, 1.0e-4)                             # the floor part's initial perturbations


def constant_table(material: Material) -> Material:
    """The material with each bending row held at its zero-curvature value (no softening or stiffening)."""
    return dataclasses.replace(material, name=f"{material.name} (constant table)",
                               bending=np.repeat(material.bending[:, :1], material.bending.shape[1], axis=1))


def cantilever_part(device: str, record) -> dict:
    out = {}
    for (cls, overhang), table in itertools.product(CANTILEVER.items(), ("as simulated", "constant")):
        material, name = material_of(str(cls))
        if table == "constant":
            material = constant_table(material)
        rows = {}
        for level in CANTILEVER_LEVELS:
            edge = level_edge(level)
            edges = int(round(overhang / edge))
            if edges < 1 or abs(edges * edge - overhang) > 0.05 * overhang:
                rows[level] = None
                continue
            start = time.perf_counter()
            (r,) = measure(material, edge, [edges], "u", device)
            c = r.bending_length if math.isfinite(r.bending_length) else None
            rows[level] = {"edge_mm": round(edge * 1000, 2), "chord_deg": round(math.degrees(r.angle), 2),
                           "c_cm": None if c is None else round(c * 100, 4), "settled_um": round(r.settled * 1e6, 3),
                           "seconds": round(time.perf_counter() - start, 2)}
            print(f"cantilever class {cls} ({table} table) level {level}: {rows[level]}", flush=True)
        finest = rows[CANTILEVER_LEVELS[-1]]["c_cm"]
        for row in rows.values():
            if row is not None and row["c_cm"] is not None:
                row["error_vs_finest_pct"] = round(100.0 * (row["c_cm"] / finest - 1.0), 2)
        out[f"{cls} {table}"] = {"class": cls, "table": table, "material": name, "overhang_cm": overhang * 100,
                                 "levels": rows}
        record(out)
    return out


def base_grid(x: np.ndarray, uv: np.ndarray, size: float, n: int) -> np.ndarray:
    """The positions of the n x n base-grid vertices (row-major in v, then u) among a mesh's vertices."""
    g = np.asarray(uv, np.float64) * (n - 1) / size
    on = np.all(np.abs(g - np.round(g)) < 1e-4, axis=1)
    ij = np.round(g[on]).astype(int)
    out = np.full((n * n, 3), np.nan)
    out[ij[:, 1] * n + ij[:, 0]] = x[on]
    assert not np.isnan(out).any()
    return out


def drop_scene(mesh, size: float, material) -> ClipScene:
    pos = np.stack([mesh.uv[:, 0], mesh.uv[:, 1], np.ones(len(mesh.uv))], axis=1)
    corner = int(np.argmin(mesh.uv.sum(axis=1)))
    spec = ClothSpec(mesh, pos, material.stretching, material.bending, material.density, pinned=[corner])
    return ClipScene(spec, np.zeros(3), {"scene": "drop"})


def folding_scenes(cfg: SimConfig, name: str):
    """The mesh, the simulate function and the two folding scenes (``drop``, ``wind``: one cloth per k of
    ``DT_K``, with their settle times) of a remeshing level."""
    basis = load_material(cfg.basis)
    materials = [basis.scaled(1.0, k) for k in DT_K]
    mesh, simulate = setting_simulator(cfg, parse_setting(f"wind-{name}"))
    scenes = {"drop": ([drop_scene(mesh, cfg.cloth_size_m, m) for m in materials], 0.0),
              "wind": ([wind_scene(mesh, cfg.cloth_size_m, m, seeding.rng(0, WIND_CLIP, seeding.SIM, "motion-wind"),
                                   "full") for m in materials], cfg.settle_s)}
    return mesh, simulate, scenes


def final_shapes(cfg: SimConfig, mesh, simulate, batch, settle: float, substeps: int, on: bool,
                 device: str) -> list[np.ndarray]:
    """Each cloth's base-grid vertices 1 s (``fps`` frames) after the settle."""
    results = simulate(batch, fps=cfg.fps, frames=int(round(cfg.fps)), substeps=substeps, settle_s=settle,
                       cg_iterations=cfg.cg_iterations, cg_tolerance=cfg.cg_tolerance, self_collision=on,
                       collision_thickness=cfg.collision_thickness, device=device)
    assert all(r.reason is None for r in results), [r.reason for r in results]
    last = [r.frames[-1] if r.frames is not None else (r.positions[-1], mesh.faces, mesh.uv) for r in results]
    return [base_grid(x, uv, cfg.cloth_size_m, cfg.grid_vertices) for x, _, uv in last]


def distances_mm(a: list[np.ndarray], b: list[np.ndarray]) -> dict:
    """Mean (over the cloths of the mean vertex distance) and max distance between two sets of shapes, mm."""
    d = [np.linalg.norm(x - y, axis=1) for x, y in zip(a, b)]
    return {"mean": round(1000 * float(np.mean([x.mean() for x in d])), 2),
            "max": round(1000 * float(max(x.max() for x in d)), 2),
            "per_k_mean": {f"k{k:g}": round(1000 * float(x.mean()), 2) for k, x in zip(DT_K, d)}}


def each_scene(cfg: SimConfig, levels: list[str], label: str, record, cell) -> dict:
    """``cell(mesh, simulate, batch, settle, on)`` for every level, folding scene and self-collision off / on,
    as {level: {scene: {"off": ..., "on": ...}}}, recorded after each scene."""
    out = {}
    for name in levels:
        mesh, simulate, scenes = folding_scenes(cfg, name)
        out[name] = {}
        for kind, (batch, settle) in scenes.items():
            out[name][kind] = row = {}
            for on in (False, True):
                row["on" if on else "off"] = cell(mesh, simulate, batch, settle, on)
                print(f"{label} {name} {kind} self-collision {'on' if on else 'off'}: "
                      f"{json.dumps(row['on' if on else 'off'])}", flush=True)
            record(out)
    return out


def dt_part(cfg: SimConfig, levels: list[str], device: str, record) -> dict:
    def cell(mesh, simulate, batch, settle, on):
        shapes, seconds = {}, {}
        series = (cfg.substeps, 2 * cfg.substeps, 4 * cfg.substeps) if on else (cfg.substeps, 2 * cfg.substeps)
        for substeps in series:
            start = time.perf_counter()
            shapes[substeps] = final_shapes(cfg, mesh, simulate, batch, settle, substeps, on, device)
            seconds[substeps] = round(time.perf_counter() - start, 2)
        shifts = {f"dt 1/{int(cfg.fps * a)} vs 1/{int(cfg.fps * b)}": distances_mm(shapes[a], shapes[b])
                  for a, b in zip(series, series[1:])}
        finest = shapes[series[-1]]
        steps = {f"k{a:g}-k{b:g}": distances_mm([finest[DT_K.index(a)]], [finest[DT_K.index(b)]])
                 for a, b in NEIGHBOURS}
        return {"dt_shift_mm": shifts,
                "class_step_mm": {key: {"mean": d["mean"], "max": d["max"]} for key, d in steps.items()},
                "class_step_dt": f"1/{int(cfg.fps * series[-1])}", "seconds": seconds}

    return each_scene(cfg, levels, "dt", record, cell)


def floor_part(cfg: SimConfig, levels: list[str], device: str, record) -> dict:
    """How far the same folding scenes drift apart at the stage's dt when every vertex starts a distance of
    the order of ``NUDGES_M`` away (normal, seeded): what any perturbation grows to in 1 s, the floor under
    dt_shift (one step of free fall at 1/200 s already differs from the exact path by g h^2 / 2 = 0.12 mm)."""
    def cell(mesh, simulate, batch, settle, on):
        ref = final_shapes(cfg, mesh, simulate, batch, settle, cfg.substeps, on, device)
        out = {}
        for nudge in NUDGES_M:
            rng = np.random.default_rng(0)
            nudged = [dataclasses.replace(s, spec=dataclasses.replace(
                s.spec, positions=s.spec.positions + rng.normal(0.0, nudge, s.spec.positions.shape)))
                for s in batch]
            out[f"{nudge * 1e6:g} um"] = distances_mm(
                ref, final_shapes(cfg, mesh, simulate, nudged, settle, cfg.substeps, on, device))
        return out

    return each_scene(cfg, levels, "floor", record, cell)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--parts", default="cantilever,dt,floor")
    ap.add_argument("--settings", default="uniform1,uniform2,uniform3,adaptive", help="remeshing levels of the dt part")
    ap.add_argument("--out", type=Path, help="JSON path (default: benchmarks/results/sim_resolution-<device>.json)")
    args = ap.parse_args()
    device = resolve_device(args.device)
    out = args.out or (Path(__file__).resolve().parent / "results" / f"sim_resolution-{device.replace(':', '')}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    # Each part replaces only its own entry of an existing result file, with the command that made it.
    result = json.loads(out.read_text()) if out.is_file() else {}
    result.update(device=device, platform=platform.platform())
    command = " ".join([Path(sys.executable).name, *sys.argv])

    def recorder(key):
        def record(part):
            result[key] = part
            result.setdefault("commands", {})[key] = command
            out.write_text(json.dumps(result, indent=2) + "\n")
        return record

    parts = args.parts.split(",")
    if "cantilever" in parts:
        cantilever_part(device, recorder("cantilever"))
    if "dt" in parts:
        dt_part(SimConfig(), args.settings.split(","), device, recorder("dt"))
    if "floor" in parts:
        floor_part(SimConfig(), args.settings.split(","), device, recorder("floor"))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
