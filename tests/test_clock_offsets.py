"""Peer clock-offset estimate from message stamps (injected times, no sleeps)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from onboard.comm.clock import ClockOffsets


def test_estimate_is_offset_plus_smallest_latency() -> None:
    rng = np.random.default_rng(0)
    clocks = ClockOffsets(bound_s=0.05, window_s=10.0)
    true_offset = -0.2  # the peer's clock runs 0.2 s ahead of ours
    for k in range(100):
        send_peer = 1000.0 + 0.1 * k  # the peer's clock
        latency = 0.002 + rng.exponential(0.01)
        clocks.add(7, send_peer + true_offset + latency, send_peer)  # our clock
    est = clocks.offset(7)
    assert est is not None and true_offset < est < true_offset + 0.003
    r = clocks.report()[7]
    assert r.exceeded and r.samples == 100
    assert clocks.exceeded() == {7} and clocks.max_abs_offset() == pytest.approx(abs(est))
    assert clocks.offset(8) is None


def test_window_forgets_old_samples() -> None:
    clocks = ClockOffsets(bound_s=0.05, window_s=5.0)
    clocks.add(1, 100.0, 100.0 - 0.001)
    for k in range(1, 20):  # the offset then grows to 1 s (a clock step)
        t = 100.0 + k
        clocks.add(1, t, t - 1.0)
    assert clocks.offset(1) == pytest.approx(1.0)
    assert clocks.report()[1].samples == 6  # samples received within the last 5 s


def test_warning_once_per_excursion(caplog: pytest.LogCaptureFixture) -> None:
    clocks = ClockOffsets(bound_s=0.05, window_s=1.0, name="[drone 2] ")
    with caplog.at_level(logging.INFO, logger="onboard.comm.clock"):
        clocks.add(3, 10.0, 10.0)
        for k in range(5):
            clocks.add(3, 11.5 + k * 0.1, 11.5 + k * 0.1 - 0.2)
        assert clocks.warnings == 1 and clocks.exceeded() == {3}
        for k in range(5):
            clocks.add(3, 14.0 + k * 0.1, 14.0 + k * 0.1 - 0.01)
        assert clocks.exceeded() == set()
        clocks.add(3, 20.0, 19.0)
    assert clocks.warnings == 2
    text = [r.getMessage() for r in caplog.records]
    assert sum("bound 0.050 s" in t for t in text) == 2
    assert any("back within bound" in t for t in text)
    assert all(t.startswith("[drone 2] ") for t in text)


def test_bad_settings() -> None:
    with pytest.raises(ValueError, match="bound_s"):
        ClockOffsets(bound_s=0.0)


def test_a_rare_sender_over_a_slow_bus_is_not_taken_for_a_lagging_clock() -> None:
    """One or two messages late by bus delay (a ground station's commands) give a positive
    estimate that may be all latency: not flagged until the window holds min_samples messages
    or the excess is more than any latency explains; a peer ahead of us needs no evidence."""
    clocks = ClockOffsets(bound_s=0.05, window_s=10.0, min_samples=3, latency_allowance_s=0.5)
    clocks.add(9, 100.0, 100.0 - 0.146)  # in sync, 146 ms of bus delay
    clocks.add(9, 104.0, 104.0 - 0.120)
    assert clocks.offset(9) == pytest.approx(0.120) and clocks.exceeded() == set()
    clocks.add(9, 105.0, 105.0 - 0.130)  # a third late one: a lag is now believed
    assert clocks.exceeded() == {9}
    clocks.add(5, 100.0, 100.0 - 0.9)  # one message, 0.9 s: no latency explains it
    clocks.add(6, 100.0, 100.0 + 0.2)  # one message stamped 0.2 s in our future
    assert clocks.exceeded() == {9, 5, 6}
    with pytest.raises(ValueError, match="min_samples"):
        ClockOffsets(min_samples=0)
