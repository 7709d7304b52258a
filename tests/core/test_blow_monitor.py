"""The forced blow as it happens (core/analysis/blow_monitor.py): nothing before the blow starts, the
back-extrapolated volume and FET during it, the end-of-test plateau when it comes, the same values
as the report's analysis of the whole blow, and the best blow by ATS/ERS 2019."""

from __future__ import annotations

import numpy as np
import pytest

from core.analysis.values import ANALYSIS_RATE_HZ, pef_not_given, resample
from core.analysis.blow_monitor import best_blow, live_blow
from core.analysis.spirometry import forced_values


def _session(fvc_l: float = 4.0, tau_s: float = 0.6, rate_hz: float = 100.0):
    """Quiet breathing, a full inspiration to 3 L above FRC at 1 s before the mark, then a blow
    of fvc_l (exhaled = fvc (1 - exp(-t/tau)) from the mark), then breathing in again at 10 s."""
    t = np.arange(-3.0, 12.0, 1.0 / rate_hz)
    v = np.where(t < -1.0, 0.3 * np.sin(2 * np.pi * t / 4), 0.0)
    rising = (t >= -1.0) & (t < 0.0)
    v[rising] = 3.0 * (t[rising] + 1.0)
    blowing = t >= 0.0
    v[blowing] = 3.0 - fvc_l * (1 - np.exp(-t[blowing] / tau_s))
    after = t >= 10.0
    v[after] = v[after][0] + 1.5 * (t[after] - 10.0)
    return t, v


def test_the_blow_is_followed_from_start_to_plateau():
    t, v = _session()
    before = live_blow(t[t <= -0.2], v[t <= -0.2], 0.0)
    assert not before.started and "waiting" in before.status()
    during = live_blow(t[t <= 1.5], v[t <= 1.5], 0.0)
    assert during.started and not during.end_of_test
    assert during.values.bev_ok and during.values.fet_s == pytest.approx(1.5, abs=0.1)
    assert "keep blowing" in during.status()
    done = live_blow(t[t <= 9.0], v[t <= 9.0], 0.0)
    assert done.end_of_test and "end of test reached" in done.status()
    assert done.values.fvc_l == pytest.approx(4.0, abs=0.01)
    # what the operator saw is what the report says: the report's analysis of the same blow
    grid, vg = resample(t[(t >= -1.0) & (t <= 9.5)], v[(t >= -1.0) & (t <= 9.5)])
    top = int(np.argmax(vg))
    report = forced_values(vg[top] - vg[top:], ANALYSIS_RATE_HZ)
    assert done.values.fev1_l == pytest.approx(report.fev1_l, abs=0.005)
    assert done.values.pef_lps == pytest.approx(report.pef_lps, abs=0.05)
    # the next inspiration is not part of the blow's curves
    after = live_blow(t, v, 0.0)
    assert np.all(np.diff(after.exhaled_l) >= -1e-9) and after.exhaled_l[-1] == pytest.approx(after.values.fvc_l)


def test_the_best_blow_is_the_acceptable_one_with_the_largest_fev1_plus_fvc():
    blows = []
    for fvc, tau in ((4.0, 0.6), (4.2, 0.6), (4.1, 0.5)):
        t, v = _session(fvc, tau)
        blows.append(live_blow(t[t <= 9.0], v[t <= 9.0], 0.0).values)
    assert all(b.fvc_acceptable for b in blows)
    assert best_blow(blows) == max(range(3), key=lambda i: blows[i].fvc_l + blows[i].fev1_l)
    blows[1].cough_in_first_second = True  # no longer acceptable: the best is another one
    assert best_blow(blows) != 1
    assert best_blow([]) is None


def test_the_live_blow_does_not_call_the_maps_noise_a_cough():
    """The report's rule, live: a blow (tau 1 s) seen a map a light cycle with 30 mL of noise
    correlated over a map; read straight, its flow rebounds by more than a fifth of its peak in the
    first second on every seed, from the noise alone. One step's flow noise is 5-8 % of the peak, over
    the 5 % a PEF within 10 % needs: the blow shows no cough and says that none could be judged."""
    from scipy import ndimage

    t, v = _session(tau_s=1.0)
    maps_s = np.arange(t[0], 9.0, 1.0 / 22.0)
    clean = np.interp(maps_s, t, v)
    for seed in range(4):
        noise = ndimage.gaussian_filter1d(np.random.default_rng(seed).normal(0.0, 1.0, len(maps_s)), 1.0)
        values = live_blow(maps_s, clean + 0.030 * noise / noise.std(), 0.0).values
        assert not values.cough_in_first_second and not values.cough_judged
        assert values.problems[-1].startswith("cough in the first second not judged")
        assert values.samples_step_s == pytest.approx(1.0 / 22.0, rel=0.01)  # nor is its PEF given
        assert pef_not_given(values).startswith(f"the noise from map to map is {100 * values.pef_noise_ratio:.0f} %")


def test_a_start_the_maps_are_too_sparse_to_place_is_not_judged():
    """A good blow seen one map every 290 ms (a slow machine's live view): straight lines between the
    maps flatten its steepest part, so time zero and the back-extrapolated volume would call it
    hesitant (the standard waveforms: 20 % of good starts so, `bench blows --bev-steps-ms`). Its start
    is not judged and it says so; one map a light cycle (45 ms) judges it."""
    from core.sim.breathing import RATE_HZ, ForcedBlow, forced_expiration_curve

    t, v = _session()
    exhaled = forced_expiration_curve(4.0, 3.3, 8.0, ForcedBlow(), 9.0)  # the flow rising to its peak as a person's
    blowing = t >= 0.0
    v[blowing] = 3.0 - np.interp(t[blowing], np.arange(len(exhaled)) / RATE_HZ, exhaled)
    fine = live_blow(t[t <= 9.0], v[t <= 9.0], 0.0)
    assert fine.values.bev_judged and fine.values.bev_ok
    for step_s, judged in ((0.045, True), (0.29, False)):
        maps = np.arange(-3.0, 9.0, step_s) + 0.013
        blow = live_blow(maps, np.interp(maps, t, v), 0.0)
        assert blow.values.bev_judged == judged and blow.values.bev_ok
        if judged:
            assert blow.values.bev_l == pytest.approx(fine.values.bev_l, abs=0.04)
            assert not any("start not judged" in p for p in blow.values.problems)
        else:
            assert "BEV not judged (a map every 290 ms)" in blow.status()
            assert "start not judged: a map every 290 ms, at least one every 50 ms needed to place time zero" in \
                blow.values.problems
            assert not any("hesitant start" in p for p in blow.values.problems)
