"""The sim stage: every (setting, clip index) of a run -> ``sim/<setting>/<clip_id>/`` (see docs/contracts.md).

Settings are ``<motion>-<remeshing>``: a motion registered in ``sim.motions.MOTIONS`` (``wind``, ``arm``);
remeshing ``uniform<L>``, the base grid refined uniformly to level L = 1, 2, 3
(``sim.mesh``), or ``adaptive``, a quadtree mesh that starts at level 1 and is
refined where the cloth curves and coarsened where it is flat after every
frame, up to level 3 (``sim.adaptive``); adaptive clips change topology between
frames and are stored per frame (``sim.clip``).

Clip ``index`` has class ``class_indices[index % n_classes]`` and sequence number
``index // n_classes``. Its material jitter comes from the ``material`` random
stream and its motion from ``motion-<motion>``, both keyed by the clip index
only, so a clip index gets the same material (and, within a motion, the same
forces) under every remeshing level.

Unfinished clips are simulated in batches of ``sim.batch_size`` cloths. A cloth
whose simulation fails the health check (non-finite, too fast, or over-stretched)
is retried once with twice the substeps; if it fails again its folder gets a
``FAILED`` file with the reason and no ``DONE``.
"""

from __future__ import annotations

import contextlib
import functools
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from clothgap import seeding
from clothgap.errors import ConfigError
from clothgap.parallel import host_processes, pool_map, pool_size
from clothgap.runs import (Run, atomic_write_json, clip_id, fresh_dir, is_done, mark_done, select_clips,
                           storage_error)
from sim import classes
from sim import remesh
from sim.adaptive import simulate_adaptive
from sim.clip import SimClip
from sim.config import REMESHING, SimConfig
from sim.intersections import count_intersections
from sim.materials import load_material, table_factors
from sim.mesh import ClothMesh, square_cloth, unique_edges, vertices_per_side
from sim.motions import MOTIONS, ClipScene, get_motion, view_box, view_zoom
from sim.phases import timed
from sim.solver import BatchSolver, CGStats, SolverParams, load_kernels, resolve_device

# Health check of every recorded frame: beyond these a cloth has exploded.
MAX_SPEED_MPS = 30.0
MAX_EDGE_STRETCH = 2.5          # current / rest edge length


@dataclass(frozen=True)
class Setting:
    name: str
    motion: str
    remeshing: str
    level: int


def parse_setting(name: str) -> Setting:
    """'<motion>-uniform<L>' or '<motion>-adaptive' -> Setting; anything else is a clear error."""
    motion, _, remeshing = name.partition("-")
    if motion not in MOTIONS:
        raise ValueError(f"setting {name!r}: unknown motion {motion!r}; known motions: {', '.join(MOTIONS)}")
    if remeshing not in REMESHING:
        raise ValueError(f"setting {name!r}: remeshing {remeshing!r} is not supported by the sim stage; "
                         f"supported: {', '.join(REMESHING)}")
    if remeshing == "adaptive":
        return Setting(name, motion, remeshing, 1)     # starts at level 1, refines up to 3
    return Setting(name, motion, remeshing, int(remeshing.removeprefix("uniform")))


@dataclass
class ClipResult:
    positions: np.ndarray | None      # (T, V, 3) float32 when ok (fixed topology)
    reason: str | None                # why it failed, else None
    frames: list | None = None        # adaptive: (positions, faces, uv) per frame when ok
    cg: CGStats | None = None         # the solver's CG work on this cloth (meta "health")
    collision_dropped: int | None = None   # self-collision pairs dropped (beyond the slots), unresolved; None: off


def _lengths(d: np.ndarray) -> np.ndarray:
    """Norms of the vectors along ``d``'s last axis (of 3): ``np.linalg.norm(d, axis=-1)``'s values, the squares
    added in the same order in ``d``'s dtype, in elementwise passes (numpy's reduction over a 3-long axis is
    ~10x slower, and an adaptive batch checks every cloth every frame)."""
    sq = d * d
    out = sq[..., 0] + sq[..., 1]
    out += sq[..., 2]
    return np.sqrt(out, out=out)


def health(x: np.ndarray, x_prev: np.ndarray, frame_dt: float, edges: np.ndarray, rest: np.ndarray) -> str | None:
    """None when a recorded frame is plausible, else the reason."""
    if not np.isfinite(x).all():
        return "non-finite positions"
    speed = float(_lengths(x - x_prev).max()) / frame_dt
    if speed > MAX_SPEED_MPS:
        return f"vertex speed {speed:.1f} m/s exceeds {MAX_SPEED_MPS} m/s"
    # np.take gathers rows ~3x faster than fancy indexing with an index column
    stretch = float((_lengths(np.take(x, edges[:, 1], axis=0) - np.take(x, edges[:, 0], axis=0)) / rest).max())
    if stretch > MAX_EDGE_STRETCH:
        return f"edge stretched {stretch:.2f}x its rest length (limit {MAX_EDGE_STRETCH}x)"
    return None


def _batch_health(cur: np.ndarray, prev: np.ndarray, frame_dt: float, edges: np.ndarray,
                  rest: np.ndarray) -> list[str | None]:
    """``health`` for B cloths on one mesh at once: cur, prev (B, V, 3)."""
    out: list[str | None] = [None] * len(cur)
    finite = np.isfinite(cur).all(axis=(1, 2))
    speed = _lengths(cur - prev).max(axis=1) / frame_dt
    stretch = (_lengths(np.take(cur, edges[:, 1], axis=1) - np.take(cur, edges[:, 0], axis=1)) / rest).max(axis=1)
    for c in np.flatnonzero(~finite | (speed > MAX_SPEED_MPS) | (stretch > MAX_EDGE_STRETCH)):
        out[c] = health(cur[c], prev[c], frame_dt, edges, rest)
    return out


def settled_solver(scenes: list[ClipScene], *, fps: float, substeps: int, settle_s: float, cg_iterations: int,
                   cg_tolerance: float, self_collision: bool, collision_thickness: float,
                   device: str, phases: dict[str, float] | None = None) -> BatchSolver:
    """The batch's solver where recording starts: settled without wind for ``settle_s``, each scene's wind set.
    ``phases`` (optional) gets the seconds of loading the kernels, building the solver and settling."""
    dt = 1.0 / (fps * substeps)
    params = SolverParams(dt=dt, cg_iterations=cg_iterations, cg_tolerance=cg_tolerance,
                          self_collision=self_collision, collision_thickness=collision_thickness)
    with timed(phases, "kernels"):       # compiled on a machine's first run, then loaded from Warp's cache
        load_kernels(device)
    with timed(phases, "solver"):
        solver = BatchSolver([s.spec for s in scenes], params, device)
    with timed(phases, "settle"):
        solver.step(int(round(settle_s / dt)))
        solver.set_wind(np.stack([s.wind for s in scenes]))
        solver.positions()               # waits for the device
    return solver


def simulate_scenes(scenes: list[ClipScene], *, fps: float, frames: int, substeps: int, settle_s: float,
                    cg_iterations: int = 30, cg_tolerance: float = SolverParams.cg_tolerance,
                    self_collision: bool = False, collision_thickness: float = SolverParams.collision_thickness,
                    device: str = "cpu", on_frame: Callable[[], None] | None = None,
                    phases: dict[str, float] | None = None) -> list[ClipResult]:
    """Simulate a batch: settle without wind for ``settle_s``, then record ``frames`` frames with the wind on.
    ``on_frame`` is called after each recorded frame (progress); ``phases`` (optional) gets the seconds of
    each phase (``settled_solver``'s, then ``record``)."""
    solver = settled_solver(scenes, fps=fps, substeps=substeps, settle_s=settle_s, cg_iterations=cg_iterations,
                            cg_tolerance=cg_tolerance, self_collision=self_collision,
                            collision_thickness=collision_thickness, device=device, phases=phases)
    with timed(phases, "record"):
        # The stage simulates a batch on one mesh: check it in one vectorised pass (else cloth by cloth).
        meshes = {id(s.spec.mesh) for s in scenes}
        groups = []
        for mesh_id in meshes:
            members = np.array([c for c, s in enumerate(scenes) if id(s.spec.mesh) == mesh_id])
            m = scenes[members[0]].spec.mesh
            e = unique_edges(m.faces)
            groups.append((members, e, np.linalg.norm(m.uv[e[:, 1]] - m.uv[e[:, 0]], axis=1)))
        reasons: list[str | None] = [None] * len(scenes)
        prev = solver.positions()
        recorded = []
        solver.step(substeps)
        for t in range(frames):
            cur = solver.positions()                 # waits for frame t
            if t + 1 < frames:
                solver.step(substeps)                # on a GPU frame t+1 runs while the host checks frame t
            for members, e, rest in groups:
                found = _batch_health(np.stack([cur[c] for c in members]), np.stack([prev[c] for c in members]),
                                      1.0 / fps, e, rest)
                for c, why in zip(members, found):
                    if why is not None and reasons[c] is None:
                        reasons[c] = f"frame {t}: {why}"
            recorded.append(cur)
            prev = cur
            if on_frame is not None:
                on_frame()
        cg = solver.cg_stats()
        dropped = solver.collision_dropped() or [None] * len(scenes)
    return [ClipResult(None if r else np.stack([f[c] for f in recorded]), r, cg=cg[c], collision_dropped=dropped[c])
            for c, r in enumerate(reasons)]


def simulate_adaptive_scenes(scenes: list[ClipScene], base, *, fps: float, frames: int, substeps: int,
                             settle_s: float, cg_iterations: int = 30,
                             cg_tolerance: float = SolverParams.cg_tolerance, self_collision: bool = False,
                             collision_thickness: float = SolverParams.collision_thickness, device: str = "cpu",
                             on_frame: Callable[[], None] | None = None,
                             phases: dict[str, float] | None = None,
                             host_workers: int | None = None) -> list[ClipResult]:
    """``simulate_scenes`` with adaptive remeshing after every frame; same health check per frame. ``phases``
    (optional) gets the seconds of ``sim.adaptive.simulate_adaptive``'s phases (settle, steps, health, remesh,
    rebuild). ``host_workers``: processes that remesh (None picks by batch size)."""
    def check(cloth, x, x_prev, frame_dt):          # on the mesh the solver ran this frame on
        return health(x, x_prev, frame_dt, cloth.state.edges, cloth.state.edge_rest)

    out = simulate_adaptive(scenes, base, fps=fps, frames=frames, substeps=substeps, settle_s=settle_s,
                            cg_iterations=cg_iterations, cg_tolerance=cg_tolerance, self_collision=self_collision,
                            collision_thickness=collision_thickness, device=device, health=check, on_frame=on_frame,
                            host_workers=host_workers, phases=phases)
    return [ClipResult(None, r.reason, r.frames, r.cg, r.collision_dropped) for r in out]


def setting_simulator(cfg: SimConfig, setting: Setting) -> tuple[ClothMesh, Callable[..., list[ClipResult]]]:
    """The mesh a setting's scenes are built on and the function that simulates a batch of them
    (``simulate_scenes``, or ``simulate_adaptive_scenes`` remeshing from the level-1 quadtree)."""
    if setting.remeshing == "adaptive":
        base = remesh.uniform(cfg.grid_vertices, cfg.cloth_size_m, 1)
        return remesh.cloth_mesh(base), functools.partial(simulate_adaptive_scenes, base=base)
    return square_cloth(cfg.cloth_size_m, cfg.grid_vertices, setting.level), simulate_scenes


def clip_health(result: ClipResult, mesh: ClothMesh) -> dict:
    """The meta's ``health``: the CG statistics, the triangle pairs that cut through each other in the last
    recorded frame (``sim.intersections``), and with self-collision the pairs it dropped, unresolved."""
    out = result.cg.health() if result.cg is not None else {}
    if result.frames is not None:
        x, faces, _ = result.frames[-1]
        out["self_intersections"] = count_intersections(x, faces)
    elif result.positions is not None:
        out["self_intersections"] = count_intersections(result.positions[-1], mesh.faces)
    if result.collision_dropped is not None:
        out["collision_pairs_dropped"] = result.collision_dropped
    return out


def clip_material(cfg: SimConfig, seed: int, index: int) -> tuple[int, float, float]:
    """(class_index, p, k) of a clip: its class and the jittered coefficients from its material stream."""
    cls = cfg.class_indices()
    class_index = cls[index % len(cls)]
    p, k = classes.jitter_class(class_index, cfg.jitter, seeding.rng(seed, index, seeding.SIM, "material"))
    return class_index, p, k


def clip_density(cfg: SimConfig, seed: int, index: int) -> float:
    """A class clip's area density under ``sim.density_range`` (log-uniform, from its own ``density`` stream, so
    that the range changes no other draw of the clip)."""
    lo, hi = cfg.density_range
    return float(np.exp(seeding.rng(seed, index, seeding.SIM, "density").uniform(np.log(lo), np.log(hi))))


def clip_table_factors(cfg: SimConfig, seed: int, index: int) -> tuple[np.ndarray, np.ndarray]:
    """A class clip's table factors under ``sim.table_spread`` (from its own ``tables`` stream, so that the spread
    changes no other draw of the clip)."""
    return table_factors(cfg.table_spread, seeding.rng(seed, index, seeding.SIM, "tables"), cfg.table_shape)


def build_scene(cfg: SimConfig, seed: int, index: int, setting: Setting, mesh: ClothMesh,
                fabric: str | None = None, density: float | None = None) -> tuple[ClipScene, dict]:
    """The scene of one clip and the label part of its meta.

    ``fabric`` overrides the material: the named measured fabric (``assets/materials``)
    with its own full Wang tables, not the basis scaled by a class's (p, k). Its
    labels are then the paper's Table 2 class (``sim.measured``) and the estimated
    ratios p~, k~ to the basis; the motion draws are the clip index's as usual. ``density`` (kg/m^2) replaces
    the fabric's own area density (a diagnostic: how much of a fabric's motion its density makes); the meta
    keeps its own as ``density_own``.
    """
    motion_rng = seeding.rng(seed, index, seeding.SIM, f"motion-{setting.motion}")
    if fabric is None:
        class_index, p, k = clip_material(cfg, seed, index)
        basis = load_material(cfg.basis)
        material = basis.scaled(p, k)
        if cfg.density_range:
            material = replace(material, density=clip_density(cfg, seed, index))
        p_class, k_class = classes.class_values(class_index)
        meta = {"class_index": class_index, "p_class": p_class, "k_class": k_class, "p": p, "k": k,
                "basis": cfg.basis, "density": material.density}
        if cfg.table_spread:
            factors = clip_table_factors(cfg, seed, index)
            material = material.reshaped(*factors)
            meta["table_factors"] = {"stretching": factors[0].tolist(), "bending": factors[1].tolist()}
    else:
        from sim.measured import fabric_labels

        material = load_material(fabric)
        meta = fabric_labels(fabric)
        if density is not None:
            material = replace(material, density=float(density))
            meta = {**meta, "density": float(density), "density_own": meta["density"]}
    return get_motion(setting.motion).scene(mesh, material, motion_rng, cfg), meta


@dataclass(frozen=True)
class ClipJob:
    """One clip to simulate: its seed index, folder name, sequence number and material override."""

    index: int                  # the clip index every random draw is keyed by (clothgap.seeding)
    name: str                   # folder name: clip_id(index), or <fabric>-<n> for a measured fabric
    sequence: int
    fabric: str | None = None   # a measured fabric simulated with its own tables (build_scene)
    density: float | None = None    # the measured fabric's density replaced by this (build_scene)


def run_sim(run: Run, progress: bool = True, indices: Sequence[int] | None = None) -> dict:
    """Simulate every unfinished clip of every setting of the run; returns counts per outcome.

    ``indices`` limits the work to those clip indices (one shard of ``clothgap.executor``).
    """
    cfg = run.config.sim
    for c in cfg.class_indices():
        classes.class_indices(c)          # validate early
    wanted = select_clips(cfg.num_clips(), indices)
    jobs = [ClipJob(i, clip_id(i), cfg.sequence_of(i)) for i in wanted]
    return simulate_jobs(run, {s: jobs for s in cfg.settings()}, run.sim_dir, progress)


def merge_shard_summaries(parts: list[dict]) -> dict:
    """One ``run_sim`` summary from the summaries of its shards (``indices=``, run by ``clothgap.executor``):
    counts add up, failed clips are listed together; ``seconds`` is left to the caller, who timed the whole."""
    merged: dict = {k: sum(p.get(k, 0) for p in parts) for k in ("simulated", "skipped", "failed", "retried")}
    merged["failed_clips"] = [f for p in parts for f in p.get("failed_clips", [])]
    merged["seconds"] = 0.0
    phases: dict[str, float] = {}
    for p in parts:
        for k, v in p.get("phases_s", {}).items():
            phases[k] = round(phases.get(k, 0.0) + v, 2)
    merged["phases_s"] = phases       # summed over shards, which may have run at the same time
    return merged


def simulate_jobs(run: Run, jobs: dict[str, list[ClipJob]], folder_of: Callable[[str], Path],
                  progress: bool = True, label: str = "sim") -> dict:
    """Simulate the unfinished ``jobs`` of each setting into ``folder_of(setting) / job.name``.

    The batching, health check, retry, FAILED/DONE markers and meta of every sim
    clip; ``run_sim`` and the measured-fabric set (``sim.measured``) both come here.
    """
    from tqdm import tqdm

    cfg = run.config.sim
    device = resolve_device(cfg.device)
    summary = {"simulated": 0, "skipped": 0, "failed": 0, "retried": 0, "failed_clips": [], "seconds": 0.0}
    # Where the seconds went: building scenes, the batch's simulation (its kernels, solver, settle and record
    # on uniform meshes; a retry's included), waiting for the previous batch's clips to be written
    # (write_wait), and, beside them in the writer's thread, checking and writing the clips (write).
    phases: dict[str, float] = {}
    start = time.perf_counter()

    def write_batch(setting, out, batch, built, substeps, results, mesh) -> list[bool]:
        with timed(phases, "write"):
            metas = [clip_meta(run, setting, job, scene, labels, sub, mesh)
                     for job, (scene, labels), sub in zip(batch, built, substeps)]
            return write_clips([out / j.name for j in batch], metas, results, mesh)

    def written(pending) -> None:
        future, setting, batch, results = pending
        with timed(phases, "write_wait"):
            ok = future.result()
        summary["simulated"] += sum(ok)
        summary["failed"] += len(ok) - sum(ok)
        summary["failed_clips"] += [{"setting": setting, "clip_id": j.name, "error": r.reason}
                                    for j, r, good in zip(batch, results, ok) if not good]

    # A batch is written in a writer thread while the next simulates (one batch at most waits to be written):
    # with four sim workers on a 64-core host writing took a fifth of each worker's time. A failed write is
    # raised once the next batch has simulated; leaving the block waits for a write still running.
    pending = None
    with ThreadPoolExecutor(max_workers=1) as writer:
        for setting in [parse_setting(s) for s in jobs]:
            out = folder_of(setting.name)
            todo = [j for j in jobs[setting.name] if not is_done(out / j.name)]
            summary["skipped"] += len(jobs[setting.name]) - len(todo)
            mesh, simulate = setting_simulator(cfg, setting)
            # Progress in clip-frames: a GPU batch of thousands of clips finishes all at once.
            bar = tqdm(total=len(todo) * cfg.frames, desc=f"{label} {setting.name}", unit="clip-frame",
                       unit_scale=True, disable=not progress)
            for b in range(0, len(todo), cfg.batch_size):
                batch = todo[b:b + cfg.batch_size]
                with _noting_failed_write(pending):
                    with timed(phases, "scenes"):
                        built = [build_scene(cfg, run.config.seed, j.index, setting, mesh, j.fabric, j.density)
                                 for j in batch]
                    scenes = [s for s, _ in built]
                    with timed(phases, "simulate"):
                        results, substeps = simulate_batch(cfg, simulate, scenes, device,
                                                           on_frame=lambda n=len(batch): bar.update(n),
                                                           phases=phases)
                summary["retried"] += sum(sub != cfg.substeps for sub in substeps)   # simulated a second time
                if pending is not None:
                    written(pending)
                pending = (writer.submit(write_batch, setting, out, batch, built, substeps, results, mesh),
                           setting.name, batch, results)
            bar.close()
        if pending is not None:
            written(pending)
    summary["seconds"] = round(time.perf_counter() - start, 3)
    summary["phases_s"] = {k: round(v, 2) for k, v in phases.items()}
    return summary


@contextlib.contextmanager
def _noting_failed_write(pending):
    """An error of the block also says whether the previous batch's write (``pending``: its future first) failed,
    which would otherwise be lost behind it."""
    try:
        yield
    except BaseException as err:
        failed = pending[0].exception() if pending is not None else None
        if failed is not None:
            err.add_note(f"writing the previous batch's clips failed too: {failed!r}")
        raise


def simulate_batch(cfg: SimConfig, simulate: Callable[..., list[ClipResult]], scenes: list[ClipScene], device: str,
                   on_frame: Callable[[], None] | None = None,
                   phases: dict[str, float] | None = None) -> tuple[list[ClipResult], list[int]]:
    """Simulate a batch of scenes at ``cfg.substeps``, then once more at twice the substeps those that failed
    the health check; returns each scene's result and the substeps it was simulated with."""
    solver_options = dict(cg_iterations=cfg.cg_iterations, cg_tolerance=cfg.cg_tolerance,
                          self_collision=cfg.self_collision, collision_thickness=cfg.collision_thickness,
                          device=device)
    results = simulate(scenes, fps=cfg.fps, frames=cfg.frames, substeps=cfg.substeps, settle_s=cfg.settle_s,
                       on_frame=on_frame, phases=phases, **solver_options)
    substeps = [cfg.substeps] * len(scenes)
    failed = [j for j, r in enumerate(results) if r.reason]
    if failed:
        retry = simulate([scenes[j] for j in failed], fps=cfg.fps, frames=cfg.frames, substeps=2 * cfg.substeps,
                         settle_s=cfg.settle_s, **solver_options)
        for j, r in zip(failed, retry):
            if r.reason:
                r.reason = f"{results[j].reason}; retry with {2 * cfg.substeps} substeps: {r.reason}"
            results[j] = r
            substeps[j] = 2 * cfg.substeps
    return results, substeps


def clip_meta(run: Run, setting: Setting, job: ClipJob, scene: ClipScene, labels: dict, substeps: int,
              mesh: ClothMesh) -> dict:
    """A clip's ``meta.json`` before its outcome (``health``, ``status``) is known: the clip, its labels,
    the simulation's settings, the motion's draws and the setting's camera box and zoom."""
    cfg = run.config.sim
    meta = {"clip_id": job.name, "index": job.index, "sequence": job.sequence, "setting": setting.name,
            "motion": setting.motion, "remeshing": setting.remeshing, **labels,
            "seed": run.config.seed, "fps": cfg.fps, "frames": cfg.frames, "substeps": substeps,
            "dt": 1.0 / (cfg.fps * substeps), "settle_s": cfg.settle_s, "cloth_size_m": cfg.cloth_size_m,
            "vertices_per_side": vertices_per_side(cfg.grid_vertices, setting.level),
            "motion_params": scene.motion_params, "view_box": view_box(setting.motion, cfg.cloth_size_m),
            "view_zoom": view_zoom(setting.motion, cfg), "self_collision": cfg.self_collision}
    if cfg.self_collision:
        meta["collision_thickness_m"] = cfg.collision_thickness
    return meta


# A batch this large on a machine with this many cores is checked and written by processes: the intersection
# count and the clip's files are ~4 ms of mostly GIL-holding numpy a clip, which threads do not overlap.
PROCESS_WRITE_MIN_CLIPS = 512
PROCESS_WRITE_MIN_CPUS = 8


def write_clips(folders: list[Path], metas: list[dict], results: list[ClipResult], mesh: ClothMesh,
                processes: int | None = None) -> list[bool]:
    """``write_clip`` for every clip of a batch; returns each clip's outcome.

    ``processes`` None picks: a spawned process pool (one process per CPU of this process's share,
    ``clothgap.parallel.host_processes``, chunks of clips) for a large batch on a machine with several
    cores, else threads; 0 forces threads."""
    if processes is None:
        processes = pool_size(len(folders), PROCESS_WRITE_MIN_CLIPS, PROCESS_WRITE_MIN_CPUS)
    if processes <= 0 or len(folders) < 2:
        with ThreadPoolExecutor(max_workers=min(32, host_processes(), max(len(folders), 1))) as pool:
            return list(pool.map(write_clip, folders, metas, results, [mesh] * len(folders)))
    # Results travel as arrays (~0.1 MB a clip).
    return list(pool_map(write_clip, folders, metas, results, [mesh] * len(folders), processes=processes))


def write_clip(folder: Path, meta: dict, result: ClipResult, mesh: ClothMesh) -> bool:
    """Write one simulated clip into a fresh ``folder``: the SimClip and DONE when it is healthy (True), else
    FAILED with the reason (False). A full or read-only disk leaves no half-written clip and is a StorageError."""
    try:
        return _write_clip(folder, meta, result, mesh)
    except OSError as e:
        err = storage_error(e, folder)
        if err is None:
            raise
        shutil.rmtree(folder, ignore_errors=True)
        raise err from None


def _write_clip(folder: Path, meta: dict, result: ClipResult, mesh: ClothMesh) -> bool:
    fresh_dir(folder)
    meta = {**meta, "health": clip_health(result, mesh)}
    if result.reason:
        atomic_write_json(folder / "FAILED", {**meta, "status": "failed", "reason": result.reason})
        return False
    meta["status"] = "ok"
    if result.frames is not None:
        counts = [len(f[0]) for f in result.frames]
        meta["vertex_counts"] = {"min": min(counts), "max": max(counts), "mean": float(np.mean(counts))}
        SimClip.from_frames(meta, result.frames).save(folder)
    else:
        SimClip.from_fixed(meta, result.positions, mesh.faces, mesh.uv).save(folder)
    mark_done(folder, {"status": "ok"})
    return True


def simulate_measured(run: Run, fabrics: Sequence[str], sequences: int, progress: bool = True,
                      settings: Sequence[str] | None = None, density: float | None = None,
                      folder_of: Callable[[str], Path] | None = None,
                      clips: Mapping[str, Sequence[tuple[str, int]]] | None = None) -> dict:
    """Simulate ``sequences`` clips of each fabric under every setting of the run, or those of ``settings``
    (finished ones skipped), into ``run.measured_sim_dir`` or ``folder_of(setting)``; ``density`` replaces each
    fabric's own (``build_scene``: then give a folder of their own). ``clips`` (setting -> (fabric, sequence)
    pairs among those) limits it to those settings and clips (a shard)."""
    from sim.measured import MAX_SEQUENCES, check_fabrics, clip_name, measured_index, wanted_clips

    check_fabrics(fabrics)
    if not 0 < sequences <= MAX_SEQUENCES:
        raise ConfigError(f"measured sequences must be 1..{MAX_SEQUENCES}, got {sequences}")
    if density is not None and folder_of is None:
        raise ConfigError("measured clips at another density than their own need a folder of their own (folder_of)")
    wanted = wanted_clips(fabrics, sequences)
    jobs = [ClipJob(measured_index(f, n), clip_name(f, n), n, fabric=f, density=density) for f, n in wanted]
    settings = run.config.sim.settings() if settings is None else settings
    by_setting = {s: jobs for s in settings}
    if clips is not None:
        chosen = {s: set(map(tuple, c)) for s, c in clips.items()}
        outside = sorted(set().union(*chosen.values()) - set(wanted))
        if outside:
            raise ConfigError(f"measured clips {outside[:3]} are not among {len(fabrics)} fabric(s) x {sequences}")
        by_setting = {s: [j for j, c in zip(jobs, wanted) if c in keep] for s, keep in chosen.items()}
    return simulate_jobs(run, by_setting, folder_of or run.measured_sim_dir, progress, label="sim measured")
