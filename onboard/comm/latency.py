"""Peer trajectory latency, publish -> the planner's inbox: a fixed-size histogram per service.

What one sample is: the receiver's clock when a peer's trajectory has entered the inbox the
planner reads (``onboard.service.adapters.SwarmBusAdapter``), minus the sender's stamp taken
just before it encoded and published the message. Encoding, Zenoh, the gate's checks, decoding
and the inbox update are inside. Messages the gate refuses are not samples.

What it means on one machine (the demo, the tests, ``swarm-gcs bench bus``): both stamps come
from the same system clock, so a sample is the true one-way latency. On real drones the two
stamps come from two clocks kept together by chrony: a sample is the latency plus the offset
``our clock - the sender's clock``. The bus estimates that offset per peer
(``onboard.comm.clock``: the minimum of ``receive - stamp`` over a window, i.e. the offset plus
the smallest latency in the window) and reports the largest in the status
(``clock_offset_max_s``); one-way stamps cannot separate offset from latency, so on real drones
the figure is only as good as the clock sync (chrony on a LAN with a local server: well under
1 ms). A sample below zero (the sender's clock ahead of ours by more than the latency) is
counted in ``below_zero`` and enters the histogram as 0.

Cost: a fixed histogram, no allocation per sample. Samples are truncated to whole microseconds
and counted in log-linear bins as in HdrHistogram: 1 us wide below ``2 * SUB`` us (SUB =
``2**sub_bits`` sub-bins, default 32), then SUB bins per power of two, so a bin is at most
``1/SUB`` (3.1 %) of its lower edge wide; values at or above ``top_us`` (default 2**27 us, 134 s)
share the last bin. Count, sum, minimum and maximum are exact (to the microsecond).

Percentiles are numpy's default ("linear") definition computed from the bins: for ``n`` samples
the q-th percentile lies at rank ``h = (n - 1) q / 100`` between the order statistics
``floor(h)`` and ``ceil(h)``; each of those is taken as the middle of the whole microseconds of
the bin holding it (clamped to the exact minimum and maximum), then interpolated. The error
against the exact percentile of the truncated samples is at most half a bin width (1.6 % of the
value with the default bins; none below 64 us).

Histograms of the same layout add (the services of a swarm) and subtract (a later snapshot of a
cumulative counter minus an earlier one: a time window). Through the 1 Hz counters
(``to_counters`` / ``from_counters``) they reach the flight record, where the ground station
reads them after the flight.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

DEFAULT_SUB_BITS = 5
DEFAULT_TOP_US = 1 << 27
BIN_KEY = "bin_us."
"""Counter key of one bin: ``<prefix>bin_us.<lo>-<hi>`` (microseconds, ``lo <= v < hi``)."""


def bin_index(us: int, sub_bits: int) -> int:
    """The bin of ``us`` (an integer >= 0, below the layout's top)."""
    sub = 1 << sub_bits
    if us < 2 * sub:
        return us
    shift = us.bit_length() - 1 - sub_bits  # us >> shift lies in [sub, 2 sub)
    return sub * shift + (us >> shift)


def bin_bounds(index: int, sub_bits: int) -> tuple[int, int]:
    """``(lo, hi)`` in microseconds of bin ``index``: it holds ``lo <= us < hi``."""
    sub = 1 << sub_bits
    if index < 2 * sub:
        return index, index + 1
    shift = index // sub - 1
    lo = (index - sub * shift) << shift
    return lo, lo + (1 << shift)


@dataclass(frozen=True)
class LatencyFigures:
    """A snapshot of latency samples (microseconds; all values whole microseconds).

    count: samples; below_zero: samples that came out negative (entered as 0); sum_us: their
    sum; min_us / max_us: the extremes (0 without samples), exact unless ``min_exact`` /
    ``max_exact`` is False (a window cut out of cumulative snapshots, ``minus``, knows its
    extremes exactly only when they changed inside the window; otherwise they are bounded by
    the window's lowest / highest bin); bins: ``(lo, hi, count)`` of every non-empty bin,
    sorted."""

    count: int = 0
    below_zero: int = 0
    sum_us: int = 0
    min_us: int = 0
    max_us: int = 0
    bins: tuple[tuple[int, int, int], ...] = ()
    min_exact: bool = True
    max_exact: bool = True

    def __post_init__(self) -> None:
        if sum(c for _, _, c in self.bins) != self.count:
            raise ValueError(
                f"latency bins hold {sum(c for _, _, c in self.bins)} samples, count is "
                f"{self.count}"
            )
        if self.count < 0 or self.below_zero < 0 or self.sum_us < 0:
            raise ValueError("latency count, below_zero and sum_us must be >= 0")

    # ---- percentiles --------------------------------------------------------------------------
    def _rank_value(self, rank: int) -> float:
        """The estimate of the ``rank``-th smallest sample (0-based)."""
        if rank <= 0 and self.min_exact:
            return float(self.min_us)
        if rank >= self.count - 1 and self.max_exact:
            return float(self.max_us)
        seen = 0
        for lo, hi, c in self.bins:
            seen += c
            if rank < seen:
                mid = (lo + hi - 1) / 2.0  # the middle of the whole microseconds lo .. hi - 1
                return min(max(mid, float(self.min_us)), float(self.max_us))
        raise AssertionError("rank beyond the samples")  # count == sum of bins (checked)

    def percentile_us(self, q: float) -> float | None:
        """The ``q``-th percentile (0..100) in microseconds, numpy's linear definition (see the
        module docstring for the error bound); None without samples."""
        if not 0.0 <= q <= 100.0:
            raise ValueError(f"percentile q must lie in [0, 100], got {q}")
        if self.count == 0:
            return None
        h = (self.count - 1) * q / 100.0
        lo = math.floor(h)
        v = self._rank_value(lo)
        if h > lo:
            v += (h - lo) * (self._rank_value(lo + 1) - v)
        return v

    def mean_us(self) -> float | None:
        return self.sum_us / self.count if self.count else None

    def summary_ms(self) -> dict[str, float | int | bool | None]:
        """median, p90, p99, max, mean (ms), count, below_zero, max_exact: for JSON."""

        def ms(x: float | None) -> float | None:
            return None if x is None else x / 1e3

        return {
            "median": ms(self.percentile_us(50.0)),
            "p90": ms(self.percentile_us(90.0)),
            "p99": ms(self.percentile_us(99.0)),
            "max": ms(float(self.max_us)) if self.count else None,
            "mean": ms(self.mean_us()),
            "count": self.count,
            "below_zero": self.below_zero,
            "max_exact": self.max_exact,
        }

    # ---- windows and swarms -------------------------------------------------------------------
    def minus(self, earlier: LatencyFigures) -> LatencyFigures:
        """The samples added after ``earlier``, an earlier snapshot of the same cumulative
        histogram (ValueError if it is not one)."""
        if earlier.count == 0:
            return self
        before = {(lo, hi): c for lo, hi, c in earlier.bins}
        bins = []
        for lo, hi, c in self.bins:
            d = c - before.pop((lo, hi), 0)
            if d < 0:
                raise ValueError(f"latency bin {lo}-{hi} us shrank: not an earlier snapshot")
            if d:
                bins.append((lo, hi, d))
        if before or self.count < earlier.count or self.sum_us < earlier.sum_us:
            raise ValueError("latency counts shrank: not an earlier snapshot")
        count = self.count - earlier.count
        if count == 0:
            return LatencyFigures(below_zero=self.below_zero - earlier.below_zero)
        # an extreme that moved after ``earlier`` was set by a sample of the window
        max_exact = self.max_us > earlier.max_us and self.max_exact
        min_exact = self.min_us < earlier.min_us and self.min_exact
        return LatencyFigures(
            count=count,
            below_zero=self.below_zero - earlier.below_zero,
            sum_us=self.sum_us - earlier.sum_us,
            min_us=self.min_us if min_exact else max(self.min_us, bins[0][0]),
            max_us=self.max_us if max_exact else min(self.max_us, bins[-1][1] - 1),
            bins=tuple(bins),
            min_exact=min_exact,
            max_exact=max_exact,
        )

    @staticmethod
    def merge(parts: Iterable[LatencyFigures]) -> LatencyFigures:
        """All samples of ``parts`` together (e.g. every service of a swarm)."""
        full = [p for p in parts if p.count]
        if not full:
            return LatencyFigures(below_zero=0)
        bins: dict[tuple[int, int], int] = {}
        for p in full:
            for lo, hi, c in p.bins:
                bins[(lo, hi)] = bins.get((lo, hi), 0) + c
        top = max(full, key=lambda p: p.max_us)
        bottom = min(full, key=lambda p: p.min_us)
        return LatencyFigures(
            count=sum(p.count for p in full),
            below_zero=sum(p.below_zero for p in full),
            sum_us=sum(p.sum_us for p in full),
            min_us=bottom.min_us,
            max_us=top.max_us,
            bins=tuple((lo, hi, c) for (lo, hi), c in sorted(bins.items())),
            min_exact=bottom.min_exact,
            max_exact=top.max_exact,
        )

    # ---- counters -----------------------------------------------------------------------------
    def to_counters(self, prefix: str = "peer_latency.") -> dict[str, int]:
        """As non-negative integer counters: ``count``, ``below_zero``, ``sum_us``, ``min_us``,
        ``max_us``, ``p50_us`` and ``p99_us`` (for a live view; windows and swarms are computed
        from the bins) and one ``bin_us.<lo>-<hi>`` per non-empty bin."""
        out = {
            f"{prefix}count": self.count,
            f"{prefix}below_zero": self.below_zero,
            f"{prefix}sum_us": self.sum_us,
            f"{prefix}min_us": self.min_us,
            f"{prefix}max_us": self.max_us,
            f"{prefix}p50_us": round(self.percentile_us(50.0) or 0.0),
            f"{prefix}p99_us": round(self.percentile_us(99.0) or 0.0),
        }
        for lo, hi, c in self.bins:
            out[f"{prefix}{BIN_KEY}{lo}-{hi}"] = c
        return out

    @staticmethod
    def from_counters(
        counters: Mapping[str, float], prefix: str = "peer_latency."
    ) -> LatencyFigures | None:
        """Back from ``to_counters``' keys (under ``prefix``) in a counter map, e.g. a flight
        record's ``/counters`` (there prefixed ``bus.``); None if the map has none."""
        if f"{prefix}count" not in counters:
            return None
        bins = []
        start = prefix + BIN_KEY
        for k, v in counters.items():
            if k.startswith(start):
                lo, sep, hi = k[len(start) :].partition("-")
                if not sep or not lo.isdigit() or not hi.isdigit() or int(hi) <= int(lo):
                    raise ValueError(f"bad latency bin counter {k!r}")
                if int(v):
                    bins.append((int(lo), int(hi), int(v)))
        return LatencyFigures(
            count=int(counters[f"{prefix}count"]),
            below_zero=int(counters.get(f"{prefix}below_zero", 0)),
            sum_us=int(counters.get(f"{prefix}sum_us", 0)),
            min_us=int(counters.get(f"{prefix}min_us", 0)),
            max_us=int(counters.get(f"{prefix}max_us", 0)),
            bins=tuple(sorted(bins)),
        )


class LatencyRecorder:
    """A cumulative latency histogram (see the module docstring). Not thread-safe: the owner
    serialises ``add`` and ``snapshot``.

    sub_bits: 2**sub_bits bins per power of two (bin width at most 2**-sub_bits of the value);
    top_us: values at or above it share the last bin (the maximum stays exact)."""

    def __init__(self, sub_bits: int = DEFAULT_SUB_BITS, top_us: int = DEFAULT_TOP_US) -> None:
        if not 1 <= sub_bits <= 10:
            raise ValueError(f"latency sub_bits must lie in [1, 10], got {sub_bits}")
        if top_us < 4 << sub_bits:
            raise ValueError(f"latency top_us must be >= {4 << sub_bits}, got {top_us}")
        self.sub_bits = int(sub_bits)
        self.top_us = int(top_us)
        self._last = bin_index(self.top_us - 1, self.sub_bits)
        self._counts = [0] * (self._last + 1)
        self.count = 0
        self.below_zero = 0
        self.sum_us = 0
        self.min_us = 0
        self.max_us = 0

    def add(self, latency_s: float) -> None:
        """One sample in seconds; a non-finite one is a caller's bug (ValueError)."""
        if not math.isfinite(latency_s):
            raise ValueError(f"latency sample must be finite, got {latency_s}")
        if latency_s < 0.0:
            self.below_zero += 1
            us = 0
        else:
            us = int(latency_s * 1e6)
        self._counts[self._last if us >= self.top_us else bin_index(us, self.sub_bits)] += 1
        if self.count == 0 or us < self.min_us:
            self.min_us = us
        if us > self.max_us:
            self.max_us = us
        self.count += 1
        self.sum_us += us

    def snapshot(self) -> LatencyFigures:
        bins = []
        for i, c in enumerate(self._counts):
            if c:
                lo, hi = bin_bounds(i, self.sub_bits)
                if i == self._last:
                    hi = max(hi, self.max_us + 1)  # the last bin holds everything above
                bins.append((lo, hi, c))
        return LatencyFigures(
            count=self.count,
            below_zero=self.below_zero,
            sum_us=self.sum_us,
            min_us=self.min_us,
            max_us=self.max_us,
            bins=tuple(bins),
        )
