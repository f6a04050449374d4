"""The peer latency histogram (``onboard.comm.latency``): percentiles against numpy within the
stated bound, exact count and extremes, fixed memory, windows and swarms, counters round trip."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from onboard.comm.latency import (
    LatencyFigures,
    LatencyRecorder,
    bin_bounds,
    bin_index,
)

QS = (0.0, 1.0, 10.0, 50.0, 90.0, 99.0, 99.9, 100.0)


def _bound_us(x_us: float, sub_bits: int = 5) -> float:
    """Half a bin's width at ``x_us`` (the stated error bound), plus a microsecond for the
    truncation of the raw samples."""
    lo, hi = bin_bounds(bin_index(int(x_us), sub_bits), sub_bits)
    return (hi - lo) / 2.0 + 1.0


def _record(samples_s: np.ndarray) -> LatencyFigures:
    r = LatencyRecorder()
    for s in samples_s:
        r.add(float(s))
    return r.snapshot()


def test_bins_tile_the_line_with_bounded_width() -> None:
    for sub_bits in (1, 3, 5):
        prev = -1
        for us in range(300_000):
            i = bin_index(us, sub_bits)
            lo, hi = bin_bounds(i, sub_bits)
            assert lo <= us < hi
            assert i in (prev, prev + 1)  # consecutive samples: the same bin or the next
            assert bin_bounds(i - 1, sub_bits)[1] == lo if i > 0 else lo == 0  # no gap
            prev = i
            if lo >= 2 << sub_bits:
                assert (hi - lo) / lo <= 2.0**-sub_bits


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_percentiles_match_numpy_within_half_a_bin(seed: int) -> None:
    rng = np.random.default_rng(seed)
    # loopback-like: a few hundred us to tens of ms, a heavy tail, a few microsecond ones
    samples = np.concatenate(
        [
            rng.lognormal(np.log(2e-3), 0.8, 5000),
            rng.uniform(0.0, 60e-6, 50),
            [0.35, 1e-6, 0.0],
        ]
    )
    fig = _record(samples)
    us = samples * 1e6
    assert fig.count == samples.size and fig.below_zero == 0
    assert fig.max_us == int(us.max()) and fig.min_us == int(us.min())
    assert fig.sum_us == int(np.sum(np.floor(us)))
    for q in QS:
        want = float(np.percentile(us, q))
        got = fig.percentile_us(q)
        assert got is not None
        assert abs(got - want) <= _bound_us(want), (q, got, want)
    # below 64 us the bins are 1 us wide: exact against the truncated samples
    small = np.array([3e-6, 10e-6, 10e-6, 17e-6, 40e-6, 63e-6])
    fs = _record(small)
    ints = np.floor(small * 1e6 + 1e-9)
    for q in QS:
        assert fs.percentile_us(q) == pytest.approx(float(np.percentile(ints, q)), abs=0.51)


def test_no_samples_and_negative_ones() -> None:
    empty = LatencyRecorder().snapshot()
    assert empty.count == 0 and empty.percentile_us(50.0) is None
    assert empty.summary_ms()["median"] is None and empty.summary_ms()["max"] is None
    r = LatencyRecorder()
    for s in (-0.002, 0.001, 0.003):
        r.add(s)
    f = r.snapshot()
    assert f.count == 3 and f.below_zero == 1 and f.min_us == 0 and f.max_us == 3000
    with pytest.raises(ValueError, match="finite"):
        r.add(float("nan"))
    with pytest.raises(ValueError, match=r"\[0, 100\]"):
        f.percentile_us(101.0)


def test_memory_is_fixed_whatever_the_samples() -> None:
    r = LatencyRecorder()
    n_bins = len(r._counts)
    before = sys.getsizeof(r._counts)
    rng = np.random.default_rng(3)
    for s in rng.exponential(0.01, 20000):
        r.add(float(s))
    r.add(1e6)  # absurdly late: the last bin, the maximum stays exact
    assert len(r._counts) == n_bins == 736 and sys.getsizeof(r._counts) == before
    f = r.snapshot()
    assert f.count == 20001 and f.max_us == 10**12
    assert f.percentile_us(100.0) == 10**12 and f.bins[-1][1] > 10**12
    assert len(f.bins) <= n_bins


def test_windows_and_swarms_add_up() -> None:
    rng = np.random.default_rng(4)
    a, b = rng.exponential(3e-3, 400), rng.exponential(3e-3, 300)
    r = LatencyRecorder()
    for s in a:
        r.add(float(s))
    early = r.snapshot()
    for s in b:
        r.add(float(s))
    late = r.snapshot()
    window = late.minus(early)
    direct = _record(b)
    assert window.count == direct.count and window.bins == direct.bins
    assert window.sum_us == direct.sum_us
    # the window's maximum is exact only when it moved inside the window
    assert window.max_exact == (b.max() > a.max())
    if window.max_exact:
        assert window.max_us == direct.max_us
    else:
        assert direct.max_us <= window.max_us <= direct.bins[-1][1] - 1
    assert late.minus(LatencyFigures()) is late
    with pytest.raises(ValueError, match="earlier snapshot"):
        early.minus(late)
    merged = LatencyFigures.merge([_record(a), _record(b), LatencyFigures()])
    assert merged.count == late.count and merged.bins == late.bins
    assert merged.max_us == late.max_us and merged.min_us == late.min_us
    both = np.concatenate([a, b]) * 1e6
    for q in (50.0, 99.0):
        want = float(np.percentile(both, q))
        assert abs((merged.percentile_us(q) or 0.0) - want) <= _bound_us(want)


def test_counters_round_trip() -> None:
    f = _record(np.array([0.0012, 0.0019, 0.0190, 0.0021, -0.001]))
    c = f.to_counters("bus.peer_latency.")
    assert all(isinstance(v, int) and v >= 0 for v in c.values())
    assert c["bus.peer_latency.count"] == 5 and c["bus.peer_latency.max_us"] == 19000
    back = LatencyFigures.from_counters({**c, "bus.rx.traj": 9}, "bus.peer_latency.")
    assert back == f
    assert LatencyFigures.from_counters({"bus.rx.traj": 9}, "bus.peer_latency.") is None
    with pytest.raises(ValueError, match="bad latency bin"):
        LatencyFigures.from_counters({**c, "bus.peer_latency.bin_us.9-x": 1}, "bus.peer_latency.")
    with pytest.raises(ValueError, match="count is"):
        LatencyFigures(count=2, bins=((1, 2, 1),))
