"""Baseline of the paper's comparison: virtual structure with potential fields (Zhou et al. 2018).

A rigid virtual structure (the formation at its configured size and orientation) moves from the
start centre to the goal centre; it slows down while the drones lag behind their slots. Each
drone is a point mass with speed and acceleration limits whose velocity command is

    v_cmd = v_structure + k_slot (slot - p) + sum of repulsions (obstacles, peers)

with Khatib's repulsive potential ``k (1/d - 1/d0) / d^2`` along the distance gradient for every
obstacle surface (cylinders, rings, boxes, ground) and every peer closer than its influence
distance, each drone sensing only within the simulation's sensing radius. No planning: local
minima of the summed fields (a trunk right ahead) stall drones, as the paper reports.

(The other baseline, Turpin et al.'s fixed relative positions, runs in our own optimiser as the
formation variant ``formation_penalty='relative'``.)
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gcs.fastsim import (
    SimConfig,
    SimResult,
    build_flight,
    default_time_limit_s,
    result_from_monitor,
)
from gcs.monitor import FlightMonitor, MonitorConfig
from onboard.world import World


@dataclass(frozen=True)
class VirtualStructureParams:
    """Gains and limits of the virtual-structure controller (tuned on the medium forest)."""

    k_slot: float = 1.0
    """Attraction to the slot [1/s]."""
    obstacle_influence_m: float = 1.0
    """d0 of the obstacle potential: surfaces farther than this do not push."""
    k_obstacle: float = 0.15
    """Gain of the obstacle repulsion."""
    peer_influence_m: float = 1.0
    """d0 of the peer potential (centre to centre)."""
    k_peer: float = 0.15
    """Gain of the peer repulsion."""
    a_max_m_s2: float = 2.0
    """Acceleration limit of the point-mass drones."""
    structure_speed_fraction: float = 0.9
    """The structure cruises at this fraction of v_max."""
    slowdown_m: float = 1.5
    """Structure speed is scaled by max(0.1, 1 - mean slot error / slowdown_m)."""


def _repulsion(world: World, pos: np.ndarray, sensing_m: float, d0: float, k: float) -> np.ndarray:
    """Sum over obstacle primitives within min(d0, sensing) of each drone: (N, 3)."""
    out = np.zeros_like(pos)
    d0 = min(d0, sensing_m)
    cyl = world.cylinders
    if cyl.shape[0]:
        # vertical cylinders, exact surface distance and gradient, vectorised (N, K)
        dx = pos[:, None, 0] - cyl[None, :, 0]
        dy = pos[:, None, 1] - cyl[None, :, 1]
        rho = np.hypot(dx, dy)
        radial = rho - cyl[None, :, 2]
        below = cyl[None, :, 3] - pos[:, None, 2]
        above = pos[:, None, 2] - cyl[None, :, 4]
        vert = np.maximum(below, above)
        outside = np.hypot(np.maximum(radial, 0.0), np.maximum(vert, 0.0))
        d = np.where((radial <= 0) & (vert <= 0), np.maximum(radial, vert), outside)
        with np.errstate(invalid="ignore", divide="ignore"):
            ux = np.where(rho > 1e-9, dx / rho, 1.0)
            uy = np.where(rho > 1e-9, dy / rho, 0.0)
            rw = np.maximum(radial, 0.0)
            vw = np.maximum(vert, 0.0)
            norm = np.hypot(rw, vw)
            gr = np.where(norm > 1e-12, rw / np.maximum(norm, 1e-12), 1.0)
            gz = np.where(norm > 1e-12, vw / np.maximum(norm, 1e-12), 0.0)
            gz = np.where(below > above, -gz, gz)
        dd = np.maximum(d, 0.05)
        mag = np.where(d < d0, k * (1.0 / dd - 1.0 / d0) / (dd * dd), 0.0)
        out[:, 0] += np.sum(mag * gr * ux, axis=1)
        out[:, 1] += np.sum(mag * gr * uy, axis=1)
        out[:, 2] += np.sum(mag * gz, axis=1)
    rest = World(
        cylinders=np.zeros((0, 5)), rings=world.rings, boxes=world.boxes, ground_z=world.ground_z
    )
    if rest.n_primitives or rest.ground_z is not None:
        d, g = rest.distance(pos)
        dd = np.maximum(d, 0.05)
        mag = np.where(d < d0, k * (1.0 / dd - 1.0 / d0) / (dd * dd), 0.0)
        out += mag[:, None] * g
    return out


def _peer_repulsion(pos: np.ndarray, d0: float, k: float) -> np.ndarray:
    diff = pos[:, None, :] - pos[None, :, :]
    dist = np.linalg.norm(diff, axis=2)
    np.fill_diagonal(dist, np.inf)
    dd = np.maximum(dist, 0.05)
    mag = np.where(dist < d0, k * (1.0 / dd - 1.0 / d0) / (dd * dd), 0.0)
    return np.sum((mag / dd)[:, :, None] * diff, axis=1)


def _const(v: np.ndarray) -> Callable[[], np.ndarray]:
    return lambda: v


def run_virtual_structure(
    cfg: SimConfig,
    params: VirtualStructureParams | None = None,
    progress: Callable[[float, float], None] | None = None,
) -> SimResult:
    """Fly ``cfg.formation`` through ``cfg.world`` with the virtual-structure controller."""
    vp = params or VirtualStructureParams()
    wall0 = time.perf_counter()
    world, starts, goals = build_flight(cfg)
    t_limit = (
        cfg.time_limit_s
        if cfg.time_limit_s is not None
        else default_time_limit_s(starts, goals, cfg.params.v_max_m_s)
    )
    mon = FlightMonitor(
        world,
        goals,
        cfg.formation.points,
        MonitorConfig(
            dt_s=cfg.dt_s,
            sample_period_s=cfg.sample_period_s,
            goal_tolerance_m=cfg.goal_tolerance_m,
            arrival_speed_m_s=cfg.arrival_speed_m_s,
            collision_obstacle_m=cfg.collision_obstacle_m,
            collision_drone_m=cfg.collision_drone_m,
            max_events=cfg.max_events,
        ),
    )
    c_start = starts.mean(axis=0)
    c_goal = goals.mean(axis=0)
    off_start = starts - c_start
    off_goal = goals - c_goal
    path = c_goal - c_start
    length = float(np.linalg.norm(path))
    u = path / length if length > 0 else np.zeros(3)
    s_struct = 0.0  # distance the structure has travelled
    pos = starts.astype(np.float64).copy()
    vel = np.zeros_like(pos)
    dt = cfg.dt_s
    v_max = cfg.params.v_max_m_s
    step_ms: list[float] = []
    t = 0.0
    timed_out = True
    progress_every = max(1, int(round(1.0 / dt)))
    for k in range(int(math.ceil(t_limit / dt)) + 1):
        t = k * dt
        if mon.step(k, t, pos, _const(vel)):
            timed_out = False
            break
        c0 = time.perf_counter()
        frac = s_struct / length if length > 0 else 1.0
        slots = c_start + s_struct * u + (1.0 - frac) * off_start + frac * off_goal
        err = float(np.mean(np.linalg.norm(slots - pos, axis=1)))
        speed = vp.structure_speed_fraction * v_max * max(0.1, 1.0 - err / vp.slowdown_m)
        v_struct = u * speed if s_struct < length else np.zeros(3)
        cmd = v_struct + vp.k_slot * (slots - pos)
        cmd += _repulsion(world, pos, cfg.sensing_radius_m, vp.obstacle_influence_m, vp.k_obstacle)
        cmd += _peer_repulsion(pos, vp.peer_influence_m, vp.k_peer)
        sp = np.linalg.norm(cmd, axis=1, keepdims=True)
        cmd = np.where(sp > v_max, cmd * (v_max / np.maximum(sp, 1e-12)), cmd)
        dv = cmd - vel
        dvn = np.linalg.norm(dv, axis=1, keepdims=True)
        lim = vp.a_max_m_s2 * dt
        dv = np.where(dvn > lim, dv * (lim / np.maximum(dvn, 1e-12)), dv)
        vel = vel + dv
        pos = pos + vel * dt
        s_struct = min(length, s_struct + speed * dt)
        step_ms.append((time.perf_counter() - c0) * 1e3)
        if progress is not None and k % progress_every == 0:
            progress(t, t_limit)
    return result_from_monitor(
        cfg,
        mon,
        mon.arrived(pos, vel),
        world,
        starts,
        goals,
        t,
        timed_out,
        replan_ms=step_ms,
        iterations=[],
        evaluations=[],
        status_counts={},
        wall_s=time.perf_counter() - wall0,
        warmup_s=0.0,
        config={"method": "virtual-structure", "params": dataclasses.asdict(vp)},
    )
