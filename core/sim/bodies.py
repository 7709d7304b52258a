"""A parametric human trunk: bodies of many shapes for the simulated population.

A body is given by the measures an anthropometrist takes (stature, mass, biacromial, chest,
waist and hip breadths, chest and waist depths) and a few shape traits (breasts, abdominal
protrusion, shoulder slope, arms close to the trunk or held away, kyphosis, lordosis). The
trunk is a stack of superelliptic cross-sections through those measures; the front and back
height fields are its two halves about the mid-coronal plane, with the arms as cylinders that
hide the trunk's sides when they hang close.

Breathing moves three modes, as the respiratory physiology of the chest wall has it (Konno and
Mead 1967; Kenyon et al. 1997): the rib cage (left and right halves) expands forward and
sideways, the abdomen mostly forward; the back moves little. A mode's volume is what it sweeps
on the trunk itself, including where an arm hides it (`HeightField.swept_mode_volumes_mm3`): the
lungs do not know where the arms are.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator

from core.sim.surfaces import BodyGrid, HeightField, build_height_field
from core.sim.textures import body_albedo

ARMS = ("away", "close")
SEXES = ("male", "female")
MAX_LATERAL_SLOPE = 4.0  # the sides' lateral expansion, in mm of height per mm of sideways motion, at most
# How far each side of the trunk moves out at unit amplitude of a mode (1 mm forward at the front's middle)
LATERAL_SIDE_MM = {"rib_cage": 0.5, "abdomen": 0.15}


# The ranges a body's fields must lie in (Body refuses others; random_body draws within them).
BODY_RANGES = {"age_years": (5, 100), "height_cm": (100, 215), "weight_kg": (15, 220),
               "shoulder_width_mm": (220, 520), "shoulder_slope_deg": (0, 40), "chest_width_mm": (180, 480),
               "waist_width_mm": (160, 520), "hip_width_mm": (180, 560), "chest_depth_mm": (130, 400),
               "waist_depth_mm": (110, 450), "breast_mm": (0, 120), "abdominal_protrusion_mm": (0, 150),
               "arm_radius_mm": (25, 80), "kyphosis_mm": (0, 60), "lordosis_mm": (0, 60)}


@dataclass(frozen=True)
class Body:
    """One subject's trunk. Lengths in millimetres; y runs down from the xiphoid."""

    name: str = "average-man"
    sex: str = "male"
    age_years: float = 40.0
    height_cm: float = 176.0
    weight_kg: float = 80.0
    shoulder_width_mm: float = 400.0  # biacromial breadth
    shoulder_slope_deg: float = 20.0  # from the neck to the acromion, below the horizontal
    chest_width_mm: float = 320.0  # breadth at the nipples
    waist_width_mm: float = 300.0
    hip_width_mm: float = 350.0
    chest_depth_mm: float = 245.0  # front to back at the nipples, without breasts
    waist_depth_mm: float = 225.0
    breast_mm: float = 0.0  # how far each breast stands out of the chest wall
    abdominal_protrusion_mm: float = 15.0  # the belly in front of the waist's own curve
    arms: str = "away"
    arm_radius_mm: float = 45.0
    kyphosis_mm: float = 0.0  # the upper back's extra rounding
    lordosis_mm: float = 20.0  # the lumbar hollow

    def __post_init__(self) -> None:
        if self.sex not in SEXES:
            raise ValueError(f"body {self.name!r}: sex must be male or female, got {self.sex!r}")
        if self.arms not in ARMS:
            raise ValueError(f"body {self.name!r}: arms must be 'away' or 'close', got {self.arms!r}")
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float | int) and not np.isfinite(value):
                raise ValueError(f"body {self.name!r}: {f.name} must be finite")
        for key, (lo, hi) in BODY_RANGES.items():
            value = getattr(self, key)
            if not lo <= value <= hi:
                raise ValueError(f"body {self.name!r}: {key} {value:g} outside {lo}-{hi}")
        if self.chest_width_mm > self.shoulder_width_mm + 40:
            raise ValueError(f"body {self.name!r}: chest_width_mm {self.chest_width_mm:g} is wider than the shoulders "
                             f"({self.shoulder_width_mm:g} mm) allow")

    @property
    def bmi(self) -> float:
        return self.weight_kg / (self.height_cm / 100.0) ** 2

    @property
    def stature_scale(self) -> float:
        """Lengths along the trunk against an adult of 176 cm."""
        return self.height_cm / 176.0

    def as_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)


def anthropometric_body(name: str, sex: str, age_years: float, height_cm: float, weight_kg: float,
                        **traits: float | str) -> Body:
    """A body with breadths and depths that follow stature and BMI as adult and child surveys do
    (ANSUR II means scaled; breadth grows with BMI^0.5, depth with BMI^0.8), traits as given."""
    if sex not in SEXES:
        raise ValueError(f"body {name!r}: sex must be male or female, got {sex!r}")
    s = height_cm / (176.0 if sex == "male" else 163.0)
    bmi = weight_kg / (height_cm / 100.0) ** 2
    child = age_years < 13
    reference_bmi = 17.0 if child else 24.5
    breadth = (bmi / reference_bmi) ** 0.5
    depth = (bmi / reference_bmi) ** 0.8
    if sex == "male":
        base = dict(shoulder_width_mm=400 * s, chest_width_mm=318 * s * breadth, waist_width_mm=300 * s * breadth,
                    hip_width_mm=350 * s * breadth, chest_depth_mm=245 * s * depth, waist_depth_mm=225 * s * depth,
                    breast_mm=0.0, arm_radius_mm=45 * s * breadth)
    else:
        base = dict(shoulder_width_mm=360 * s, chest_width_mm=290 * s * breadth, waist_width_mm=272 * s * breadth,
                    hip_width_mm=370 * s * breadth, chest_depth_mm=215 * s * depth, waist_depth_mm=205 * s * depth,
                    breast_mm=0.0 if child else 40.0 * breadth, arm_radius_mm=41 * s * breadth)
    if child:
        base["shoulder_width_mm"] *= 0.92
        base["chest_depth_mm"] *= 0.95
    base["abdominal_protrusion_mm"] = float(np.clip(6.0 * (bmi - reference_bmi) + 10.0, 0.0, 120.0))
    base["shoulder_width_mm"] = max(base["shoulder_width_mm"], base["chest_width_mm"] - 30.0)
    # the smallest children's breadths scaled so fall just below the ranges Body holds (population
    # seed 1, subject 11: chest 176 mm); they are taken at the ranges' edges
    base = {k: float(np.clip(v, *BODY_RANGES[k])) for k, v in base.items()}
    base.update(traits)
    return Body(name=name, sex=sex, age_years=age_years, height_cm=height_cm, weight_kg=weight_kg, **base)


PRESETS: dict[str, Body] = {b.name: b for b in (
    anthropometric_body("average-man", "male", 40, 176, 80),
    anthropometric_body("average-woman", "female", 40, 163, 65),
    anthropometric_body("obese-man", "male", 50, 175, 120, lordosis_mm=10.0),
    anthropometric_body("obese-woman", "female", 45, 162, 100, breast_mm=70.0),
    anthropometric_body("thin-woman", "female", 25, 170, 50, breast_mm=20.0),
    anthropometric_body("child", "male", 8, 128, 26, lordosis_mm=15.0),
    anthropometric_body("girl", "female", 11, 145, 36, lordosis_mm=15.0),
    anthropometric_body("elderly-kyphotic", "female", 78, 156, 60, kyphosis_mm=35.0, shoulder_slope_deg=26.0),
    anthropometric_body("athletic-man", "male", 28, 182, 84, shoulder_width_mm=445.0, abdominal_protrusion_mm=0.0,
                        waist_width_mm=280.0),
    anthropometric_body("arms-close", "male", 40, 176, 80, arms="close"),
)}


def random_body(seed: int) -> Body:
    """A body drawn within plausible ranges: sex, age 6-85, stature and BMI by age and sex,
    arms close or away, kyphosis in the old; the seed picks it."""
    rng = np.random.default_rng(seed + 9001)
    sex = SEXES[int(rng.integers(2))]
    age = float(rng.choice([rng.uniform(6, 12.9), rng.uniform(18, 85)], p=[0.2, 0.8]))
    if age < 13:
        height = float(np.clip(rng.normal(115 + 5.5 * (age - 6), 6), 105, 165))
        bmi = float(np.clip(rng.lognormal(np.log(16.5), 0.12), 13.5, 24))
    else:
        height = float(np.clip(rng.normal(176 if sex == "male" else 163, 7) - 0.08 * max(0.0, age - 50), 148, 200))
        bmi = float(np.clip(rng.lognormal(np.log(26.0), 0.17), 17.5, 42))
    weight = bmi * (height / 100.0) ** 2
    traits: dict[str, float | str] = {"arms": ARMS[int(rng.integers(2))],
                                      "shoulder_slope_deg": float(np.clip(rng.normal(20, 4), 8, 32)),
                                      "lordosis_mm": float(rng.uniform(8, 30))}
    if age > 65:
        traits["kyphosis_mm"] = float(rng.uniform(0, 35))
    body = anthropometric_body(f"random-{seed}", sex, round(age, 1), round(height, 1), round(weight, 1), **traits)
    jitter = {k: getattr(body, k) * float(np.clip(rng.normal(1, 0.05), 0.88, 1.12))
              for k in ("chest_width_mm", "waist_width_mm", "hip_width_mm", "chest_depth_mm", "waist_depth_mm")}
    if body.breast_mm > 0:
        jitter["breast_mm"] = body.breast_mm * float(rng.uniform(0.5, 1.6))
    jitter["chest_width_mm"] = min(jitter["chest_width_mm"], body.shoulder_width_mm + 30.0)
    return replace(body, **{k: float(np.clip(v, *BODY_RANGES[k])) for k, v in jitter.items()})


def body_from_toml(path: str | Path) -> Body:
    """A body file: `[body]` with any field of `Body` (the rest from `anthropometric_body` of its
    sex, age, height and weight)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path}: not a readable body file ({exc})") from exc
    table = data.get("body")
    if not isinstance(table, dict):
        raise ValueError(f"{path}: no [body] table")
    known = {f.name for f in fields(Body)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ValueError(f"{path}: unknown key {unknown[0]!r} in [body]; known: {', '.join(sorted(known))}")
    try:
        core = {k: table.pop(k) for k in ("sex", "age_years", "height_cm", "weight_kg") if k in table}
        core.setdefault("sex", "male")
        core.setdefault("age_years", 40.0)
        core.setdefault("height_cm", 176.0 if core["sex"] == "male" else 163.0)
        core.setdefault("weight_kg", 24.5 * (core["height_cm"] / 100.0) ** 2)
        return anthropometric_body(table.pop("name", path.stem), core["sex"], float(core["age_years"]),
                                   float(core["height_cm"]), float(core["weight_kg"]), **table)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {exc}") from exc


def body_named(spec: str, seed: int = 1):
    """`random` (drawn with `seed`), a preset's name, a body TOML file, or `mesh:N`: the mesh
    population's subject N (core/sim/makehuman.py)."""
    if spec == "random":
        return random_body(seed)
    if spec.startswith("mesh:"):
        from core.sim.makehuman import mesh_body

        try:
            number = int(spec[len("mesh:"):])
        except ValueError:
            raise ValueError(f"unknown body {spec!r}: mesh:N takes a whole number N") from None
        return mesh_body(number)
    if spec in PRESETS:
        return PRESETS[spec]
    if spec.endswith(".toml"):
        return body_from_toml(spec)
    raise ValueError(f"unknown body {spec!r}: random, mesh:N, a .toml file or one of {', '.join(PRESETS)}")


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _gauss(*terms: np.ndarray) -> np.ndarray:
    return np.exp(-0.5 * sum(t * t for t in terms))


# The trunk's levels for an adult of 176 cm, mm down from the xiphoid; other statures in proportion.
_LEVELS_MM = {"neck": -265.0, "acromion": -215.0, "axilla": -135.0, "nipples": -85.0, "costal_margin": 70.0,
              "waist": 150.0, "navel": 175.0, "waistband": 250.0, "hips": 340.0}


@dataclass(frozen=True)
class _Landmarks:
    """Heights (y, mm, down from the xiphoid) of the trunk's levels for one stature."""

    s: float
    neck: float
    acromion: float
    axilla: float
    nipples: float
    costal_margin: float
    waist: float
    navel: float
    waistband: float
    hips: float

    @classmethod
    def of(cls, stature_scale: float) -> "_Landmarks":
        return cls(stature_scale, **{name: y * stature_scale for name, y in _LEVELS_MM.items()})


def _profile(y: np.ndarray, knots: list[tuple[float, float]]) -> np.ndarray:
    ys, vs = zip(*knots)
    return PchipInterpolator(ys, vs)(np.clip(y, ys[0], ys[-1]))


def _superellipse(x: np.ndarray, half_width: np.ndarray, depth: np.ndarray, exponent: float) -> np.ndarray:
    s = np.clip(np.abs(x) / half_width, 0.0, 1.0)
    return np.where(np.abs(x) < half_width, depth * (1.0 - s**exponent) ** (1.0 / exponent), np.nan)


def _smooth_union(a: np.ndarray, b: np.ndarray, k_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Smooth maximum of two heights (NaN = absent) and the weight of `a` in it (its derivative)."""
    a0 = np.where(np.isfinite(a), a, -1e9)
    b0 = np.where(np.isfinite(b), b, -1e9)
    hi = np.maximum(a0, b0)
    union = hi + k_mm * np.log1p(np.exp(-np.abs(a0 - b0) / k_mm))
    weight = 1.0 / (1.0 + np.exp(np.clip((b0 - a0) / k_mm, -50, 50)))
    return np.where(hi > -1e8, union, np.nan), np.where(np.isfinite(a), weight, 0.0)


def body_surfaces(body: Body, grid_step_mm: float = 1.0, clothing: str = "skin", seed: int = 0,
                  skin_albedo: float = 0.45, specular: float = 0.0, shininess: float = 30.0,
                  arm_motion: bool = False, widening: bool = False) -> dict[str, HeightField]:
    """Front and back height fields of a body's trunk and arms, with breathing modes
    (chest_left, chest_right, abdomen; 1 mm peak forward motion of the front at unit amplitude)
    and, with `arm_motion`, a mode "arms": both arms 1 mm outwards (no volume: not breathing).

    The sides' lateral expansion is, with `widening`, the trunk itself stretched sideways (its
    silhouette widens, the arms move out with its sides: `HeightField.stretch_modes`); without, each
    mode's height change -e x dh/dx, cut at MAX_LATERAL_SLOPE near the sides, where a height field
    cannot move sideways (the silhouette stays put)."""
    s = body.stature_scale
    lm = _Landmarks.of(s)
    half_span = max(body.shoulder_width_mm, body.hip_width_mm) / 2 + 2.6 * body.arm_radius_mm + 40.0
    grid = BodyGrid.covering(half_span, lm.neck - 70.0 * s, lm.hips + 60.0 * s, grid_step_mm)
    x, y = grid.coordinates()

    chest_w, waist_w, hip_w = body.chest_width_mm / 2, body.waist_width_mm / 2, body.hip_width_mm / 2
    shoulder_w = body.shoulder_width_mm / 2
    half_width = _profile(y, [(lm.neck, 0.9 * chest_w), (lm.axilla, 1.02 * chest_w), (lm.nipples, chest_w),
                              (lm.costal_margin, 0.5 * (chest_w + waist_w)), (lm.waist, waist_w),
                              (lm.waistband, 0.5 * (waist_w + hip_w)), (lm.hips, hip_w)])
    neck_w = 0.16 * body.shoulder_width_mm
    slope = np.tan(np.radians(body.shoulder_slope_deg))
    top = lm.acromion - (shoulder_w - np.clip(np.abs(x), neck_w, shoulder_w)) * slope
    top = np.where(np.abs(x) < neck_w, lm.neck - 40.0 * s, top)

    chest_d, waist_d = body.chest_depth_mm / 2, body.waist_depth_mm / 2
    front_depth = _profile(y, [(lm.neck, 0.55 * chest_d), (lm.axilla, 0.92 * chest_d), (lm.nipples, chest_d),
                               (lm.costal_margin, 0.5 * (chest_d + waist_d)), (lm.waist, waist_d),
                               (lm.hips, 0.95 * waist_d)])
    back_depth = _profile(y, [(lm.neck, 0.6 * chest_d), (lm.axilla, 0.95 * chest_d), (lm.nipples, 0.95 * chest_d),
                              (lm.waist, 0.9 * waist_d), (lm.hips, 1.05 * waist_d)])
    back_depth = back_depth + body.kyphosis_mm * _gauss((y - lm.axilla) / (70.0 * s))
    back_depth = back_depth - body.lordosis_mm * _gauss((y - lm.waistband) / (60.0 * s))
    front_depth = front_depth - 0.3 * body.kyphosis_mm * _gauss((y - lm.axilla) / (60.0 * s))

    rounding_mm = 30.0 * s
    below_top = np.clip((y - top) / rounding_mm, 0.0, 1.0)
    shoulders = np.sqrt(below_top * (2.0 - below_top))
    on_trunk = (np.abs(x) < half_width) & (y > top)
    trunk_front = np.where(on_trunk, _superellipse(x, half_width, front_depth, 2.3) * shoulders, np.nan)
    trunk_back = np.where(on_trunk, _superellipse(x, half_width, back_depth, 2.8) * shoulders, np.nan)
    across = np.where(on_trunk, np.clip(1.0 - (x / half_width) ** 2, 0.0, 1.0), 0.0)

    ax = np.abs(x)
    features_front = (
        -3.0 * _gauss(x / 14.0, (y - lm.nipples) / (90.0 * s))  # sternum
        + 3.5 * _gauss((y - lm.neck - 45.0 * s - 0.12 * ax) / 9.0) * (ax < 0.9 * shoulder_w)  # clavicles
        + 3.0 * _gauss((y - lm.costal_margin + 20.0 * s - 0.35 * ax) / 12.0) * (ax < 0.8 * chest_w)  # costal margin
        + body.abdominal_protrusion_mm * _gauss(x / (0.55 * waist_w), (y - lm.navel) / (95.0 * s))
        - 5.0 * _gauss(x / 7.0, (y - lm.navel) / 7.0)  # navel
    )
    if body.sex == "male" or body.breast_mm < 5:
        features_front = features_front + 8.0 * _gauss((ax - 0.3 * chest_w) / (0.2 * chest_w),
                                                       (y - lm.nipples + 20.0 * s) / (45.0 * s))  # pectorals
    if body.breast_mm > 0:
        sag = np.clip((y - lm.nipples) / (60.0 * s), -1.5, 1.5)
        breast = body.breast_mm * _gauss((ax - 0.42 * chest_w) / (0.26 * chest_w),
                                         (y - lm.nipples - 15.0 * s) / ((55.0 + 15.0 * sag) * s))
        features_front = features_front + breast
    features_back = (
        9.0 * _gauss((ax - 0.3 * body.shoulder_width_mm) / (0.15 * body.shoulder_width_mm),
                     (y - lm.axilla) / (70.0 * s))  # scapulae
        - 5.0 * _gauss(x / 12.0) * (y > lm.neck)  # spine groove
    )
    trunk_front = trunk_front + features_front * across ** 0.5
    trunk_back = trunk_back + features_back * across ** 0.5

    arm_front, arm_back = _arms(body, x, y, lm, half_width, front_depth)
    front_h, front_w = _smooth_union(trunk_front, arm_front, 3.0)
    back_h, back_w = _smooth_union(trunk_back, arm_back, 3.0)

    modes_front, modes_back, stretch = _breathing_modes(x, y, lm, half_width, trunk_front, trunk_back, on_trunk,
                                                        grid.step, widening)
    swept = tuple(float(np.sum(modes_front[n] + modes_back[n], dtype=np.float64)) * grid.cell_area_mm2
                  for n in modes_front)
    seen_front = {n: m * front_w for n, m in modes_front.items()}
    seen_back = {n: m * back_w for n, m in modes_back.items()}
    if arm_motion:
        # an arm moved outwards by e changes its height by -e sign(x) dh/dx, where it is on top
        for seen, arm, weight in ((seen_front, arm_front, front_w), (seen_back, arm_back, back_w)):
            outwards = -np.sign(x) * np.gradient(np.nan_to_num(arm), grid.step, axis=1)
            seen["arms"] = np.where(np.isfinite(arm), np.clip(outwards, -MAX_LATERAL_SLOPE, MAX_LATERAL_SLOPE),
                                    0.0) * (1.0 - weight)
        swept = swept + (0.0,)

    on_arm_front = np.isfinite(arm_front) & (front_w < 0.5)
    on_arm_back = np.isfinite(arm_back) & (back_w < 0.5)
    a_front = body_albedo(x, y, body, lm, half_width, top, clothing, seed, skin_albedo, on_arm_front, back=False)
    a_back = body_albedo(x, y, body, lm, half_width, top, clothing, seed + 1, skin_albedo, on_arm_back, back=True)
    front = build_height_field(grid, front_h, a_front, seen_front, specular=specular, shininess=shininess)
    back = build_height_field(grid, back_h, a_back, seen_back, specular=specular, shininess=shininess)
    front_swept = tuple(float(np.sum(m, dtype=np.float64)) * grid.cell_area_mm2 for m in modes_front.values())
    front_swept = front_swept + (0.0,) * (len(swept) - len(front_swept))
    back_swept = tuple(v - f for v, f in zip(swept, front_swept))
    out = {"front": replace(front, swept_mode_volumes_mm3=front_swept),
           "back": replace(back, swept_mode_volumes_mm3=back_swept)}
    if stretch is not None:
        still = np.zeros((grid.ny, 2))  # the arms' mode stretches nothing
        stretch_modes = np.stack([stretch.get(n, still) for n in front.mode_names])
        for name, trunk, modes in (("front", trunk_front, modes_front), ("back", trunk_back, modes_back)):
            out[name] = replace(out[name], stretch_modes=stretch_modes, trunk_half_width_mm=half_width[:, 0].copy(),
                                section_area_mm2=_row_side_areas(np.where(on_trunk, np.nan_to_num(trunk), 0.0), x,
                                                                 grid.step),
                                mode_section_area_mm2=np.stack([
                                    _row_side_areas(modes[n], x, grid.step) if n in modes
                                    else still for n in front.mode_names]))
    return out


def _row_side_areas(height_mm: np.ndarray, x: np.ndarray, step: float) -> np.ndarray:
    """(rows, 2): the area under a height on each grid row's side x > 0 and x < 0 (mm^2), the middle
    column shared half and half."""
    weight = np.where(x > 0, 1.0, np.where(x < 0, 0.0, 0.5))
    return np.stack([np.sum(height_mm * weight, axis=1), np.sum(height_mm * (1.0 - weight), axis=1)], axis=1) * step


def _arms(body: Body, x: np.ndarray, y: np.ndarray, lm: _Landmarks, half_width: np.ndarray,
          front_depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The upper arms and forearms as cylinders hanging from the shoulders; close arms overlap the
    trunk's sides by a third of their radius, arms held away leave a gap that opens downwards."""
    r = body.arm_radius_mm
    at_shoulder = body.shoulder_width_mm / 2 - 0.3 * r
    drop = np.clip(y - lm.acromion, 0.0, None)
    if body.arms == "close":
        beside = half_width + 0.67 * r
        centre = np.maximum(at_shoulder - drop * 0.05, beside)
    else:
        centre = np.maximum(at_shoulder + drop * np.tan(np.radians(12.0)), half_width + 0.67 * r)
    forward = 0.12 * front_depth
    radius = r * (1.0 - 0.25 * _smoothstep(lm.costal_margin, lm.waistband, y))  # forearm thinner than upper arm
    out = []
    for sign in (-1.0, 1.0):
        across = np.clip(1.0 - ((x - sign * centre) / radius) ** 2, 0.0, None)
        present = (across > 0) & (y > lm.acromion + 0.2 * r)
        cap = np.sqrt(np.clip((y - lm.acromion + r) / (1.2 * r), 0.0, 1.0))
        out.append(np.where(present, radius * np.sqrt(across) * cap, np.nan))
    section = np.fmax(out[0], out[1])
    return section + forward, section - forward


def _breathing_modes(x: np.ndarray, y: np.ndarray, lm: _Landmarks, half_width: np.ndarray,
                     trunk_front: np.ndarray, trunk_back: np.ndarray, on_trunk: np.ndarray, step: float,
                     widening: bool = False
                     ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, np.ndarray] | None]:
    """Rib cage (left, right) and abdomen: forward motion tapering to the sides, plus the sides'
    lateral expansion, a sideways stretch x -> x (1 + e) by LATERAL_SIDE_MM / half width at unit
    amplitude. Without `widening` the stretch is each mode's height change -e x dh/dx (cut at
    MAX_LATERAL_SLOPE) and the third value is None; with it the modes move along the axis only and
    the third gives each mode's stretch of every grid row's two sides (x > 0, x < 0), (rows, 2)."""
    s = lm.s
    rib_cage = _smoothstep(lm.acromion, lm.axilla, y) * (1.0 - _smoothstep(lm.costal_margin - 40 * s,
                                                                          lm.waist, y))
    abdomen = _smoothstep(lm.costal_margin - 20 * s, lm.waist - 10 * s, y) * (1.0 - _smoothstep(lm.navel + 40 * s,
                                                                                                lm.hips, y))
    forward = np.where(on_trunk, np.clip(1.0 - (x / half_width) ** 2, 0.0, 1.0), 0.0)

    def lateral(h: np.ndarray) -> np.ndarray:
        hx = np.gradient(np.nan_to_num(h), step, axis=1)
        stretch = np.clip(-(x / half_width) * hx, 0.0, MAX_LATERAL_SLOPE)
        return np.where(on_trunk & np.isfinite(h), stretch, 0.0)

    lat_front, lat_back = (0.0, 0.0) if widening else (lateral(trunk_front), lateral(trunk_back))
    left = 1.0 / (1.0 + np.exp(-x / 25.0))  # the subject's left is the front image's right
    side = LATERAL_SIDE_MM
    rc_front = rib_cage * (forward + side["rib_cage"] * lat_front)
    rc_back = rib_cage * (0.25 * forward + side["rib_cage"] * lat_back)
    ab_front = abdomen * (forward + side["abdomen"] * lat_front)
    ab_back = abdomen * (0.05 * forward + side["abdomen"] * lat_back)
    front = {"chest_left": rc_front * left, "chest_right": rc_front * (1 - left), "abdomen": ab_front}
    back = {"chest_left": rc_back * left, "chest_right": rc_back * (1 - left), "abdomen": ab_back}
    if not widening:
        return front, back, None
    per_row = 1.0 / half_width[:, 0]
    rc, ab = side["rib_cage"] * rib_cage[:, 0] * per_row, side["abdomen"] * abdomen[:, 0] * per_row
    zero = np.zeros_like(rc)
    stretch = {"chest_left": np.stack([rc, zero], axis=1), "chest_right": np.stack([zero, rc], axis=1),
               "abdomen": np.stack([ab, ab], axis=1)}
    return front, back, stretch
