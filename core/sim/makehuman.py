"""Human bodies from MakeHuman's CC0 base mesh and macro targets: the test population.

A body is the base mesh plus a weighted sum of targets, weighted as MakeHuman's macro system
weights them (../shared/data/makehuman/README.md): gender, age, muscle, weight, height and the
ethnic proportions. These bodies were modelled by artists on anthropometric references; no method
of this project was tuned on them (docs/benchmarks.md: the two populations).

Coordinates here are the mesh's, in millimetres: x across the body, y up from the soles, z forward.
The data are read from ../shared/data/makehuman (or $PHOTOPFT_SHARED/data/makehuman); they are never
copied into the repository or the application.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

DECIMETRE_MM = 100.0
BODY_DENSITY_KG_PER_L = 1.01  # whole body, lungs at rest included (Siri's range 1.00-1.10)

# MakeHuman's age parameter at these ages (years): piecewise linear between them
_AGE_KNOTS = ((1.0, 0.0), (11.0, 0.1875), (25.0, 0.5), (90.0, 1.0))
_AGES = ("baby", "child", "young", "old")
_LEVELS3 = ("min", "average", "max")
RACES = ("african", "asian", "caucasian")


def makehuman_dir() -> Path:
    """Where the MakeHuman data are read from: $PHOTOPFT_SHARED/data/makehuman, else ../shared beside the checkout."""
    shared = os.environ.get("PHOTOPFT_SHARED")
    root = Path(shared) if shared else Path(__file__).resolve().parents[3] / "shared"
    return root / "data" / "makehuman"


class MeshDataError(ValueError):
    """The MakeHuman data are missing or not as documented."""


@dataclass(frozen=True)
class Macros:
    """MakeHuman's macro parameters, each 0-1 (ethnic proportions summing to 1)."""

    gender: float  # 0 female, 1 male
    age: float  # 0 = 1 year, 0.1875 = 11, 0.5 = 25, 1 = 90
    muscle: float
    weight: float
    height: float
    african: float = 1 / 3
    asian: float = 1 / 3
    caucasian: float = 1 / 3

    def __post_init__(self) -> None:
        for name in ("gender", "age", "muscle", "weight", "height", *RACES):
            value = getattr(self, name)
            if not (np.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"MakeHuman macro {name} must be within 0-1, got {value}")
        if abs(self.african + self.asian + self.caucasian - 1.0) > 1e-6:
            raise ValueError("MakeHuman's ethnic proportions must sum to 1")


def age_parameter(age_years: float) -> float:
    years, params = zip(*_AGE_KNOTS)
    return float(np.interp(age_years, years, params))


def age_years(age_parameter_value: float) -> float:
    years, params = zip(*_AGE_KNOTS)
    return float(np.interp(age_parameter_value, params, years))


@dataclass(frozen=True)
class MeshData:
    verts_mm: np.ndarray  # (V, 3)
    quads: np.ndarray  # (F, 4), counter-clockwise seen from outside
    targets: dict  # name -> (indices, offsets_mm)
    trunk_weight: np.ndarray  # (V,) skinning weight of the trunk's bones
    arm_weight: np.ndarray  # (V,) of the arms'


@lru_cache(maxsize=2)
def load_mesh_data(folder: str | None = None) -> MeshData:
    path = Path(folder) if folder else makehuman_dir()
    npz = path / "body.npz"
    if not npz.is_file():
        raise MeshDataError(f"{npz}: the MakeHuman body mesh is not there; mesh bodies read it from "
                            f"../shared/data/makehuman (or set PHOTOPFT_SHARED)")
    try:
        with np.load(npz) as data:
            verts = np.asarray(data["verts"], dtype=np.float64) * DECIMETRE_MM
            quads = np.asarray(data["quads"], dtype=np.int64)
            names = {k[2:-2] for k in data.files if k.startswith("t/")}
            targets = {n: (np.asarray(data[f"t/{n}/i"], dtype=np.int64),
                           np.asarray(data[f"t/{n}/d"], dtype=np.float64) * DECIMETRE_MM) for n in names}
            trunk, arm = (np.asarray(data[k], dtype=np.float64) for k in ("trunk_w", "arm_w"))
    except (OSError, KeyError, ValueError) as exc:
        raise MeshDataError(f"{npz}: not the MakeHuman body data described in its README ({exc})") from exc
    if verts.ndim != 2 or verts.shape[1] != 3 or quads.ndim != 2 or quads.shape[1] != 4 \
            or quads.min() < 0 or quads.max() >= len(verts) or trunk.shape != (len(verts),):
        raise MeshDataError(f"{npz}: its arrays do not have the shapes its README gives")
    return MeshData(verts, quads, targets, trunk, arm)


def _pair(value: float, low: str, high: str) -> dict[str, float]:
    return {low: 1.0 - value, high: value}


def _level3(value: float) -> dict[str, float]:
    """min-average on [0, 0.5], average-max on [0.5, 1]."""
    if value <= 0.5:
        return {"min": 1.0 - 2.0 * value, "average": 2.0 * value}
    return {"average": 2.0 - 2.0 * value, "max": 2.0 * value - 1.0}


def _age_weights(age: float) -> dict[str, float]:
    edges = (0.0, 0.1875, 0.5, 1.0)
    for k in range(3):
        if age <= edges[k + 1]:
            share = (age - edges[k]) / (edges[k + 1] - edges[k])
            return {_AGES[k]: 1.0 - share, _AGES[k + 1]: share}
    return {"old": 1.0}


def target_weights(m: Macros) -> dict[str, float]:
    """Each target's weight for these macros, as MakeHuman's macro modifiers give them."""
    genders = _pair(m.gender, "female", "male")
    ages = _age_weights(m.age)
    muscles = {f"{k}muscle": w for k, w in _level3(m.muscle).items()}
    weights = {f"{k}weight": w for k, w in _level3(m.weight).items()}
    heights = ({"minheight": 1.0 - 2.0 * m.height} if m.height < 0.5 else {"maxheight": 2.0 * m.height - 1.0})
    out: dict[str, float] = {}
    for g, wg in genders.items():
        for a, wa in ages.items():
            for race in RACES:
                out[f"{race}-{g}-{a}"] = out.get(f"{race}-{g}-{a}", 0.0) + getattr(m, race) * wg * wa
            for mu, wm in muscles.items():
                for we, ww in weights.items():
                    w = wg * wa * wm * ww
                    out[f"universal-{g}-{a}-{mu}-{we}"] = w
                    for h, wh in heights.items():
                        out[f"height/{g}-{a}-{mu}-{we}-{h}"] = w * wh
    return {k: v for k, v in out.items() if v > 0.0}


def body_vertices(m: Macros, data: MeshData) -> np.ndarray:
    """The mesh's vertices (mm) for these macros, soles at y = 0."""
    verts = data.verts_mm.copy()
    for name, weight in target_weights(m).items():
        if name in data.targets:  # the targets that move nothing are not shipped
            index, offsets = data.targets[name]
            verts[index] += weight * offsets
    verts[:, 1] -= verts[:, 1].min()
    return verts


def triangles(quads: np.ndarray) -> np.ndarray:
    """Each quad as two triangles with its winding."""
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def closed_volume_mm3(verts: np.ndarray, tris: np.ndarray) -> float:
    """The volume a closed, outward-wound triangle mesh encloses (divergence theorem)."""
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


@dataclass(frozen=True)
class MeshBody:
    """One subject of the mesh population: macros drawn, and the measures read off the mesh."""

    name: str
    seed: int
    macros: Macros
    sex: str
    age_years: float
    height_cm: float  # the mesh's stature
    weight_kg: float  # the mesh's volume at BODY_DENSITY_KG_PER_L
    skin_type: int  # Fitzpatrick I-VI
    sheen: float  # the skin's surface reflection
    bucket_share: float  # the rib cage's sideways motion per forward motion
    chest_share: dict  # manoeuvre -> the rib cage's share of the volume ("tidal", "vc", "forced")
    abdomen_lag_s: float

    @property
    def bmi(self) -> float:
        return self.weight_kg / (self.height_cm / 100.0) ** 2

    def as_json(self) -> str:
        out = asdict(self)
        out.update(kind="makehuman mesh", arms="away")  # MakeHuman's rest pose holds them 45 degrees down
        return json.dumps(out)

    def vertices_mm(self, data: MeshData | None = None) -> np.ndarray:
        return body_vertices(self.macros, data or load_mesh_data())


def _draw_age(rng: np.random.Generator) -> float:
    """Children 8-17 one in six, adults 18-64 three in five, elderly 65-85 the rest."""
    group = rng.random()
    if group < 1 / 6:
        return float(rng.uniform(8.0, 17.0))
    if group < 1 / 6 + 0.6:
        return float(rng.uniform(18.0, 64.0))
    return float(rng.uniform(65.0, 85.0))


def mesh_body(seed: int, data: MeshData | None = None) -> MeshBody:
    """The test population's subject `seed`: sex, age, build, stature and skin drawn; thin to heavy
    (MakeHuman weight 0-1, one in five above 0.8: its heaviest adult has a BMI of about 23 by the
    mesh's volume, docs/simulator.md); statures within MakeHuman's height 0.3-0.7 (an adult man
    158-202 cm)."""
    data = data or load_mesh_data()
    rng = np.random.default_rng(seed + 7919)
    sex = "male" if rng.random() < 0.5 else "female"
    years = _draw_age(rng)
    weight = float(rng.uniform(0.8, 1.0)) if rng.random() < 0.2 else float(rng.uniform(0.0, 0.8))
    races = rng.dirichlet(np.ones(3))
    macros = Macros(gender=1.0 if sex == "male" else 0.0, age=age_parameter(years),
                    muscle=float(rng.uniform(0.25, 0.75)), weight=weight, height=float(rng.uniform(0.3, 0.7)),
                    african=float(races[0]), asian=float(races[1]), caucasian=1.0 - float(races[0]) - float(races[1]))
    verts = body_vertices(macros, data)
    stature_mm = float(np.ptp(verts[:, 1]))
    volume_l = closed_volume_mm3(verts, triangles(data.quads)) * 1e-6
    tidal = float(rng.uniform(0.25, 0.55))
    vc = float(rng.uniform(0.45, 0.75))
    return MeshBody(name=f"mesh-{seed}", seed=seed, macros=macros, sex=sex, age_years=round(years, 1),
                    height_cm=round(stature_mm / 10.0, 1), weight_kg=round(volume_l * BODY_DENSITY_KG_PER_L, 1),
                    skin_type=int(rng.integers(1, 7)), sheen=float(rng.uniform(0.0, 0.3)),
                    bucket_share=float(rng.uniform(0.3, 1.0)),
                    chest_share={"tidal": tidal, "vc": vc,
                                 "forced": float(np.clip(vc + rng.uniform(-0.1, 0.1), 0.35, 0.85))},
                    abdomen_lag_s=float(rng.uniform(0.0, 0.15)))
