"""The 54 material classes as the eval stage sees them.

Class index = 9 * p_index + k_index (Yang et al. 2017, Sec. 4.2): p scales every
stretching entry of the basis material, k every bending entry.

The value tuples are a local copy of the paper's sub-space; ``sim.classes`` is
meant to own them. When it exists and defines ``P_VALUES``/``K_VALUES`` they are
taken from there (and must agree), so the two stages cannot drift apart.
"""

from __future__ import annotations

import numpy as np

P_VALUES: tuple[float, ...] = (0.5, 1.0, 2.0, 3.0, 10.0, 20.0)
K_VALUES: tuple[float, ...] = (0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 10.0, 15.0, 20.0)

try:  # prefer the sim stage's table once it has landed
    from sim import classes as _sim_classes  # type: ignore[attr-defined]

    P_VALUES = tuple(float(v) for v in getattr(_sim_classes, "P_VALUES", P_VALUES))
    K_VALUES = tuple(float(v) for v in getattr(_sim_classes, "K_VALUES", K_VALUES))
except ImportError:
    pass

NUM_P = len(P_VALUES)
NUM_K = len(K_VALUES)
NUM_CLASSES = NUM_P * NUM_K

# Mean of the 15 bending entries (N*m) of the basis material camel-ponte-roma
# (Wang, Ramamoorthi, O'Brien 2011 measured tables, as shipped in the project's
# reference folder). A class's bending stiffness is k times this value.
BASIS_MEAN_BENDING_N_M = 3.3052e-05


def p_index(class_index) -> np.ndarray:
    return np.asarray(class_index) // NUM_K


def k_index(class_index) -> np.ndarray:
    return np.asarray(class_index) % NUM_K


def class_of(p_idx: int, k_idx: int) -> int:
    return int(p_idx) * NUM_K + int(k_idx)


def p_value(class_index) -> np.ndarray:
    return np.asarray(P_VALUES)[p_index(class_index)]


def k_value(class_index) -> np.ndarray:
    return np.asarray(K_VALUES)[k_index(class_index)]


def nearest_class(p: float, k: float) -> int:
    """The class whose (p, k) is nearest in log space (how Table 2 discretises)."""
    pi = int(np.argmin(np.abs(np.log(P_VALUES) - np.log(p))))
    ki = int(np.argmin(np.abs(np.log(K_VALUES) - np.log(k))))
    return class_of(pi, ki)


def label(class_index: int) -> str:
    """Short human label, e.g. 'p2 k0.5'."""
    return f"p{P_VALUES[int(p_index(class_index))]:g} k{K_VALUES[int(k_index(class_index))]:g}"
