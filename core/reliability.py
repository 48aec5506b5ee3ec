"""Reliability-based pruning, Eq. (6).

R(E_min, E_next) = sigma(eps1 * ((E_next - E_min) / (eps2 * E_min) - eps3)), and the reliable
pixels are P_L^R = {p in P_L : R > threshold}.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from threadrecon.core.params import Params, param
from threadrecon.core.stereo import StereoResult

E_FLOOR = 1e-6  # E_min = 0 (a perfect match) gives an infinite ratio: R -> 1 without a 0/0


@dataclass(frozen=True)
class ReliabilityParams(Params):
    eps1: float = param(8.0, lo=0, hi=1000, symbol="eps1", slider=(0.0, 30.0, 0.1), label="ε1")
    """Sigmoid gain epsilon_1 of Eq. (6)."""
    eps2: float = param(5.0, lo=1e-09, hi=1000, symbol="eps2", slider=(0.1, 30.0, 0.1), label="ε2")
    """Energy-ratio scale epsilon_2 of Eq. (6)."""
    eps3: float = param(0.8, lo=-1000, hi=1000, symbol="eps3", slider=(-5.0, 5.0, 0.01), label="ε3")
    """Sigmoid shift epsilon_3 of Eq. (6)."""
    threshold: float = param(0.9, lo=0, hi=0.999999, slider=(0.0, 0.99, 0.01), label="threshold")
    """Reliable when R > threshold."""


@dataclass(frozen=True)
class ReliabilityResult:
    """``R``: (N,) float in [0, 1] per pixel of P_L; ``reliable``: (N,) bool, p in P_L^R."""

    R: np.ndarray
    reliable: np.ndarray

    @property
    def count(self) -> int:
        return int(self.reliable.sum())


def reliability(
    E_min: np.ndarray, E_next: np.ndarray, p: ReliabilityParams = ReliabilityParams()
) -> np.ndarray:
    """Eq. (6), elementwise; E_next = inf (no second candidate) gives R = 1."""
    if p.eps2 <= 0:
        raise ValueError(f"eps2 must be > 0, got {p.eps2}")
    E_min = np.maximum(np.asarray(E_min, dtype=np.float64), E_FLOOR)
    with np.errstate(over="ignore", invalid="ignore"):
        z = p.eps1 * ((np.asarray(E_next, dtype=np.float64) - E_min) / (p.eps2 * E_min) - p.eps3)
        R = 0.5 * (1.0 + np.tanh(0.5 * z))  # sigma(z), overflow-free
    return np.nan_to_num(R, nan=0.0)


def prune(stereo: StereoResult, p: ReliabilityParams = ReliabilityParams()) -> ReliabilityResult:
    """Reliability of every pixel of P_L and the reliable set P_L^R (finite depth only)."""
    if not 0.0 <= p.threshold < 1.0:
        raise ValueError(f"threshold must be in [0, 1), got {p.threshold}")
    R = reliability(stereo.E_min, stereo.E_next, p)
    reliable = (p.threshold < R) & np.isfinite(stereo.depth)
    return ReliabilityResult(R=R, reliable=reliable)
