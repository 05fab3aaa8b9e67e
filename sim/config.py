"""The sim stage's settings (no heavy imports here: the CLI reads this at start-up).

The names the sim stage supports live here or, for the motions, in the registry
``sim.motions.MOTIONS`` (no Warp there either), so that a config is checked
without importing Warp: ``sim.stage`` builds scenes for the registered motions
and meshes for ``REMESHING`` (``parse_setting``).
"""

from __future__ import annotations

from dataclasses import dataclass

from clothgap import checks

REMESHING = ("uniform1", "uniform2", "uniform3", "adaptive")    # uniform<level>; adaptive refines 1..3
WIND_NUISANCE = ("full", "speed")                               # what a wind clip draws (sim.motions.wind_scene)
ARM_NUISANCE = ("full", "speed")                                # what an arm clip draws (sim.motions.arm_scene)


@dataclass(frozen=True)
class SimConfig:
    # The simulated settings: every (motion, remeshing) pair is one dataset.
    motions: tuple[str, ...] = ("wind",)            # names in sim.motions.MOTIONS: "wind", "arm"
    remeshing: tuple[str, ...] = ("uniform1",)      # "uniform1", "uniform2", "uniform3", "adaptive"
    # Material classes simulated (indices into sim.classes, 0..53); empty = all 54.
    classes: tuple[int, ...] = ()
    sequences_per_class: int = 48                   # 54 x 48 = 2,592, the paper's dataset size
    basis: str = "camel-ponte-roma"                 # the paper's basis material
    jitter: float = 0.1                             # relative jitter of (p, k) around the class value
    # A class clip's area density, kg/m^2: () keeps the basis fabric's (the paper: the classes differ in stiffness
    # only); (lo, hi) draws it log-uniform in [lo, hi] per clip (meta "density"), so that a class is read from
    # motion made at many weights, as real fabrics have (the measured ones: 0.11-0.32). The label stays (p, k).
    density_range: tuple[float, ...] = ()
    # A class clip's tables off the paper's sub-space: 0 (the paper) scales the basis's by (p, k); s > 0 multiplies
    # each entry by exp(s z) drawn per clip (meta "table_factors"), then rescales each table back to p and k times
    # the basis's summary figure (sim.materials.Material.reshaped), so a class is read from cloths of many
    # anisotropies and curves, as the measured fabrics are. The label stays (p, k).
    table_spread: float = 0.0
    table_shape: str = "entries"                    # how: "entries" (one draw an entry) or "smooth" (a factor a
                                                    # direction, a high-strain factor, a trend over curvature)
    grid_vertices: int = 16                         # vertices per side at uniform level 1
    cloth_size_m: float = 0.5                       # side of the square cloth, metres
    frames: int = 20                                # frames written per sequence
    fps: float = 25.0
    substeps: int = 8                               # solver steps per frame
    settle_s: float = 0.4                           # simulated seconds before the first recorded frame
    cg_iterations: int = 30                         # the most conjugate-gradient iterations per solver step
    cg_tolerance: float = 1.0e-3                    # a cloth's CG stops at |r| <= tol |r0|; 0: run to float32's limit
    self_collision: bool = False                    # keep non-adjacent parts of a cloth apart (sim.collision)
    collision_thickness: float = 0.003              # m, the gap self-collision keeps; below half the finest edge
    device: str = "auto"                            # "auto", "cpu", "cuda", "cuda:N"
    batch_size: int = 512                           # cloths advanced together in one launch
    wind_nuisance: str = "full"                     # "full": pose, gathering, wind speed and direction drawn
                                                    # per clip; "speed": only the wind speed (the paper varies
                                                    # "the external force magnitude"); rod pose, fixed gathering
    arm_nuisance: str = "full"                      # "full": the cloth's place on the arm and the forearm's speed
                                                    # drawn per clip; "speed": only the speed, the cloth centred
    arm_view_zoom: float = 1.0                      # the arm camera's field of view narrowed by this factor from
                                                    # its view box (meta view_zoom; the paper preset: 1.3)

    def problems(self) -> list[str]:
        """What is wrong with these settings, one message each (empty when they are valid)."""
        from sim.classes import NUM_CLASSES          # numpy only
        from sim.materials import TABLE_SHAPES, list_materials     # numpy only
        from sim.motions import MOTIONS              # numpy only

        out = checks.names("sim.motions", self.motions, tuple(MOTIONS), "motion")
        out += checks.names("sim.remeshing", self.remeshing, REMESHING, "remeshing")
        bad = [c for c in self.classes if not 0 <= c < NUM_CLASSES]
        if bad:
            out.append(f"sim.classes: class index {', '.join(map(str, bad))} out of range 0..{NUM_CLASSES - 1}")
        else:
            out += checks.names("sim.classes", self.classes, range(NUM_CLASSES), "class", required=False)
        out += checks.choice("sim.basis", self.basis, list_materials())
        out += checks.number("sim.sequences_per_class", self.sequences_per_class, 1)
        out += checks.number("sim.jitter", self.jitter, 0, 1, hi_open=True)
        if self.density_range:
            lo_hi = list(self.density_range)
            if len(lo_hi) != 2 or not 0 < lo_hi[0] <= lo_hi[1] or lo_hi[1] > 10:
                out.append(f"sim.density_range={','.join(f'{v:g}' for v in lo_hi)}: give two area densities "
                           "LO,HI in kg/m^2 with 0 < LO <= HI <= 10 (e.g. 0.1,0.35), or leave it empty for the "
                           "basis fabric's")
        out += checks.number("sim.table_spread", self.table_spread, 0, 1)    # runs went to 0.5; 1 spans 7x at 2 sigma
        out += checks.choice("sim.table_shape", self.table_shape, tuple(TABLE_SHAPES))
        if self.table_shape != "entries" and not self.table_spread:
            out.append(f"sim.table_shape={self.table_shape}: reshapes nothing without sim.table_spread (set it above 0, "
                       "e.g. 0.5, or leave the shape at entries)")
        out += checks.number("sim.grid_vertices", self.grid_vertices, 2)
        out += checks.number("sim.cloth_size_m", self.cloth_size_m, 0, lo_open=True)
        out += checks.number("sim.frames", self.frames, 1)
        out += checks.number("sim.fps", self.fps, 0, lo_open=True)
        out += checks.number("sim.substeps", self.substeps, 1)
        out += checks.number("sim.settle_s", self.settle_s, 0)
        out += checks.number("sim.cg_iterations", self.cg_iterations, 1)
        out += checks.number("sim.cg_tolerance", self.cg_tolerance, 0, 1, hi_open=True)
        out += checks.number("sim.batch_size", self.batch_size, 1)
        thickness = checks.number("sim.collision_thickness", self.collision_thickness, 0, lo_open=True)
        out += thickness
        if self.self_collision and not thickness and not out:
            # A flat mesh has triangles not incident to a vertex 0.71 edge from it: a thickness near that
            # pushes the resting cloth apart from itself.
            edge = self.finest_edge_m()
            if self.collision_thickness >= 0.5 * edge:
                out.append(f"sim.collision_thickness={self.collision_thickness:g}: must be below half the finest "
                           f"edge, {0.5 * edge:.4g} m ({self.grid_vertices} vertices per side on a "
                           f"{self.cloth_size_m:g} m cloth, level {self.finest_level()})")
        out += checks.choice("sim.wind_nuisance", self.wind_nuisance, WIND_NUISANCE)
        out += checks.choice("sim.arm_nuisance", self.arm_nuisance, ARM_NUISANCE)
        out += checks.number("sim.arm_view_zoom", self.arm_view_zoom, 0, lo_open=True)
        out += checks.device("sim.device", self.device)
        return out

    def finest_level(self) -> int:
        """The finest uniform level the settings reach (adaptive remeshing refines up to level 3)."""
        return max(3 if r == "adaptive" else int(r.removeprefix("uniform")) for r in self.remeshing)

    def finest_edge_m(self) -> float:
        """The shortest (axis-aligned) edge of the finest mesh the settings reach, metres."""
        return self.cloth_size_m / ((self.grid_vertices - 1) * 2 ** (self.finest_level() - 1))

    def class_indices(self) -> tuple[int, ...]:
        return self.classes or tuple(range(54))

    def sequence_of(self, index: int) -> int:
        """The sequence number of clip ``index``: clips go round the classes (class ``class_indices()[index %
        n]``), so the n clips of one round are sequence ``index // n`` of each class."""
        return index // len(self.class_indices())

    def settings(self) -> list[str]:
        """Dataset names, one per (motion, remeshing): e.g. 'wind-uniform1'."""
        return [f"{m}-{r}" for m in self.motions for r in self.remeshing]

    def num_clips(self) -> int:
        return len(self.class_indices()) * self.sequences_per_class
