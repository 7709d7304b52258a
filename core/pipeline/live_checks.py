"""The checks `photopft process` makes before it gives an optical volume, made as the maps come in,
for the live view: the operator learns during the session, not from the report, that the skin or
the lights do not follow the light model (a sheen, reflectance_refusal) or that the two heads' maps
are bent against each other (core/pipeline/quality.py, bend_refusal), and can act (polarising filters,
a towel on oily skin, the rig's calibration).

Both look at a map of each head's stream every LOOK_INTERVAL_S (`process`: every SURVEY_INTERVAL_S)
and take the median of what the last WINDOW_S gave, where `process` takes the whole session's."""

from __future__ import annotations

import collections
import threading

import numpy as np

from core.limits import Refusal
from core.pipeline.quality import bend_refusal, reflectance_refusal
from core.volume.sides import sides_tilt

# A look costs a side profile and the sheen's fit, a few ms. Until 2026-11-27 it cost a map at the
# photometric fit's own distance: at scale 1 the live view made 6.0 maps/s a head without looks, 5.1 with
# a look a second, 5.3-5.5 with one every 2 s (`photopft bench gui --scale 1 --seconds 20 --no-record --loop 11`)
LOOK_INTERVAL_S = 2.0
WINDOW_S = 10.0  # five looks a head: one map's verdict is not the subject's


class LiveOpticalChecks:
    """Each head's thread tells it, every LOOK_INTERVAL_S (`due`), its map's sheen
    (`add_sheen`, core/reconstruction/reflectance.py) and side profile (`add_profile`,
    core/volume/sides.py side_profile_mm); `refusal` says why the optical volume would be refused
    now, or None."""

    def __init__(self, heads: list[str]) -> None:
        self._heads = list(heads)
        self._lock = threading.Lock()
        self._last_look: dict[str, float] = {}
        self._sheen: dict[str, collections.deque] = {h: collections.deque() for h in heads}
        self._newest_profile: dict[str, tuple[float, tuple[np.ndarray, np.ndarray]]] = {}
        self._tilts: collections.deque = collections.deque()

    def due(self, head: str, t_s: float) -> bool:
        """Whether the head's map at t_s is to be looked at (then it counts as looked at)."""
        with self._lock:
            last = self._last_look.get(head)
            if last is not None and 0.0 <= t_s - last < LOOK_INTERVAL_S:
                return False
            self._last_look[head] = t_s
            return True

    def add_sheen(self, head: str, t_s: float, sheen: float) -> None:
        with self._lock:
            self._sheen[head].append((t_s, float(sheen)))
            self._forget(t_s)

    def add_profile(self, head: str, t_s: float, profile: tuple[np.ndarray, np.ndarray]) -> None:
        """A head's side profile; paired with the other head's newest one if that lies within
        LOOK_INTERVAL_S (two heads only)."""
        with self._lock:
            self._newest_profile[head] = (t_s, profile)
            others = [self._newest_profile[h] for h in self._heads if h != head and h in self._newest_profile]
            if len(self._heads) == 2 and others and abs(others[0][0] - t_s) <= LOOK_INTERVAL_S:
                other = others[0][1]
                front, back = (profile, other) if head == self._heads[0] else (other, profile)
                self._tilts.append((t_s, sides_tilt(front, back)))
            self._forget(t_s)

    def _forget(self, now_s: float) -> None:
        for series in (*self._sheen.values(), self._tilts):
            while series and series[0][0] < now_s - WINDOW_S:
                series.popleft()

    def clear(self) -> None:
        """Forget everything (a replay moved: its time runs afresh)."""
        with self._lock:
            self._last_look.clear()
            self._newest_profile.clear()
            for series in (*self._sheen.values(), self._tilts):
                series.clear()

    @property
    def checked(self) -> bool:
        """Whether the last WINDOW_S gave anything to judge by."""
        with self._lock:
            return any(self._sheen.values()) or bool(self._tilts)

    def refusal(self) -> Refusal | None:
        """Why the optical volume would be refused now, or None."""
        with self._lock:
            sheen = {h: float(np.median([o for _, o in s])) for h, s in self._sheen.items() if s}
            tilts = np.array([t for _, t in self._tilts], dtype=float)
        return reflectance_refusal(sheen) or bend_refusal(tilts)
