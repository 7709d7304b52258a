"""The checks `photopft process` makes before it gives an optical volume, made as the maps come in,
for the live view: the operator learns during the session, not from the report, that the skin or
the lights do not follow the light model (a sheen, reflectance_refusal), that the two heads' maps are bent
against each other (core/volume/sides.py, bend_refusal), or that the trunk's sides move with the
breathing (core/volume/metric.py, reference_refusal) or that its silhouettes widen as it breathes
(withheld_for_flanks: VC, FVC, FEV1 and PEF not given, the tidal volume too where the breaths would
lose over 50 mL to the flanks), and can act (polarising filters, a towel on
oily skin, the rig's calibration, the arms held away).

The first two look at a map of each head's stream every LOOK_INTERVAL_S (`process`: every
SURVEY_INTERVAL_S) and take the median of what the last WINDOW_S gave, where `process` takes the
whole session's. The third compares the live volume referred to the sides and to the top of the
view over the last REFERENCE_WINDOW_S, every map; the fourth the two heads' silhouette widths
against the volume over the same window."""

from __future__ import annotations

import collections
import threading

import numpy as np

from core.reconstruction.process import reflectance_refusal
from core.volume.metric import (MIN_WIDENING_SPAN_S, flank_refusal, flank_share, reference_refusal,
                                reference_slope, silhouette_widening, tidal_flank_loss)
from core.volume.sides import bend_refusal, sides_tilt

# A look costs a side profile and the sheen's fit, a few ms. Until 2026-11-27 it cost a map at the
# photometric fit's own distance: at scale 1 the live view made 6.0 maps/s a head without looks, 5.1 with
# a look a second, 5.3-5.5 with one every 2 s (`photopft bench gui --scale 1 --seconds 20 --no-record --loop 11`)
LOOK_INTERVAL_S = 2.0
WINDOW_S = 10.0  # five looks a head: one map's verdict is not the subject's
# The two references' slope wants the volume to swing (metric.MIN_REFERENCE_SWING_L): several breaths,
# so that one breath's noise does not decide it
REFERENCE_WINDOW_S = 30.0


class LiveOpticalChecks:
    """Each head's thread tells it, every LOOK_INTERVAL_S (`due`), its map's sheen
    (`add_sheen`, core/reconstruction/reflectance.py) and side profile (`add_profile`,
    core/volume/sides.py side_profile_mm); `refusal` says why the optical volume would be refused
    now, or None, and `withheld` which of its values would not be given."""

    def __init__(self, heads: list[str]) -> None:
        self._heads = list(heads)
        self._lock = threading.Lock()
        self._last_look: dict[str, float] = {}
        self._sheen: dict[str, collections.deque] = {h: collections.deque() for h in heads}
        self._newest_profile: dict[str, tuple[float, tuple[np.ndarray, np.ndarray]]] = {}
        self._tilts: collections.deque = collections.deque()
        self._volumes: collections.deque = collections.deque()  # (t, referred to the sides, to the top)

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

    def add_volumes(self, t_s: float, side_referred_l: float, top_referred_l: float,
                    silhouette: tuple[float, float] = (float("nan"), float("nan"))) -> None:
        """The live volume at t_s referred to the trunk's sides and to the top of the view
        (core/volume/metric.py, LiveMetricVolume.top_referred_l), and the heads' silhouettes then
        (LiveMetricVolume.silhouette_sample)."""
        with self._lock:
            self._volumes.append((t_s, float(side_referred_l), float(top_referred_l), *map(float, silhouette)))
            self._forget(t_s)

    def _forget(self, now_s: float) -> None:
        for series in (*self._sheen.values(), self._tilts):
            while series and series[0][0] < now_s - WINDOW_S:
                series.popleft()
        while self._volumes and self._volumes[0][0] < now_s - REFERENCE_WINDOW_S:
            self._volumes.popleft()

    def clear(self) -> None:
        """Forget everything (a replay moved: its time runs afresh)."""
        with self._lock:
            self._last_look.clear()
            self._newest_profile.clear()
            for series in (*self._sheen.values(), self._tilts, self._volumes):
                series.clear()

    @property
    def checked(self) -> bool:
        """Whether the last WINDOW_S (REFERENCE_WINDOW_S for the references) gave anything to judge by."""
        with self._lock:
            return any(self._sheen.values()) or bool(self._tilts) or np.isfinite(self._reference_slope())

    def reference_slope(self) -> float:
        """The slope of the top-referred volume on the side-referred one over the last
        REFERENCE_WINDOW_S (core/volume/metric.py, reference_slope)."""
        with self._lock:
            return self._reference_slope()

    def _reference_slope(self) -> float:
        volumes = np.array([v[1:3] for v in self._volumes], dtype=float).reshape(-1, 2)
        return reference_slope(volumes[:, 0], volumes[:, 1])

    def _flanks(self) -> tuple[str | None, str | None]:
        """What the silhouettes' widening over the last REFERENCE_WINDOW_S withholds, as `process` does
        (core/volume/metric.py, withheld_for_flanks): (why VC, FVC, FEV1 and PEF would not be given, what
        the breaths would lose where that withholds the tidal volume too), each None where it does not."""
        rows = np.array([v for v in self._volumes], dtype=float).reshape(-1, 5)
        if len(rows) == 0 or np.ptp(rows[:, 0]) < MIN_WIDENING_SPAN_S:
            return None, None
        widening = silhouette_widening(rows[:, 3], rows[:, 1])
        area = float(np.nanmedian(rows[:, 4])) if np.isfinite(rows[:, 4]).any() else float("nan")
        share = flank_share(widening, area)
        reason = flank_refusal(widening, share)
        if reason is None:
            return None, None
        # the breaths' size: the swing of the last REFERENCE_WINDOW_S, its 5th to 95th percentile
        swing_l = float(np.subtract(*np.nanpercentile(rows[:, 1], [95, 5])))
        return reason, tidal_flank_loss(share, swing_l)

    def refusal(self) -> str | None:
        """Why the optical volume would be refused now, or None; the silhouettes' widening only where
        it withholds the tidal volume too (`withheld` says what it withholds otherwise)."""
        with self._lock:
            sheen = {h: float(np.median([o for _, o in s])) for h, s in self._sheen.items() if s}
            tilts = np.array([t for _, t in self._tilts], dtype=float)
            slope, (flanks, tidal_loss) = self._reference_slope(), self._flanks()
        return (reflectance_refusal(sheen) or bend_refusal(tilts)
                or (f"no tidal volume, rate, VC, FVC, FEV1 or PEF would be given: {flanks}; of a breath of the "
                    f"last {REFERENCE_WINDOW_S:.0f} s {tidal_loss}" if tidal_loss else None)
                or reference_refusal(slope))

    def withheld(self) -> str | None:
        """The optical values the silhouettes' widening would withhold while the tidal volume and rate
        would still be given, and why; None otherwise."""
        with self._lock:
            flanks, tidal_loss = self._flanks()
        return f"VC, FVC, FEV1 and PEF would not be given: {flanks}" if flanks and not tidal_loss else None
