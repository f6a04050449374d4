"""Figures of simulated flights (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection, PatchCollection  # noqa: E402
from matplotlib.patches import Circle, Rectangle  # noqa: E402

if TYPE_CHECKING:
    from gcs.fastsim import SimResult
    from onboard.world import World


def _draw_world(ax: Any, world: World, cluttered_x: tuple[float, float]) -> np.ndarray:
    """Cylinders as disks, rings as footprint segments, boxes as rectangles, the cluttered span
    shaded; returns the cylinders (for axis limits)."""
    lo, hi = cluttered_x
    ax.axvspan(lo, hi, color="0.93", zorder=0, label="cluttered area")
    cyl = world.cylinders
    if cyl.shape[0]:
        disks = [Circle((c[0], c[1]), c[2]) for c in cyl]
        ax.add_collection(
            PatchCollection(disks, facecolor="0.35", edgecolor="0.15", linewidth=0.5, zorder=2)
        )
    rings = world.rings
    if rings.shape[0]:
        segs = []
        for cx, cy, _cz, yaw, rh, _rv, _tube in rings:
            u = np.array([-math.sin(yaw), math.cos(yaw)])
            c = np.array([cx, cy])
            segs.append([c - rh * u, c + rh * u])
        ax.add_collection(LineCollection(segs, colors="tab:brown", linewidths=3.0, zorder=2))
    boxes = world.boxes
    if boxes.shape[0]:
        rects = [Rectangle((b[0], b[1]), b[3] - b[0], b[4] - b[1]) for b in boxes]
        ax.add_collection(
            PatchCollection(rects, facecolor="0.55", edgecolor="0.15", linewidth=0.5, zorder=2)
        )
    return cyl


def _save(fig: Any, path: str | Path) -> Path:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def plot_snapshots(
    result: SimResult, path: str | Path, count: int = 8, title: str | None = None
) -> Path:
    """Top view with the formation's outline (convex hull of the drones, dots at the drones)
    at ``count`` regular times while the swarm crosses the cluttered span."""
    from scipy.spatial import ConvexHull

    fig, ax = plt.subplots(figsize=(12, 6), dpi=120)
    _draw_world(ax, result.world, result.cluttered_x)
    pos = result.tracks.pos
    if pos.shape[0]:
        cx = pos[:, :, 0].mean(axis=1)
        lo, hi = result.cluttered_x
        inside = np.flatnonzero((cx >= lo - 2.0) & (cx <= hi + 2.0))
        idx = inside if inside.size else np.arange(pos.shape[0])
        picks = np.unique(np.linspace(idx[0], idx[-1], count).round().astype(int))
        cmap = plt.get_cmap("viridis")
        for j, k in enumerate(picks):
            pts = pos[k, :, :2]
            color = cmap(j / max(len(picks) - 1, 1))
            try:
                hull = ConvexHull(pts)
                ring = np.append(hull.vertices, hull.vertices[0])
                ax.plot(pts[ring, 0], pts[ring, 1], "-", color=color, linewidth=1.5, zorder=3)
            except Exception:  # degenerate (collinear) formation: no hull to draw
                pass
            ax.plot(pts[:, 0], pts[:, 1], "o", color=color, markersize=4, zorder=4)
            ax.annotate(
                f"{result.tracks.t[k]:.0f} s",
                (float(pts[:, 0].mean()), float(pts[:, 1].max()) + 0.4),
                fontsize=7,
                ha="center",
            )
        all_pts = pos[:, :, :2].reshape(-1, 2)
        ax.set_xlim(float(all_pts[:, 0].min()) - 1.5, float(all_pts[:, 0].max()) + 1.5)
        ax.set_ylim(float(all_pts[:, 1].min()) - 1.5, float(all_pts[:, 1].max()) + 1.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.set_title(
        title or f"formation snapshots: {result.formation_name}, seed {result.seed}", fontsize=9
    )
    ax.grid(True, linewidth=0.3, alpha=0.5)
    fig.tight_layout()
    return _save(fig, path)


def plot_esim(results: Mapping[str, SimResult], path: str | Path, title: str = "") -> Path:
    """e_sim over time, one line per labelled flight."""
    fig, ax = plt.subplots(figsize=(10, 4), dpi=120)
    for label, r in results.items():
        tr = r.tracks
        if tr.t.size:
            ax.plot(tr.t, tr.e_sim, linewidth=1.2, label=label)
    ax.set_ylim(bottom=0.0)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("e_sim (formation similarity metric)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, linewidth=0.3, alpha=0.5)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def plot_top_view(result: SimResult, path: str | Path, title: str | None = None) -> Path:
    """Top view (x east, y north) of a flight, saved to ``path`` (PNG, PDF, SVG by suffix).

    Cylinders as disks, rings as their horizontal footprint segments, boxes as rectangles,
    every drone's track in its own colour with start (circle) and goal (cross), the cluttered
    x span shaded, collision events marked in red. Equal aspect.
    """
    world = result.world
    fig, ax = plt.subplots(figsize=(12, 6), dpi=120)
    cyl = _draw_world(ax, world, result.cluttered_x)

    pos = result.tracks.pos  # (T, N, 3)
    n = result.starts.shape[0]
    cmap = plt.get_cmap("tab10" if n <= 10 else "tab20")
    for i in range(n):
        color = cmap(i % cmap.N)
        if pos.shape[0]:
            ax.plot(pos[:, i, 0], pos[:, i, 1], color=color, linewidth=1.2, zorder=3)
        ax.plot(*result.starts[i, :2], "o", color=color, markersize=5, zorder=4)
        ax.plot(*result.goals[i, :2], "x", color=color, markersize=7, mew=2, zorder=4)
    for ev in result.events:
        k = int(np.searchsorted(result.tracks.t, ev.t_s)) if result.tracks.t.size else 0
        k = min(k, max(pos.shape[0] - 1, 0))
        if pos.shape[0]:
            for i in ev.ids:
                ax.plot(*pos[k, i, :2], "o", mfc="none", mec="red", markersize=12, zorder=5)

    pts = np.concatenate(
        [result.starts[:, :2], result.goals[:, :2], pos[:, :, :2].reshape(-1, 2)]
        + ([cyl[:, :2]] if cyl.shape[0] else [])
    )
    margin = 1.5
    ax.set_xlim(float(pts[:, 0].min()) - margin, float(pts[:, 0].max()) + margin)
    ax.set_ylim(float(pts[:, 1].min()) - margin, float(pts[:, 1].max()) + margin)
    ax.set_aspect("equal")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    if title is None:
        outcome = "success" if result.success else "FAILED"
        title = (
            f"{result.formation_name} through {result.world_name} (seed {result.seed}): "
            f"{outcome}, {result.collisions} collisions, "
            f"min clearance {result.min_obstacle_clearance_m:.2f} m, "
            f"e_sim mean {result.e_sim_mean:.4f}"
        )
    ax.set_title(title, fontsize=9)
    ax.grid(True, linewidth=0.3, alpha=0.5)
    fig.tight_layout()
    return _save(fig, path)
