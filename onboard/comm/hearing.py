"""Whether the peers hear this drone, from what their statuses say about their link to it.

A drone cannot see its own uplink fail: its trajectories leave, and nothing comes back to say
they were lost. Its peers can: each one's 1 Hz status (``onboard.comm.wire.StatusBody``) lists
a ``peer/<id>`` link per peer it knows, up unless silent, with the age of that peer's newest
sign of life (states at 10 Hz, trajectories). A peer that does not hear us plans around our
last broadcast trajectory and its ghosts, not around where we fly; we then keep the two apart
alone, and the flight service plans with a wider berth (``PlannerParams.unheard_margin_m``).

Pure functions of what was received: the flight service feeds them from the bus
(``SwarmBusAdapter``), the fast-time simulator from its agents.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

UNHEARD_AGE_S = 1.0
"""A peer whose newest sign of life from us is this old does not hear us: ten 10 Hz states in
a row lost (20 % loss: p = 1e-7) or a second of trajectories and states delayed."""
REPORT_FRESH_S = 10.0
"""A status older than this (by its stamp) says nothing any more: ten status periods. Shorter
(3 s) let three statuses lost in a row on a lossy bus end a drone's wider berth in the middle of
its outage (the bus-faults flight, 2026-11-30); a peer that stops sending statuses for good
has died or cannot reach us, and is avoided as silent anyway."""
UNLISTED_GRACE_S = 3.0
"""A peer's status that lists no link to us means it does not hear us once we have published
trajectories for this long before the status was sent (it forgot us, or never heard us) ...
"""
UNLISTED_RECENT_S = 3.0
"""... and published one at most this long before it (a trajectory's validity): a landed
drone, which publishes none, is forgotten by its peers and not listed, and hears nothing wrong
in that."""


@dataclass(frozen=True)
class HearingReport:
    """What peer ``peer``'s status, sent at its time ``stamp_s``, says about its link to us:
    whether it lists one (``listed``), up or not (``up``: not silent), and the age of our newest
    sign of life it had (``age_s``, None: never heard)."""

    peer: int
    stamp_s: float
    listed: bool
    up: bool = False
    age_s: float | None = None


def report_from_links(
    peer: int, stamp_s: float, me: int, links: Iterable[tuple[str, bool, float | None]]
) -> HearingReport:
    """The report in a status's links (``(name, up, age_s)``; ours is named ``peer/<me>``)."""
    name = f"peer/{int(me)}"
    for n, up, age in links:
        if n == name:
            ok = age is None or math.isfinite(age)
            return HearingReport(int(peer), float(stamp_s), True, bool(up), age if ok else None)
    return HearingReport(int(peer), float(stamp_s), False)


def not_hearing(
    reports: Sequence[HearingReport],
    now_s: float,
    first_published_s: float,
    last_published_s: float,
    *,
    age_limit_s: float = UNHEARD_AGE_S,
    fresh_s: float = REPORT_FRESH_S,
    grace_s: float = UNLISTED_GRACE_S,
    recent_s: float = UNLISTED_RECENT_S,
) -> frozenset[int]:
    """The peers whose newest report (at most ``fresh_s`` old at ``now_s``) says they do not
    hear us: our link down (silent) or its age ``age_limit_s`` or more, never heard, or not
    listed although we have published trajectories since ``grace_s`` before the report, the
    last at most ``recent_s`` before it (``first_published_s`` / ``last_published_s``: when we
    published our first and our newest trajectory; inf / -inf: none)."""
    newest: dict[int, HearingReport] = {}
    for r in reports:
        old = newest.get(r.peer)
        if old is None or r.stamp_s > old.stamp_s:
            newest[r.peer] = r
    out: set[int] = set()
    for pid, r in newest.items():
        if not now_s - r.stamp_s <= fresh_s:
            continue
        if r.listed:
            if not r.up or r.age_s is None or r.age_s >= age_limit_s:
                out.add(pid)
        elif r.stamp_s - first_published_s >= grace_s and (
            r.stamp_s - last_published_s <= recent_s
        ):
            out.add(pid)
    return frozenset(out)
