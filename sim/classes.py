"""The paper's 54-class material sub-space (Yang, Liang, Lin 2017, Section 4.2.2).

A class is a pair (p, k): every stretching entry of the basis material times p,
every bending entry times k. Class index = 9 * p_index + k_index, so indices run
0..53 and a higher index is (generally) a stiffer cloth: stretching dominates the
ordering, bending orders within one stretching value.

Closeness between coefficients is measured on a log scale (ratios), which is how
the paper's Table 2 maps measured fabrics onto the grid (e.g. k~ = 3.5 -> 4, 12 -> 10).
"""

from __future__ import annotations

import math

import numpy as np

P_VALUES: tuple[float, ...] = (0.5, 1.0, 2.0, 3.0, 10.0, 20.0)                      # stretching scale
K_VALUES: tuple[float, ...] = (0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 10.0, 15.0, 20.0)      # bending scale
NUM_CLASSES = len(P_VALUES) * len(K_VALUES)

# A jittered value stays within this fraction of the (log) half-gap to the
# neighbouring grid value, so it is always nearer its own class than a neighbour's.
_JITTER_GAP_FRACTION = 0.9


def _check_index(class_index: int) -> int:
    if not 0 <= int(class_index) < NUM_CLASSES:
        raise ValueError(f"class index {class_index} out of range 0..{NUM_CLASSES - 1}")
    return int(class_index)


def class_index(p_index: int, k_index: int) -> int:
    """The class of grid position (p_index, k_index)."""
    if not (0 <= p_index < len(P_VALUES) and 0 <= k_index < len(K_VALUES)):
        raise ValueError(f"grid position ({p_index}, {k_index}) outside 6 x 9")
    return len(K_VALUES) * p_index + k_index


def class_indices(class_index_: int) -> tuple[int, int]:
    """(p_index, k_index) of a class."""
    return divmod(_check_index(class_index_), len(K_VALUES))


def class_values(class_index_: int) -> tuple[float, float]:
    """(p, k) of a class."""
    pi, ki = class_indices(class_index_)
    return P_VALUES[pi], K_VALUES[ki]


def _nearest(values: tuple[float, ...], x: float) -> int:
    if not x > 0:
        raise ValueError(f"a stiffness coefficient must be positive, got {x}")
    return int(np.argmin([abs(math.log(x / v)) for v in values]))


def nearest_class(p: float, k: float) -> int:
    """The class whose (p, k) is nearest (in log ratio, per axis) to the given coefficients."""
    return class_index(_nearest(P_VALUES, p), _nearest(K_VALUES, k))


def _jitter_one(values: tuple[float, ...], i: int, jitter: float, rng: np.random.Generator) -> float:
    c = values[i]
    lo = math.log1p(-jitter) if jitter < 1 else -math.inf
    hi = math.log1p(jitter)
    if i > 0:
        lo = max(lo, -_JITTER_GAP_FRACTION * 0.5 * math.log(c / values[i - 1]))
    if i + 1 < len(values):
        hi = min(hi, _JITTER_GAP_FRACTION * 0.5 * math.log(values[i + 1] / c))
    # Draw a relative jitter c * (1 + u * jitter), then keep it inside the class's own cell.
    x = c * (1.0 + rng.uniform(-jitter, jitter))
    return float(min(max(x, c * math.exp(lo)), c * math.exp(hi)))


def jitter_class(class_index_: int, jitter: float, rng: np.random.Generator) -> tuple[float, float]:
    """(p, k) drawn around the class value with relative spread ``jitter`` (e.g. 0.1 = +-10 %).

    Each draw stays nearer its own class value than any neighbour's, so
    ``nearest_class(*jitter_class(c, ...)) == c`` always holds.
    """
    if not 0 <= jitter < 1:
        raise ValueError(f"jitter must be in [0, 1), got {jitter}")
    pi, ki = class_indices(class_index_)
    p = _jitter_one(P_VALUES, pi, jitter, rng)
    k = _jitter_one(K_VALUES, ki, jitter, rng)
    return p, k
