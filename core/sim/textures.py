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


def fitzpatrick_albedo(skin_type: int) -> float:
    """Diffuse albedo of skin in the near infrared-red band of the rig's LEDs, Fitzpatrick I to VI
    (0.6 for the palest to 0.1 for the darkest, as the issue's clinic asks)."""
    if not 1 <= skin_type <= 6:
        raise ValueError(f"Fitzpatrick skin type must be 1-6, got {skin_type}")
    return float(np.interp(skin_type, [1, 6], [0.6, 0.1]))


def body_albedo(x: np.ndarray, y: np.ndarray, body, landmarks, half_width: np.ndarray, top: np.ndarray,
                clothing: str, seed: int, skin: float, on_arm: np.ndarray, back: bool) -> np.ndarray:
    """A parametric body's albedo: bare skin of the given tone with blotches, moles, chest hair on
    men, a tattoo for some; trousers with a waistband; a bra (band, cups, straps) on women; or a
    tight T-shirt over it all (`clothing='tshirt'`)."""
    if clothing not in ("skin", "tshirt"):
        raise ValueError(f"unknown clothing {clothing!r}: tshirt or skin")
    rng = np.random.default_rng(seed + 31)
    s = landmarks.s
    albedo = skin * (1.0 + 0.07 * smooth_noise(x, y, seed + 7, 60.0, octaves=2))
    for _ in range(int(rng.integers(4, 14))):
        mx, my = rng.uniform(-200, 200) * s, rng.uniform(landmarks.acromion, landmarks.hips)
        albedo = np.where((x - mx) ** 2 + (y - my) ** 2 < rng.uniform(4, 16), 0.5 * skin, albedo)
    adult = body.age_years >= 16
    if body.sex == "male" and adult and not back and rng.random() < 0.6:
        density = rng.uniform(0.2, 0.6)
        region = np.exp(-0.5 * ((x / (90 * s)) ** 2 + ((y - landmarks.nipples) / (110 * s)) ** 2))
        speckle = smooth_noise(x, y, seed + 13, 3.0, octaves=1) > 1.0 - density
        albedo = np.where(speckle & (region > 0.3), 0.55 * albedo, albedo)
    if adult and rng.random() < 0.3:
        cx = rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.7) * body.chest_width_mm / 2
        cy = rng.uniform(landmarks.axilla, landmarks.navel)
        u, v = (x - cx) / (40 * s), (y - cy) / (30 * s)
        ink = (u * u + v * v < 1.0) & (np.sin(9.0 * u) * np.cos(7.0 * v) > 0.1)
        albedo = np.where(ink, 0.35 * skin, albedo)
    if clothing == "tshirt":
        albedo = tshirt_albedo(x, y, half_width, top, seed, back=back)
    elif body.sex == "female" and adult:
        band_y = landmarks.nipples + 75.0 * s
        cloth = 0.75 if rng.random() < 0.5 else 0.12
        band = np.abs(y - band_y) < 14.0 * s
        if back:
            straps = (np.abs(np.abs(x) - 0.27 * body.shoulder_width_mm) < 9.0 * s) & (y < band_y)
            albedo = np.where(band | straps, cloth, albedo)
        else:
            cups = ((np.abs(x) - 0.42 * body.chest_width_mm / 2) / (0.3 * body.chest_width_mm / 2)) ** 2 + \
                   ((y - landmarks.nipples - 10.0 * s) / (55.0 * s)) ** 2 < 1.0
            straps = (np.abs(np.abs(x) - 0.3 * body.chest_width_mm / 2) < 8.0 * s) & (y < landmarks.nipples)
            albedo = np.where(band | cups | straps, cloth, albedo)
    albedo = np.where(on_arm, skin * (1.0 + 0.05 * smooth_noise(x, y, seed + 5, 40.0, octaves=1)), albedo)
    trousers = y > landmarks.waistband + 12.0 * s
    waistband = np.abs(y - landmarks.waistband) <= 12.0 * s
    albedo = np.where(trousers & ~on_arm, 0.12, np.where(waistband & ~on_arm, 0.3, albedo))
    return np.clip(albedo, 0.02, 0.95)
