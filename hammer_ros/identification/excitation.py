"""Excitation signals used by the papers and the demo (all return float arrays of length n)."""

from __future__ import annotations

import numpy as np


def gaussian_white_noise(n: int, std: float, mean: float = 0.0, seed=None) -> np.ndarray:
    """i.i.d. N(mean, std^2) samples; paper 000 sec. 4.1 uses std = 1/(2 pi), paper 003 a
    non-zero mean."""
    return mean + std * np.random.default_rng(seed).standard_normal(n)


def uniform_white_noise(n: int, low: float = -1.0, high: float = 1.0, seed=None) -> np.ndarray:
    """i.i.d. uniform samples on [low, high] (paper 001, Examples 1-2)."""
    return np.random.default_rng(seed).uniform(low, high, n)


def sine(n: int, omega: float, amplitude: float = 1.0, phase: float = 0.0) -> np.ndarray:
    """amplitude * sin(omega k + phase), omega in rad/sample (the single harmonic of paper 002)."""
    return amplitude * np.sin(omega * np.arange(n) + phase)


def phase_modulated_chirp(
    n: int,
    sample_rate: float = 100.0,
    amplitude: float = 0.5,
    center_hz: float = 20.0,
    deviation_hz: float = 19.5,
    sweep_hz: float = 0.02,
) -> np.ndarray:
    """Phase-modulated sinusoid of paper 000, eq. (13):

        v(t) = A sin(w0 t + (Dw / ws) sin(ws t)),   t = k / sample_rate,

    with w0 = 2 pi center_hz, Dw = 2 pi deviation_hz, ws = 2 pi sweep_hz (the paper gives the
    frequencies in Hz; read as cyclic frequencies, the instantaneous frequency
    w0 + Dw cos(ws t) sweeps 0.5..39.5 Hz, inside the 50 Hz Nyquist band at 100 Hz).
    """
    t = np.arange(n) / sample_rate
    w0, dw, ws = 2 * np.pi * center_hz, 2 * np.pi * deviation_hz, 2 * np.pi * sweep_hz
    return amplitude * np.sin(w0 * t + (dw / ws) * np.sin(ws * t))
