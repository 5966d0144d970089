"""The twin's receiver through the real NMEA decoders: a receiver converging from float to
fixed, and float errors that wander (as a real float solution's do) instead of white noise."""

from __future__ import annotations

import dataclasses
import datetime as dt

import numpy as np
import pytest

from treetraits.drivers.gnss.epochs import EpochAssembler
from treetraits.drivers.gnss.sentences import decode
from treetraits.drivers.gnss.stream import SentenceSplitter
from treetraits.pipeline.localization.utm import UtmGrid
from treetraits.sim.gnss import GnssEmulator, GnssSettings, UtmZone
from treetraits.sim.run import ORIGIN_UTM, UTM_ZONE

START = dt.datetime(2026, 5, 12, 17, 0, 0, tzinfo=dt.UTC)


def standing_fixes(settings: GnssSettings, seconds: float, seed: int = 2):
    """(t_s, quality, east error, north error) of a receiver standing at the origin, each
    epoch's bytes decoded by the real splitter, decoder and epoch assembler."""
    emulator = GnssEmulator(
        UtmZone(UTM_ZONE), ORIGIN_UTM, np.eye(4), settings, np.random.default_rng(seed)
    )
    splitter, epochs, out = SentenceSplitter(), EpochAssembler(), []
    grid = None
    for k in range(int(seconds * settings.rate_hz)):
        t_s = k / settings.rate_hz
        utc = START + dt.timedelta(seconds=t_s)
        data = b"".join(emulator.epoch(t_s, utc, 0.0, 0.0, 0.0, 0.0))
        for sentence in splitter.push(data, int(utc.timestamp() * 1e9)):
            record = decode(sentence)
            if record is not None and (fix := epochs.push(record)) is not None:
                grid = grid or UtmGrid.for_position(fix.lat, fix.lon)
                east, north = grid.forward(fix.lat, fix.lon)
                out.append((fix.utc_ns, fix.quality, east - ORIGIN_UTM[0], north - ORIGIN_UTM[1]))
    t0 = out[0][0]
    return np.array([((t - t0) / 1e9, q, e, n) for t, q, e, n in out])


def lag_correlation(values: np.ndarray, lag: int) -> float:
    return float(np.corrcoef(values[:-lag], values[lag:])[0, 1])


def test_a_converging_receiver_is_float_then_fixed():
    fixes = standing_fixes(GnssSettings(converge_s=30.0), 60.0)
    float_part, fixed_part = fixes[fixes[:, 0] < 30.0], fixes[fixes[:, 0] >= 30.0]
    assert set(float_part[:, 1]) == {5} and set(fixed_part[:, 1]) == {4}
    assert len(float_part) == pytest.approx(300, abs=2)
    assert np.abs(fixed_part[:, 2:]).max() < 0.1  # 2 cm white


def test_float_errors_wander_over_a_minute_while_fixed_ones_are_white():
    settings = dataclasses.replace(GnssSettings(), quality=5, rate_hz=2.0)
    fixes = standing_fixes(settings, 600.0)
    east = fixes[:, 2]
    # Gauss-Markov, tau 60 s: correlation exp(-lag/tau) at 1 s and 60 s, sigma 0.25 m.
    assert lag_correlation(east, 2) > 0.95
    assert 0.1 < lag_correlation(east, 120) < 0.65
    assert np.std(fixes[:, 2:]) == pytest.approx(0.25, rel=0.4)
    fixed = standing_fixes(GnssSettings(), 60.0)
    assert abs(lag_correlation(fixed[:, 2], 10)) < 0.2
