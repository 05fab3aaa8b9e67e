"""Seeds per stage and per clip.

Every random draw in the platform comes from ``rng(seed, clip_index, stage,
*stream)``: the run seed, the clip's index, the stage, and optionally a named
stream inside the stage (one per randomizer). Turning one randomizer on or off
therefore never shifts the draws of another, and the same clip index gets the
same simulation under every render variant (paired ablations).
"""

from __future__ import annotations

import zlib

import numpy as np

# Stage ids are part of every seed: never renumber them.
SIM = 1
RENDER = 2
TRAIN = 3
EVAL = 4


def stream_id(name: str) -> int:
    """A stable integer for a stream name (crc32, independent of PYTHONHASHSEED)."""
    return zlib.crc32(name.encode("utf-8"))


def seed_sequence(seed: int, clip_index: int, stage: int, *stream: int | str) -> np.random.SeedSequence:
    parts = [int(seed), int(clip_index), int(stage)]
    parts += [stream_id(s) if isinstance(s, str) else int(s) for s in stream]
    return np.random.SeedSequence(parts)


def rng(seed: int, clip_index: int, stage: int, *stream: int | str) -> np.random.Generator:
    """The generator of one clip in one stage (and one named stream)."""
    return np.random.default_rng(seed_sequence(seed, clip_index, stage, *stream))


def derive_int(seed: int, clip_index: int, stage: int, *stream: int | str) -> int:
    """A 31-bit integer seed for libraries that take one (Mitsuba's sampler, torch)."""
    return int(seed_sequence(seed, clip_index, stage, *stream).generate_state(1)[0] & 0x7FFFFFFF)
