"""Shapes of the simulated scenes as height fields on a body grid (mm).

Each builder returns the front and back `HeightField` of an object; the placement in front
of the cameras is the scene's job (core/sim/scene.py).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import PchipInterpolator

from core.sim.surfaces import BodyGrid, HeightField, build_height_field
from core.sim.textures import skin_albedo, smooth_noise, tshirt_albedo

TORSO_MODES = ("chest_left", "chest_right", "abdomen")


def _gauss(*terms: np.ndarray) -> np.ndarray:
    return np.exp(-0.5 * sum(t * t for t in terms))


def _smooth_max(a: np.ndarray, b: np.ndarray, k_mm: float) -> np.ndarray:
    """Smooth union of two heights (NaN = absent)."""
    a = np.where(np.isfinite(a), a, -1e9)
    b = np.where(np.isfinite(b), b, -1e9)
    hi = np.maximum(a, b)
    out = hi + k_mm * np.log1p(np.exp(-np.abs(a - b) / k_mm))
    return np.where(hi > -1e8, out, np.nan)


def torso_outline(y: np.ndarray) -> np.ndarray:
    """Half-width of the trunk (mm) against height y (mm, down; 0 = mid-chest)."""
    knots_y = [-235, -190, -140, -100, -40, 40, 150, 230, 300, 380]
    knots_w = [300, 322, 318, 300, 288, 265, 218, 232, 250, 255]
    return PchipInterpolator(knots_y, knots_w)(np.clip(y, -235, 380))


def shoulder_top(x: np.ndarray) -> np.ndarray:
    """y of the upper edge of the trunk (shoulder line) against x."""
    ax = np.abs(x)
    return -228.0 + 58.0 * np.clip((ax - 75.0) / 250.0, 0.0, None) ** 1.7


def _trunk(x: np.ndarray, y: np.ndarray, half_depth: np.ndarray, exponent: float) -> tuple[np.ndarray, np.ndarray]:
    """Height of a superelliptic trunk cross-section with rounded shoulders; also the cross-section factor."""
    w = torso_outline(y)
    top = shoulder_top(x)
    s = np.clip(np.abs(x) / w, 0.0, 1.0)
    inside = (np.abs(x) < w) & (y > top)
    across = np.where(inside, (1.0 - s**exponent) ** (1.0 / exponent), 0.0)
    below_top = np.clip((y - top) / 45.0, 0.0, 1.0)
    rounding = np.sqrt(below_top * (2.0 - below_top))
    height = np.where(inside, half_depth * across * rounding, np.nan)
    return height, across * rounding


def _neck(x: np.ndarray, y: np.ndarray, half_depth_mm: float) -> np.ndarray:
    s = np.abs(x) / 62.0
    return np.where((s < 1.0) & (y < -150), half_depth_mm * np.sqrt(np.clip(1 - s * s, 0, 1)), np.nan)


def torso(grid_step_mm: float = 1.0, clothing: str = "tshirt", seed: int = 0,
          specular: float = 0.0) -> dict[str, HeightField]:
    """An adult torso, about 650 x 450 mm seen from the front (shoulder line to lower abdomen).

    Front: pectorals, sternum, clavicles, costal margin, abdomen and navel, T-shirt folds at the
    waist. Back: scapulae, spine groove, lumbar curve. The trunk goes on below the field of view
    (trousers from y = 260 mm) and the neck above it. Breathing modes (1 mm peak each): left and
    right chest, abdomen; the back moves about a third as much as the front.
    """
    grid = BodyGrid.covering(340.0, -360.0, 400.0, grid_step_mm)
    x, y = grid.coordinates()
    w = torso_outline(y)
    top = shoulder_top(x)

    front_depth = PchipInterpolator([-235, -150, -60, 30, 130, 250, 400], [70, 98, 122, 118, 116, 108, 104])(
        np.clip(y, -235, 400))
    h_front, c_front = _trunk(x, y, front_depth, 2.4)
    features = (
        12.0 * _gauss((np.abs(x) - 95.0) / 62.0, (y + 85.0) / 52.0)  # pectorals
        - 4.0 * _gauss(x / 14.0, (y + 70.0) / 90.0)  # sternum
        + 4.0 * _gauss((y + 192.0 + 0.12 * np.abs(x)) / 9.0) * (np.abs(x) < 190)  # clavicles
        + 3.0 * _gauss((y - 40.0 - 0.35 * np.abs(x)) / 12.0) * (np.abs(x) < 170)  # costal margin
        + 12.0 * _gauss(x / 130.0, (y - 140.0) / 90.0)  # abdomen
        - 5.0 * _gauss(x / 7.0, (y - 205.0) / 7.0)  # navel
        + 1.2 * np.sin(x / 17.0 + 0.4 * y / 17.0) * _gauss((y - 238.0) / 22.0)  # folds at the waist
    )
    h_front = _smooth_max(h_front + features * c_front, _neck(x, y, 55.0), 6.0)

    back_depth = PchipInterpolator([-235, -150, -60, 60, 180, 400], [70, 100, 108, 104, 92, 100])(
        np.clip(y, -235, 400))
    h_back, c_back = _trunk(x, y, back_depth, 2.7)
    back_features = (
        10.0 * _gauss((np.abs(x) - 100.0) / 55.0, (y + 110.0) / 70.0)  # scapulae
        - 6.0 * _gauss(x / 12.0) * (y > -210)  # spine groove
        + 2.0 * _gauss(x / 4.0) * np.cos(y / 12.0) ** 8 * (y > -210)  # spinous processes
        - 8.0 * _gauss((y - 200.0) / 60.0) * np.clip(1 - np.abs(x) / 250, 0, 1)  # lumbar curve
    )
    h_back = _smooth_max(h_back + back_features * c_back, _neck(x, y, 55.0), 6.0)

    on_trunk = (np.abs(x) < w) & (y > top)
    breathing_taper = np.where(on_trunk, np.clip(1.0 - (x / w) ** 2, 0.0, 1.0), 0.0)
    chest = _gauss((y + 60.0) / 85.0) * breathing_taper
    left = 1.0 / (1.0 + np.exp(-x / 25.0))  # subject's left is the front image's right
    abdomen = _gauss((y - 150.0) / 80.0) * breathing_taper
    front_modes = {"chest_left": chest * left, "chest_right": chest * (1 - left), "abdomen": abdomen}
    back_modes = {"chest_left": 0.35 * chest * left, "chest_right": 0.35 * chest * (1 - left),
                  "abdomen": 0.15 * abdomen}

    trousers = y > 262.0
    if clothing == "tshirt":
        a_front = tshirt_albedo(x, y, w, top, seed)
        a_back = tshirt_albedo(x, y, w, top, seed + 1, back=True)
    elif clothing == "skin":
        a_front = skin_albedo(x, y, seed)
        a_back = skin_albedo(x, y, seed + 1)
    else:
        raise ValueError(f"unknown clothing {clothing!r}: tshirt or skin")
    neck = (y < top + 2.0) | (np.abs(x) < 62) & (y < -215)
    a_front = np.where(trousers, 0.12, np.where(neck, 0.45, a_front))
    a_back = np.where(trousers, 0.12, np.where(neck, 0.45, a_back))

    front = build_height_field(grid, h_front, a_front, front_modes, specular=specular, shininess=30.0)
    back = build_height_field(grid, h_back, a_back, back_modes, specular=specular, shininess=30.0)
    return {"front": front, "back": back}


def plane(grid_step_mm: float = 2.0, tilt_x_deg: float = 10.0, tilt_y_deg: float = 5.0,
          albedo: float = 0.8, half_width_mm: float = 350.0, half_height_mm: float = 260.0) -> dict[str, HeightField]:
    """A flat board, tilted about the vertical (x slope) and horizontal (y slope) axes."""
    grid = BodyGrid.covering(half_width_mm, -half_height_mm, half_height_mm, grid_step_mm)
    x, y = grid.coordinates()
    h = 10.0 + x * np.tan(np.radians(tilt_x_deg)) + y * np.tan(np.radians(tilt_y_deg))
    a = np.full_like(x, albedo)
    return {"front": build_height_field(grid, h, a), "back": build_height_field(grid, -h + 20.0, a)}


def vase(grid_step_mm: float = 1.0, seed: int = 0) -> dict[str, HeightField]:
    """A surface of revolution about the vertical axis with bulges and flutes (strong curvature)."""
    grid = BodyGrid.covering(200.0, -240.0, 240.0, grid_step_mm)
    x, y = grid.coordinates()
    radius = 120.0 + 40.0 * np.sin(2 * np.pi * (y + 240.0) / 320.0) + 10.0 * np.cos(2 * np.pi * y / 95.0)
    theta = np.arcsin(np.clip(x / radius, -1, 1))
    radius = radius + 3.0 * np.cos(12.0 * theta)  # flutes
    inside = (np.abs(x) < radius) & (np.abs(y) < 230.0)
    h = np.where(inside, np.sqrt(np.clip(radius**2 - x**2, 0, None)), np.nan)
    a = 0.75 + 0.05 * smooth_noise(x, y, seed, 50.0)
    surfaces = build_height_field(grid, h, a)
    return {"front": surfaces, "back": surfaces}


def relief(grid_step_mm: float = 1.0, seed: int = 0) -> dict[str, HeightField]:
    """A mannequin-like relief: an elliptic dome with bumps, ridges and dimples of 15-60 mm."""
    grid = BodyGrid.covering(300.0, -230.0, 230.0, grid_step_mm)
    x, y = grid.coordinates()
    r2 = (x / 290.0) ** 2 + (y / 220.0) ** 2
    inside = r2 < 1.0
    h = 90.0 * np.sqrt(np.clip(1.0 - r2, 0.0, None))
    rng = np.random.default_rng(seed + 101)
    for _ in range(10):
        cx, cy = rng.uniform(-200, 200), rng.uniform(-150, 150)
        sigma = rng.uniform(15, 60)
        h = h + rng.uniform(-12, 18) * _gauss((x - cx) / sigma, (y - cy) / sigma) * np.sqrt(np.clip(1 - r2, 0, 1))
    h = h + 3.0 * np.sin(x / 14.0) * np.sin(y / 19.0) * np.clip(1 - 1.5 * r2, 0, 1)
    h = np.where(inside, h, np.nan)
    a = 0.7 + 0.08 * smooth_noise(x, y, seed, 80.0)
    surfaces = build_height_field(grid, h, a)
    return {"front": surfaces, "back": surfaces}


SHAPES = {"torso": torso, "plane": plane, "vase": vase, "relief": relief}
