"""Albedo textures on the body grid: a tight white T-shirt (print, seams, collar) and skin."""

from __future__ import annotations

import numpy as np


def smooth_noise(x: np.ndarray, y: np.ndarray, seed: int, wavelength_mm: float, octaves: int = 3) -> np.ndarray:
    """Deterministic band-limited noise in about [-1, 1]: a sum of random plane waves."""
    rng = np.random.default_rng(seed)
    out = np.zeros_like(x, dtype=float)
    total = 0.0
    for octave in range(octaves):
        k = 2 * np.pi / (wavelength_mm / 2**octave)
        weight = 0.5**octave
        for _ in range(4):
            angle = rng.uniform(0, np.pi)
            phase = rng.uniform(0, 2 * np.pi)
            out += weight * np.cos(k * (x * np.cos(angle) + y * np.sin(angle)) + phase)
            total += weight
    return out / np.sqrt(total * 2)


def tshirt_albedo(x: np.ndarray, y: np.ndarray, half_width: np.ndarray, top: np.ndarray, seed: int,
                  back: bool = False) -> np.ndarray:
    """White cotton (0.82) with weave variation, a dark chest print, shoulder and side seams, a collar."""
    albedo = 0.82 + 0.015 * smooth_noise(x, y, seed, 40.0)
    seam = 0.62
    side = np.abs(np.abs(x) - 0.93 * half_width) < 1.5
    shoulder = np.abs(y - (top + 18.0)) < 1.5
    albedo = np.where(side | shoulder, seam, albedo)
    hem = np.abs(y - 255.0) < 2.0
    albedo = np.where(hem, seam, albedo)
    if not back:
        # A print on the chest: block letters and a stripe, ink albedo 0.18.
        u, v = x + 95.0, y + 40.0
        in_box = (u >= 0) & (u <= 190) & (v >= 0) & (v <= 60)
        letter = (np.floor(u / 19.0) % 2 == 0) & ((v < 10) | (v > 50) | (np.mod(u, 19.0) < 5))
        stripe = (v > 26) & (v < 34)
        albedo = np.where(in_box & (letter | stripe), 0.18, albedo)
    return albedo


def skin_albedo(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """Skin (0.45) with slow blotches and a few small moles."""
    albedo = 0.45 + 0.03 * smooth_noise(x, y, seed + 7, 60.0, octaves=2)
    rng = np.random.default_rng(seed + 11)
    for _ in range(6):
        mx, my = rng.uniform(-180, 180), rng.uniform(-150, 200)
        albedo = np.where((x - mx) ** 2 + (y - my) ** 2 < 9.0, 0.25, albedo)
    return albedo
