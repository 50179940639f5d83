"""Simulators of the block structures, shared by every method, test and the demo plant.

Every simulator takes the input sequence first, then the blocks; the maps are any callables
on numpy arrays (the static_maps classes or plain functions such as ``np.tanh``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .linear import LinearModel

StaticMap = Callable[[np.ndarray], np.ndarray]


def simulate_hammerstein(v: np.ndarray, nonlinearity: StaticMap, linear: LinearModel) -> np.ndarray:
    """y = G(q) F[v]: static map F, then the linear block G (paper 000, Fig. 1)."""
    return linear.simulate(nonlinearity(np.asarray(v, dtype=float)))


def add_noise(x: np.ndarray, noise_to_signal: float, seed=None) -> np.ndarray:
    """x plus white Gaussian noise whose standard deviation is ``noise_to_signal`` times
    std(x) (paper 000 sec. 4.3: "noise-to-signal ratios of 4% to 6%")."""
    rng = np.random.default_rng(seed)
    return x + noise_to_signal * np.std(x) * rng.standard_normal(np.shape(x))
