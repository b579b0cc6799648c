"""Adaptive bracketing: the rule on known levels, and the acceptance on the simulated box."""

from dataclasses import replace
from fractions import Fraction

import numpy as np

from ilt.capture.adaptive import AdaptiveBracket
from ilt.capture.config import PAPER_SHUTTERS, Exposure
from ilt.capture.emulator import PTUEmulator
from ilt.capture.loop import capture
from tests.capture_helpers import pointing_of, small_config

PAPER = tuple(sorted([Exposure(Fraction(s), 1.2) for s in PAPER_SHUTTERS] + [Exposure(Fraction(1, 8000), 16.0)],
                     key=lambda e: -e.relative))


def _frame(radiance, e, sat=1000.0):
    dn = np.minimum(radiance * e.relative, 1.1 * sat)
    return dn, sat, dn >= sat


def test_rule_jumps_by_low_and_stops_when_nothing_saturates():
    chooser = AdaptiveBracket(PAPER, low=1 / 64, high=0.9)
    # radiances spanning 1e3 .. 1e8 DN/s: saturated at 1/15 f/1.2 (e = 0.046) above ~2e4
    radiance = np.array([[1e3, 1e5, 1e7, 1.5e8]])
    taken = []
    e = chooser.first()
    while e is not None:
        taken.append(str(e.shutter) + f"@f{e.aperture:g}")
        chooser.add(e, *_frame(radiance, e))
        e = chooser.next()
    # 1/15 -> shortest e >= e_prev / 64 * (0.9 ...): 1/500; then 1/8000; then the f/16 frame
    assert taken == ["1/15@f1.2", "1/500@f1.2", "1/8000@f1.2", "1/8000@f16"]
    assert len(chooser.skipped()) == 7


def test_rule_stops_at_once_for_a_dim_scene():
    chooser = AdaptiveBracket(PAPER)
    chooser.add(PAPER[0], *_frame(np.array([[10.0, 1e3]]), PAPER[0]))
    assert chooser.next() is None


def test_box_scene_saves_30_percent_with_equal_hdr(tmp_path):
    from ilt.hdr.bracket import list_beams, read_beam
    from ilt.hdr.merge import NoiseModel, merge_bracket
    from ilt.io.raw import read_green

    base = small_config(
        camera={"scene": "box", "px_per_beam": 8.0, "radiance_scale": 3.0e8},
        bracket={"shutter": list(PAPER_SHUTTERS), "extra": [{"shutter": "1/8000", "aperture": 16}], "stride": 1},
        plan={"kind": "grid", "pan": 0.0, "tilt": [3.0, -3.0], "shape": [3, 1]},
    )
    runs = {}
    for adaptive in (False, True):
        cfg = replace(base, bracket=replace(base.bracket, adaptive=adaptive))
        with PTUEmulator("pty", speed=20000) as emu:
            cfg = replace(cfg, ptu=replace(cfg.ptu, port=emu.port))
            runs[adaptive] = (tmp_path / str(adaptive), capture(cfg, tmp_path / str(adaptive), pointing=pointing_of(emu)))
    summary = runs[True][1]
    assert summary["exposures_full"] == 3 * 11
    saved = summary["exposures_skipped"] / summary["exposures_full"]
    assert saved >= 0.30, saved
    assert summary["seconds_saved"] > 0

    noise = NoiseModel(gain=1.0, read_noise=2.0)
    worst = 0.0
    for full_dir, fast_dir in zip(list_beams(runs[False][0]), list_beams(runs[True][0])):
        merged = {}
        for key, beam_dir in (("full", full_dir), ("fast", fast_dir)):
            b = read_beam(beam_dir)
            greens = [read_green(b.path(f), f.exposure_time, f.f_number) for f in b.frames]
            dark, _ = read_green(b.path(b.dark))
            e = [g[1].exposure.relative_exposure() for g in greens]
            x, count, _ = merge_bracket([g[0] for g in greens], e, [g[1].saturated for g in greens],
                                        noise=noise, dark=dark)
            x = x.astype(np.float64)
            # variance of the inverse-variance merge over the samples it used (unsaturated)
            info = sum(np.where(g[1].saturated, 0.0, ek**2 / noise.variance(x * ek)) for g, ek in zip(greens, e))
            merged[key] = (x, count, 1.0 / np.maximum(info, 1e-300))
        x_full, c_full, v_full = merged["full"]
        x_fast, c_fast, v_fast = merged["fast"]
        lit = (c_full > 0) & (c_fast > 0) & (x_full > 0)
        z = np.abs(x_fast[lit] - x_full[lit]) / np.sqrt(v_full[lit] + v_fast[lit])
        worst = max(worst, float(np.quantile(z, 0.999)))
        assert np.mean(z) < 1.0  # differences are noise-sized: |z| of a unit normal averages 0.8
    print(f"adaptive: saved {saved:.0%} of exposures, worst 99.9% |z| {worst:.2f}")
    assert worst < 5.0, worst
