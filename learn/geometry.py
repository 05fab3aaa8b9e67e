"""The simulator's geometry as a training-time target: the cloth's lattice per rendered frame.

A model on renders sees the cloth only through pixels; the simulation that made
them knows where every point of the cloth was. With ``train.aux_geometry`` > 0 (or ``train.bottleneck``)
the CNN also regresses, from each frame, the 8 x 8 lattice of cloth points
(``sim.lattice``) that the learnability probe reads, so its features must carry
the shape the material class shows in. The target exists at training time
only: prediction and evaluation read pixels alone.

Targets are standardised per setting, robustly: each coordinate of each point
minus its median over all frames (``train.geometry_centre=frame``: over the
frames of the same index, so that what every clip does at that moment, such as
the arm's sweep, is not part of the target), divided by one global spread (the
RMS deviation of the median clip), then clipped to +-``TARGET_LIMIT``. A few clips
whose cloth leaves its usual place would otherwise set the spread, shrink every
other frame's target towards zero and leave the regression nothing to learn;
those clips are named in a warning. The loss weight means the same on every
setting. Targets are cached per setting in
``cache/geometry/<setting>/lattice-8.npz`` (one array per clip).
"""

from __future__ import annotations

import warnings

import numpy as np
from tqdm import tqdm

from clothgap.errors import MissingInputError
from clothgap.files import atomic_path
from clothgap.parallel import pool_map, pool_size
from clothgap.runs import Run
from learn.dataset import FrameCache
from learn.models import GEOMETRY_DIM
from sim.lattice import LATTICE, clip_lattice


TARGET_LIMIT = 10.0        # standardised units
# A pool reads the lattices of at least this many clips on a host of at least this many CPUs (spawning costs
# ~1 s; a uniform clip's lattice takes ~2 ms).
POOL_MIN_CLIPS = 256
POOL_MIN_CPUS = 4


def clip_lattices(run: Run, setting: str, clip_ids: list[str], progress: bool = True,
                  processes: int | None = None) -> dict[str, np.ndarray]:
    """{clip_id: (T, 64, 3) float32} for the given clips of ``setting``, from the cache or the sim clips.

    Clips not in the cache are read in a spawned process pool when there are many (``processes`` None picks by
    ``clothgap.parallel.pool_size``; 0 reads them here): an adaptive clip needs a lattice index per frame, 12 ms a
    clip on the 2-core CPU, about 31 s for a setting's 2,592 adaptive clips in one process."""
    path = run.lattice_cache_path(setting, LATTICE)
    stored: dict[str, np.ndarray] = {}
    if path.is_file():
        with np.load(path) as data:
            stored = {k: data[k] for k in data.files}
    missing = [c for c in clip_ids if c not in stored]
    sim_dir = run.sim_dir(setting)
    for cid in missing:
        folder = sim_dir / cid
        if not (folder / "DONE").is_file():
            raise MissingInputError(f"train.aux_geometry needs the simulated clip {folder} (the lattice target "
                                    f"comes from the simulation), but it is missing or unfinished")
    if processes is None:
        processes = pool_size(len(missing), POOL_MIN_CLIPS, POOL_MIN_CPUS)
    bar = tqdm(total=len(missing), desc=f"lattice {setting}", unit="clip", disable=not progress, leave=False)
    for cid, lattice in zip(missing, pool_map(clip_lattice, [sim_dir / cid for cid in missing], processes=processes)):
        stored[cid] = lattice
        bar.update()
    bar.close()
    if missing:
        with atomic_path(path, keep_suffix=True) as tmp:
            np.savez(tmp, **stored)
    return {c: stored[c] for c in clip_ids}


def geometry_targets(run: Run, setting: str, cache: FrameCache, progress: bool = True,
                     centre: str = "median") -> np.ndarray:
    """(cache rows, 192) standardised lattice of the frame in each row of the frame cache (``centre``:
    ``train.geometry_centre``)."""
    lattices = clip_lattices(run, setting, sorted(cache.clips), progress)
    rows = cache.frames.shape[0]
    out = np.zeros((rows, GEOMETRY_DIM), np.float32)
    for cid, clip in cache.clips.items():
        lat = lattices[cid]
        if len(lat) != clip.num_frames:
            raise MissingInputError(f"clip {cid} of {setting}: {len(lat)} simulated frames but "
                                    f"{clip.num_frames} rendered ones; re-render it")
        out[clip.offset:clip.offset + clip.num_frames] = lat.reshape(len(lat), -1)
    slices = {cid: slice(c.offset, c.offset + c.num_frames) for cid, c in cache.clips.items()}
    targets, spread, far = standardise(out, slices, centre)
    if far:
        warnings.warn(f"{len(far)} clip(s) of {setting} have lattice points more than {TARGET_LIMIT:g} spreads "
                      f"({TARGET_LIMIT * spread:.3g} m) from the usual shape; their targets are clipped: "
                      f"{', '.join(far[:5])}{' ...' if len(far) > 5 else ''}", stacklevel=2)
    return targets


def standardise(lattice_rows: np.ndarray, clips: dict[str, slice],
                centre: str = "median") -> tuple[np.ndarray, float, list[str]]:
    """(targets, spread in metres, far clip ids) of flattened lattice rows (rows, 192), each clip's rows given
    by a slice: minus the median over the clips' rows (``centre="frame"``: over the rows of the same frame
    index), over the RMS deviation of the median clip, clipped to +-``TARGET_LIMIT`` (the module's docstring
    says why)."""
    shape = median_shape(lattice_rows, clips, centre)
    if centre == "median":
        targets = lattice_rows - shape
    else:
        targets = lattice_rows.copy()
        for r in clips.values():
            targets[r] -= shape[:r.stop - r.start]
    spread = float(np.sqrt(np.median([(targets[r] ** 2).mean() for r in clips.values()]))) or 1.0
    targets /= spread
    far = sorted(cid for cid, r in clips.items() if np.abs(targets[r]).max() > TARGET_LIMIT)
    return np.clip(targets, -TARGET_LIMIT, TARGET_LIMIT), spread, far


def median_shape(lattice_rows: np.ndarray, clips: dict[str, slice], centre: str = "median") -> np.ndarray:
    """What targets are measured from (``train.geometry_centre``): the median of the clips' rows, (1, 192), or
    with ``centre="frame"`` the median of the rows at each frame index, (longest clip's frames, 192)."""
    if centre == "median":
        used = np.concatenate([np.arange(r.start, r.stop) for r in clips.values()])
        return np.median(lattice_rows[used], axis=0, keepdims=True)
    if centre != "frame":
        raise ValueError(f"centre={centre!r}: expected 'median' or 'frame'")
    frames = max(r.stop - r.start for r in clips.values())
    return np.stack([np.median(lattice_rows[[r.start + t for r in clips.values() if r.stop - r.start > t]], axis=0)
                     for t in range(frames)])
