"""Where the solver steps of an adaptive batch go, against uniform1 on the same clips (the ``steps`` phase).

    python benchmarks/sim_adaptive_steps.py [--device cpu] [--motion wind] [--clips 8] [--stride 7] [--frames 6]
                                            [--profile-frame 4]
    python benchmarks/sim_adaptive_steps.py --device cuda --clips 432 --stride 1 --frames 40 --profile-frame 20
                                            # the clips of the H100 stage runs (8 sequences a class)

Simulates the ``paper`` preset's clips 0, stride, 2 stride, ... of ``<motion>-uniform1`` and ``<motion>-adaptive``
as the stage does, with the device synchronised around every solver step and read-back, so that each is timed
alone (on a GPU the stage overlaps some of them). Per recorded frame: the batch's vertices, faces and edges, the
CG iterations a step took (mean over the cloths; a GPU launches all ``cg_iterations`` whatever the count), the
first step of the frame's solver and the mean of its other steps (an adaptive frame's solver is new: on a GPU its
first step captures and instantiates a CUDA graph, so the difference is what a solver new every frame costs
there), and the read-back of positions and velocities. With ``--profile-frame F`` both settings run frame F launch
by launch with each kernel timed (its device time on a GPU, its wall time on a CPU). The clips are those of a
plain run (on a CPU the same bytes: a step split in two and a frame launch by launch change nothing). Writes
benchmarks/results/sim_adaptive_steps-<device>-<motion>-n<clips>.json with the command.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path
from unittest import mock

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, paper_scenes, simulate_options, write_result  # noqa: E402  (benchmarks/common.py)
import sim.adaptive  # noqa: E402
import sim.stage  # noqa: E402
from sim import kernels  # noqa: E402
from sim.solver import BatchSolver, resolve_device  # noqa: E402


# The CG's Hessian-product kernels (sim.kernels) with their share of the per-cloth dot product p.K p added into the
# cloth's one slot by every element (``mode`` 2: how the CG ran them before its chunked sums, so that thousands of
# adds a cloth met at one address), stored per element (1), or dropped (0). Timed side by side on the profiled
# frame's state (``TimedSolver.product_variants``), with the CG's present form: stored per element, then added up a
# chunk of a cloth at a time (sim.kernels.cloth_chunk_sum).
@wp.kernel
def face_product_forms(p: wp.array(dtype=wp.vec3), tri: wp.array2d(dtype=int), dm_inv: wp.array(dtype=wp.mat22),
                       f0_in: wp.array(dtype=wp.vec3), f1_in: wp.array(dtype=wp.vec3), kmat: wp.array(dtype=wp.vec4),
                       smat: wp.array(dtype=wp.vec3), scale: float, out: wp.array(dtype=wp.vec3),
                       dots: wp.array(dtype=float), cloth: wp.array(dtype=int), acc: wp.array2d(dtype=float),
                       mode: int):
    """sim.kernels' face product (``face_product``); its p.K p share per ``mode`` (above)."""
    f = wp.tid()
    share = kernels.face_product(f, p, tri, dm_inv, f0_in, f1_in, kmat, smat, scale, out)
    if mode == 1:
        dots[f] = share
    elif mode == 2:
        wp.atomic_add(acc, 0, cloth[f], share)


@wp.kernel
def hinge_product_forms(p: wp.array(dtype=wp.vec3), hinge: wp.array2d(dtype=int), stiffness: wp.array(dtype=float),
                        grad: wp.array2d(dtype=wp.vec3), scale: float, out: wp.array(dtype=wp.vec3),
                        dots: wp.array(dtype=float), cloth: wp.array(dtype=int), acc: wp.array2d(dtype=float),
                        mode: int):
    """sim.kernels' hinge product (``hinge_product``); its p.K p share per ``mode``."""
    h = wp.tid()
    share = kernels.hinge_product(h, p, hinge, stiffness, grad, scale, out)
    if mode == 1:
        dots[h] = share
    elif mode == 2:
        wp.atomic_add(acc, 0, cloth[h], share)


class TimedSolver(BatchSolver):
    """A ``BatchSolver`` whose steps and read-backs append their device-synchronised seconds to ``calls``, one
    entry per ``step`` call (the batch's first is the settling)."""

    calls: list[dict] = []
    profile_call: int | None = None       # the index in ``calls`` of the step call run launch by launch

    def _sync(self) -> float:
        wp.synchronize_device(self.device)
        return time.perf_counter()

    def step(self, n: int = 1) -> None:
        iterations = self.cg_iteration_sum.numpy().copy()
        call = {"steps": n, "new_solver": self._steps == 0, "vertices": self.num_vertices, "faces": self.num_faces,
                "edges": 0 if self.collision is None else int(self.collision.edge.shape[0])}
        start = self._sync()
        if len(self.calls) == self.profile_call:
            call["kernels_ms_per_step"] = self._profile(n)
            call["steps_s"] = self._sync() - start
            call["product_variants_ms"] = self.product_variants()
        elif call["new_solver"] and n > 1:
            super().step(1)
            first = self._sync()
            super().step(n - 1)
            call["first_step_s"], call["other_steps_s"] = first - start, self._sync() - first
        else:
            super().step(n)
            call["other_steps_s"] = self._sync() - start
        call["cg_iterations"] = float(((self.cg_iteration_sum.numpy() - iterations) / n).mean())
        self.calls.append(call)

    def _profile(self, n: int) -> dict[str, float]:
        times: dict[str, list[float]] = defaultdict(list)
        if wp.get_device(self.device).is_cuda:
            with wp.ScopedTimer("frame", print=False, synchronize=True, cuda_filter=wp.TIMING_KERNEL) as timer:
                self.step_uncaptured(n)
            for r in timer.timing_results:
                times[r.name].append(r.elapsed)
        else:                 # CPU launches run to completion: each launch's wall time is its kernel's
            host: dict[str, list[float]] = {}
            self.step_uncaptured(n, host_times=host)
            times.update({k: [1e3 * s for s in v] for k, v in host.items()})
        return dict(sorted(((k, round(sum(v) / n, 4)) for k, v in times.items()), key=lambda kv: -kv[1]))

    def product_variants(self, repeats: int = 30) -> dict[str, float]:
        """Milliseconds a launch of each Hessian-product form on the solver's present search direction, every cloth
        running (the next step sets that again), into scratch arrays: with the per-cloth dot product added
        by every element into the cloth's slot, stored per element, dropped, and both products as the CG runs them
        now (stored per element, then summed a chunk of a cloth at a time)."""
        nf, nh, dev = self.num_faces, self.num_hinges, self.device
        out = wp.zeros_like(self.ap)
        acc = wp.zeros((1, self.num_cloths), dtype=float, device=dev)
        dots = wp.zeros(max(nf, nh), dtype=float, device=dev)
        face = [self.p, self.tri, self.dm_inv, self.f0, self.f1, self.kmat, self.smat, 1.0, out, dots,
                self.face_cloth, acc]
        hinge = [self.p, self.hinge, self.hinge_k, self.hinge_grad, 1.0, out, dots, self.hinge_cloth, acc]
        self.cg_active.fill_(1)
        chunked: list = []                        # the solver's own recorded launches, as a CG iteration runs them
        self._record_hessian_product(self._launcher(chunked), self.p, out, 1.0, acc, 0)
        forms = {"face_per_cloth_slot": lambda: wp.launch(face_product_forms, nf, face + [2], device=dev),
                 "face_per_element": lambda: wp.launch(face_product_forms, nf, face + [1], device=dev),
                 "face_no_dot": lambda: wp.launch(face_product_forms, nf, face + [0], device=dev),
                 "hinge_per_cloth_slot": lambda: wp.launch(hinge_product_forms, nh, hinge + [2], device=dev),
                 "hinge_per_element": lambda: wp.launch(hinge_product_forms, nh, hinge + [1], device=dev),
                 "hinge_no_dot": lambda: wp.launch(hinge_product_forms, nh, hinge + [0], device=dev),
                 "both_as_the_cg_runs_them": lambda: [launch() for launch in chunked]}
        times = {}
        for name, run in forms.items():
            run()                                 # compiled and warm before the clock
            start = self._sync()
            for _ in range(repeats):
                run()
            times[name] = round(1e3 * (self._sync() - start) / repeats, 4)
        return times

    def _read(self, read) -> list[np.ndarray]:
        start = self._sync()
        out = read()
        self.calls[-1]["read_back_s"] = self.calls[-1].get("read_back_s", 0.0) + time.perf_counter() - start
        return out

    def positions(self) -> list[np.ndarray]:
        return self._read(super().positions) if self.calls else super().positions()

    def velocities(self) -> list[np.ndarray]:
        return self._read(super().velocities) if self.calls else super().velocities()


def run_setting(name: str, indices, frames: int, device: str, profile_frame: int | None) -> dict:
    cfg, simulate, built = paper_scenes(name, indices)
    TimedSolver.calls = []
    TimedSolver.profile_call = None if profile_frame is None else profile_frame + 1    # after the settling call
    phases: dict[str, float] = {}
    with mock.patch.object(sim.adaptive, "BatchSolver", TimedSolver), \
            mock.patch.object(sim.stage, "BatchSolver", TimedSolver):
        results = simulate([scene for scene, _ in built], **simulate_options(cfg, frames, device, phases=phases))
    settle, recorded = TimedSolver.calls[0], TimedSolver.calls[1:]
    rows = []
    for f, call in enumerate(recorded):
        n = call["steps"]
        row = {"frame": f, "new_solver": call["new_solver"], "vertices": call["vertices"], "faces": call["faces"],
               "edges": call["edges"], "cg_iterations": round(call["cg_iterations"], 2),
               "read_back_ms": round(1e3 * call.get("read_back_s", 0.0), 2)}
        if "kernels_ms_per_step" in call:
            row.update(profiled=True, step_ms=round(1e3 * call["steps_s"] / n, 3),
                       kernels_ms_per_step=call["kernels_ms_per_step"],
                       product_variants_ms=call["product_variants_ms"])
        else:
            others = call["other_steps_s"] / (n - 1 if "first_step_s" in call else n)
            row["step_ms"] = round(1e3 * others, 3)
            if "first_step_s" in call:
                row["first_step_extra_ms"] = round(1e3 * (call["first_step_s"] - others), 3)
        rows.append(row)
    timed = [r for r in rows if "profiled" not in r]
    steps_per_frame = recorded[0]["steps"]
    return {"setting": name, "clips": len(built), "steps_per_frame": steps_per_frame,
            "failed": sum(r.reason is not None for r in results),
            "settle_ms_per_step": round(1e3 * (settle.get("first_step_s", 0.0) + settle["other_steps_s"])
                                        / settle["steps"], 3),
            "vertices_per_cloth_mean": round(float(np.mean([r["vertices"] for r in rows])) / len(built), 1),
            "cg_iterations_mean": round(float(np.mean([r["cg_iterations"] for r in rows])), 2),
            "step_ms_mean": round(float(np.mean([r["step_ms"] for r in timed])), 3),
            "new_solver_extra_ms_per_frame": round(float(np.mean([r.get("first_step_extra_ms", 0.0) for r in timed])), 3),
            "read_back_ms_per_frame": round(float(np.mean([r["read_back_ms"] for r in rows])), 3),
            "phases_s": {k: round(v, 3) for k, v in phases.items()}, "frames": rows}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--motion", default="wind")
    ap.add_argument("--clips", type=int, default=8)
    ap.add_argument("--stride", type=int, default=7, help="clip indices 0, stride, 2 stride, ... (54 classes)")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--profile-frame", type=int, help="run this recorded frame launch by launch, kernels timed")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    indices = range(0, args.stride * args.clips, args.stride)
    rows = [run_setting(f"{args.motion}-{remeshing}", indices, args.frames, device, args.profile_frame)
            for remeshing in ("uniform1", "adaptive")]
    for row in rows:
        print({k: v for k, v in row.items() if k != "frames"}, flush=True)
    uniform, adaptive = rows
    ratios = {"step": adaptive["step_ms_mean"] / uniform["step_ms_mean"],
              "vertices": adaptive["vertices_per_cloth_mean"] / uniform["vertices_per_cloth_mean"],
              "cg_iterations": adaptive["cg_iterations_mean"] / uniform["cg_iterations_mean"]}
    print("adaptive / uniform1:", {k: round(v, 2) for k, v in ratios.items()})
    out = args.out or RESULTS / f"sim_adaptive_steps-{device.split(':')[0]}-{args.motion}-n{args.clips}.json"
    write_result("sim_adaptive_steps.py", argv, {"device": device, "gpu": wp.get_device(device).name,
                                                 "frames": args.frames,
                                                 "adaptive_over_uniform1": {k: round(v, 3) for k, v in ratios.items()},
                                                 "settings": rows}, out)


if __name__ == "__main__":
    main()
