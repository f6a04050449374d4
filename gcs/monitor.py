"""What every simulated flight is judged by, whatever flies it: collision checks at every step
against the full world, 10 Hz samples of the positions and formation metrics, arrival."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gcs.metrics import e_dist
from onboard.planner.formation import similarity
from onboard.world import World


@dataclass(frozen=True)
class CollisionEvent:
    """The start of a collision: ``kind`` 'obstacle' (ids = (drone,)) or 'drone' (ids = pair)."""

    t_s: float
    kind: str
    ids: tuple[int, ...]
    distance_m: float


@dataclass(frozen=True, eq=False)
class Tracks:
    """Recorded at the sample period: t (T,), pos (T, N, 3), e_sim (T,), e_dist (T,)."""

    t: np.ndarray
    pos: np.ndarray
    e_sim: np.ndarray
    e_dist: np.ndarray

    def z_spread_max(self) -> float:
        """The largest altitude difference between two drones at one sample (0 without
        samples): a level formation that tilts shows here, the formation metrics do not see
        it."""
        z = self.pos[:, :, 2]
        return float(np.max(z.max(axis=1) - z.min(axis=1))) if z.size else 0.0


@dataclass(frozen=True)
class MonitorConfig:
    dt_s: float = 0.01
    sample_period_s: float = 0.1
    goal_tolerance_m: float = 0.5
    arrival_speed_m_s: float = 0.1
    collision_obstacle_m: float = 0.2
    collision_drone_m: float = 0.4
    max_events: int = 20


class FlightMonitor:
    """Feed it every step's positions; it counts collisions, samples tracks, detects arrival."""

    def __init__(
        self, world: World, goals: np.ndarray, formation: np.ndarray, cfg: MonitorConfig
    ) -> None:
        self.world = world
        self.goals = goals
        self.formation = formation
        self.cfg = cfg
        n = goals.shape[0]
        self.n = n
        self.sample_every = max(1, int(round(cfg.sample_period_s / cfg.dt_s)))
        self._iu, self._ju = np.triu_indices(n, 1)
        self._in_obstacle = np.zeros(n, dtype=bool)
        self._in_contact = np.zeros(self._iu.shape[0], dtype=bool)
        self.events: list[CollisionEvent] = []
        self.obstacle_events = 0
        self.drone_events = 0
        self.min_clearance_m = math.inf
        self.min_clearance_by_drone_m = np.full(n, math.inf)
        """(N,) each drone's own minimum of ``min_clearance_m``."""
        self.min_pair_m = math.inf
        self.max_speed_m_s = 0.0
        """Highest drone speed seen at the sample instants."""
        self._t: list[float] = []
        self._p: list[np.ndarray] = []
        self._e: list[float] = []
        self._d: list[float] = []
        self.last_e_sim = math.nan
        """e_sim at the latest sample instant."""

    def step(self, k: int, t: float, pos: np.ndarray, vel: Callable[[], np.ndarray]) -> bool:
        """Check step k at time t; returns True once every drone rests at its goal (checked at
        the sample instants, where ``vel()`` is asked for the velocities)."""
        cfg = self.cfg
        dist, _ = self.world.distance(pos)
        self.min_clearance_m = min(self.min_clearance_m, float(np.min(dist)))
        np.minimum(self.min_clearance_by_drone_m, dist, out=self.min_clearance_by_drone_m)
        hit = dist < cfg.collision_obstacle_m
        for i in np.flatnonzero(hit & ~self._in_obstacle):
            self.obstacle_events += 1
            if len(self.events) < cfg.max_events:
                self.events.append(CollisionEvent(t, "obstacle", (int(i),), float(dist[i])))
        self._in_obstacle = hit
        if self._iu.shape[0]:
            pair = np.linalg.norm(pos[self._iu] - pos[self._ju], axis=1)
            self.min_pair_m = min(self.min_pair_m, float(np.min(pair)))
            touch = pair < cfg.collision_drone_m
            for q in np.flatnonzero(touch & ~self._in_contact):
                self.drone_events += 1
                if len(self.events) < cfg.max_events:
                    ids = (int(self._iu[q]), int(self._ju[q]))
                    self.events.append(CollisionEvent(t, "drone", ids, float(pair[q])))
            self._in_contact = touch
        if k % self.sample_every != 0:
            return False
        self._t.append(t)
        self._p.append(pos.copy())
        self.last_e_sim = similarity(pos, self.formation)[0]
        self._e.append(self.last_e_sim)
        self._d.append(e_dist(pos, self.formation))
        v = vel()
        self.max_speed_m_s = max(self.max_speed_m_s, float(np.max(np.linalg.norm(v, axis=1))))
        return bool(np.all(self.arrived(pos, v)))

    def retarget(self, goals: np.ndarray, formation: np.ndarray) -> None:
        """A new formation in flight: arrival is judged at ``goals`` (N, 3) and the formation
        metrics against ``formation`` (N, 3; row i: drone i's point) from the next sample on."""
        g = np.asarray(goals, dtype=np.float64)
        f = np.asarray(formation, dtype=np.float64)
        if g.shape != (self.n, 3) or f.shape != (self.n, 3):
            raise ValueError(f"retarget: goals and formation must be ({self.n}, 3)")
        self.goals = g
        self.formation = f

    def arrived(self, pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
        """(N,) bool: within the goal tolerance and slower than the arrival speed."""
        near = np.linalg.norm(pos - self.goals, axis=1) <= self.cfg.goal_tolerance_m
        return near & (np.linalg.norm(vel, axis=1) < self.cfg.arrival_speed_m_s)

    @property
    def collisions(self) -> int:
        return self.obstacle_events + self.drone_events

    def tracks(self) -> Tracks:
        t = np.array(self._t)
        p = np.array(self._p).reshape(-1, self.n, 3)
        return Tracks(t, p, np.array(self._e), np.array(self._d))
