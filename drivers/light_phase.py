"""Which light lit each frame: one rule, shared by `record` and the live engine.

The sequencer fires one slot of its sequence per trigger and counts its triggers; a camera numbers
the frames it delivers (GigE Vision block ids start at 1, whatever the sequencer had fired before).
The trigger that exposed a head's first frame gives that frame's slot; from there each frame id
counts one trigger, so a lost frame is a gap, never a shifted light. That first trigger is 0 when
the cameras are started, waiting for triggers, before the sequencer; it is the sequencer's count
when a camera joins a running sequence; on the simulated rig the frame ids are the trigger numbers.

The images confirm the phase at the start and then continuously, over the last WINDOW_CYCLES
cycles of each head: the dark slots' frames are the darkest (below DARK_RATIO of every lit slot's
mean), which fixes the phase; and each LED brightens the side of the subject it stands on, so the
brightness centroid of its frames moves from the lit frames' mean centroid towards the LED
(light_positions_mm, camera frame). A phase that the images contradict in MISMATCH_CHECKS checks
running is realigned and said; an LED order that the images contradict is an error (the LEDs are
wired or configured in another order than the rig says).
Images that cannot tell (no subject, a test pattern) leave the counted phase as it is, and say so.
"""

from __future__ import annotations

import itertools
import threading
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from core.rig import DARK, Rig

WINDOW_CYCLES = 4  # the cycles of frames each check looks at
MISMATCH_CHECKS = 3  # checks in a row that must contradict the counted phase before it is realigned
DARK_RATIO = 0.8  # a dark slot's mean brightness below this fraction of every lit slot's
MIN_LED_COSINE = 0.5  # the images "contradict" an LED order when another order fits them by this much more per LED
MIN_SHIFT = 0.002  # an LED's centroid shift, in image widths, below which its shading says nothing
STRIDE_PX = 8  # the images are summarised on every STRIDE_PX-th pixel: a check costs microseconds


class LightPhaseError(Exception):
    """The images contradict the rig's light sequence; the message says how."""


@dataclass
class _HeadPhase:
    offset: int | None = None  # light of frame id f: sequence[(f + offset) % n]
    stats: deque = field(default_factory=deque)  # (frame id, mean, centroid x, centroid y) of recent frames
    checked: int = 0
    confirmed: int = 0
    mismatches: int = 0
    since_check: int = 0


class LightPhase:
    """The light of every frame of every head. `first_trigger`: the trigger that exposed each head's
    first delivered frame (0 when the cameras were started before the sequencer); None when the
    frame ids are the trigger numbers themselves (the simulated rig)."""

    def __init__(self, rig: Rig, first_trigger: int | dict[str, int] | None = None, sequencer=None) -> None:
        self.sequence = np.asarray(rig.sequence, dtype=np.int64)
        self.rig = rig
        self.first_trigger = first_trigger
        self.sequencer = sequencer  # drivers.sequencer.Sequencer, configured and armed, or None
        self._lock = threading.Lock()
        self.notices: list[str] = []
        self._heads: dict[str, _HeadPhase] = {}

    def begin(self) -> None:
        """Called once the cameras are started and wait for triggers: an armed sequencer is started
        now, so each head's first frame is trigger 0; a running one (cameras restarted) is read, and
        its count is the first trigger of the frames to come (the images confirm it)."""
        if self.sequencer is None:
            return
        status = self.sequencer.status()
        if status.state == "armed":
            self.sequencer.start()
            self.first_trigger = 0
        elif status.state == "running":
            self.first_trigger = status.trigger_count
        else:
            raise LightPhaseError(f"the sequencer on {self.sequencer.port_name} is {status.state}, "
                                  f"not armed: the lights cannot be known")
        self._heads.clear()

    def _head(self, head: str) -> _HeadPhase:
        return self._heads.setdefault(head, _HeadPhase(stats=deque(maxlen=WINDOW_CYCLES * len(self.sequence))))

    def _start(self, state: _HeadPhase, head: str, frame_id: int) -> None:
        if self.first_trigger is None:
            state.offset = 0
            return
        first = self.first_trigger[head] if isinstance(self.first_trigger, dict) else self.first_trigger
        state.offset = int(first) - int(frame_id)

    def light_of(self, head: str, frame_id: int) -> int:
        """The light (0-3, or -1 for the dark slot) that exposed this frame."""
        state = self._head(head)
        if state.offset is None:
            self._start(state, head, frame_id)
        return int(self.sequence[(int(frame_id) + state.offset) % len(self.sequence)])

    __call__ = light_of

    def ready(self, head: str) -> bool:
        """True once the images have been checked at least once (or never can be)."""
        return self._head(head).checked > 0

    def observe(self, head: str, frame_id: int, image: np.ndarray) -> None:
        """Add a frame to the head's check; every cycle's worth of frames, check the phase."""
        with self._lock:
            state = self._head(head)
            if state.offset is None:
                self._start(state, head, frame_id)
            if state.stats and int(frame_id) <= state.stats[-1][0]:
                return  # seen already (the live engine and its recorder both pass frames here)
            self._add(head, state, frame_id, image)

    def _add(self, head: str, state: _HeadPhase, frame_id: int, image: np.ndarray) -> None:
        small = np.asarray(image)[::STRIDE_PX, ::STRIDE_PX]
        # the centroid from the row and column sums: two reductions of the strided view, no copies
        column_sums = small.sum(axis=0, dtype=np.float64)
        row_sums = column_sums if small.shape[0] == 0 else small.sum(axis=1, dtype=np.float64)
        total = float(column_sums.sum())
        if total > 0:
            # in fractions of the image's width and height
            cx = float(column_sums @ np.arange(len(column_sums)) / total / len(column_sums))
            cy = float(row_sums @ np.arange(len(row_sums)) / total / len(row_sums))
        else:
            cx = cy = float("nan")
        state.stats.append((int(frame_id), total / max(small.size, 1), cx, cy))
        state.since_check += 1
        if len(state.stats) >= 2 * len(self.sequence) and state.since_check >= len(self.sequence):
            state.since_check = 0
            self._check(head, state)

    def _slot_means(self, state: _HeadPhase) -> tuple[np.ndarray, np.ndarray] | None:
        """Per frame-id residue (id mod n): mean brightness and mean centroid; None when a residue
        has no frame in the window."""
        n = len(self.sequence)
        stats = np.asarray(state.stats, dtype=np.float64)
        residue = stats[:, 0].astype(np.int64) % n
        means, centroids = np.full(n, np.nan), np.full((n, 2), np.nan)
        for r in range(n):
            rows = stats[residue == r]
            if not len(rows):
                return None
            means[r] = rows[:, 1].mean()
            centroids[r] = rows[:, 2:4].mean(axis=0)
        return means, centroids

    def image_offset(self, head: str) -> int | None:
        """The phase the images alone give (offset, as in light_of), or None when they cannot tell."""
        state = self._head(head)
        slots = self._slot_means(state)
        if slots is None:
            return None
        means, _ = slots
        n = len(self.sequence)
        fits = []
        for offset in range(n):
            lights = self.sequence[(np.arange(n) + offset) % n]
            dark, lit = means[lights == DARK], means[lights != DARK]
            if dark.max() < DARK_RATIO * lit.min():
                fits.append(offset)
        return fits[0] if len(fits) == 1 else None

    def _led_order_problem(self, head: str, state: _HeadPhase, offset: int) -> str | None:
        """How the images contradict the LED order of the sequence, or None."""
        means, centroids = self._slot_means(state)
        n = len(self.sequence)
        lights = self.sequence[(np.arange(n) + offset) % n]
        lit_residues = [r for r in range(n) if lights[r] != DARK]
        shifts = centroids[lit_residues] - centroids[lit_residues].mean(axis=0)
        lengths = np.linalg.norm(shifts, axis=1)
        if not np.all(np.isfinite(lengths)) or lengths.min() < MIN_SHIFT:  # the shading does not move: cannot tell
            return None
        shifts = shifts / lengths[:, None]
        xy = np.asarray(self.rig.heads[head].light_positions_mm, dtype=float)[:, :2]  # x right, y down
        norms = np.linalg.norm(xy, axis=1, keepdims=True)
        if not np.all(norms > 0):
            return None
        directions = xy / norms
        said = [int(lights[r]) for r in lit_residues]

        def fit(order) -> float:
            return float(np.mean(np.sum(shifts * directions[list(order)], axis=1)))

        best = max(itertools.permutations(said), key=fit)
        if fit(best) - fit(said) > MIN_LED_COSINE:
            return (f"head {head}: the images show the LEDs firing as {list(best)} where the sequence says "
                    f"{said}: check the LED wiring and the rig's sequence")
        return None

    def _check(self, head: str, state: _HeadPhase) -> None:
        n = len(self.sequence)
        found = self.image_offset(head)
        state.checked += 1
        if found is None:
            return
        if found % n == state.offset % n:
            state.confirmed += 1
            state.mismatches = 0
        else:
            state.mismatches += 1
            # the first check comes before any of the head's frames is recorded (the recorder holds
            # them): the images decide at once; later, only a contradiction that lasts
            if state.checked == 1 or state.mismatches >= MISMATCH_CHECKS:
                newest = int(state.stats[-1][0])
                was = int(self.sequence[(newest + state.offset) % n])
                now = int(self.sequence[(newest + found) % n])
                at_start = state.checked == 1
                state.offset, state.mismatches = found, 0
                self.notices.append(f"head {head}: the images show frame {newest} lit by {_slot_name(now)}, not "
                                    f"{_slot_name(was)}: the light phase was realigned "
                                    + ("at the start" if at_start else
                                       f"there (up to {MISMATCH_CHECKS * n} frames before it may carry the "
                                       f"wrong light)"))
                state.stats.clear()
                return
        problem = self._led_order_problem(head, state, found)
        if problem:
            raise LightPhaseError(problem)

    def summary(self) -> list[str]:
        """What the images said of each head's phase, for the end of a recording."""
        lines = list(self.notices)
        for head, state in self._heads.items():
            if state.checked and not state.confirmed:
                lines.append(f"head {head}: the images could not confirm the light phase (no dark frame stood "
                             f"out in {state.checked} checks); the sequencer's trigger count was used")
        return lines


def _slot_name(light: int) -> str:
    return "the dark slot" if light == DARK else f"LED {light}"


class RecordedLights:
    """The lights a recorded session already holds for its frames (a replay): the same interface."""

    def __init__(self, lights: dict[str, dict[int, int]]) -> None:
        self._lights = lights
        self.notices: list[str] = []

    def light_of(self, head: str, frame_id: int) -> int:
        return int(self._lights[head].get(int(frame_id), -2))

    __call__ = light_of

    def ready(self, head: str) -> bool:
        return True

    def begin(self) -> None:
        """Nothing to start: the file's frames are labelled."""

    def observe(self, head: str, frame_id: int, image: np.ndarray) -> None:
        """A recorded file's lights need no check."""

    def summary(self) -> list[str]:
        return []
