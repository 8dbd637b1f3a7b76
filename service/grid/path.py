"""Paths on an occupancy grid: A* over 8-connected cells that keep `robot_radius` from
every occupied cell (free cells only, or unknown ones too with `grid.path_unknown`), then
shortened by line of sight (string pulling), so a path crosses a room straight, not in 45°
steps. Start and goal snap to the nearest cell the robot may stand on (a robot standing next
to a wall, an object that is itself an obstacle)."""
from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import cv2
import numpy as np

from .assembly import G_FREE, G_OCCUPIED, G_UNKNOWN, GridImage

SQRT2 = math.sqrt(2.0)


class NoPath(LookupError):
    """No path: the reason is the message."""


@dataclass
class GridPath:
    cells: np.ndarray  # (K, 2) int (row, column) of the shortened path's corners
    points: np.ndarray  # (K, 2) grid-frame x, y (m) of their centres
    length: float  # m, along the shortened path
    start_snap: float  # m from the given start to the start cell
    goal_snap: float  # m from the given goal to the goal cell


def traversable(grid: GridImage, robot_radius: float, unknown: bool = False) -> np.ndarray:
    """Cells a robot of that radius may stand on."""
    ok = (grid.states == G_FREE) | ((grid.states == G_UNKNOWN) if unknown else False)
    occ = (grid.states != G_OCCUPIED).astype(np.uint8)
    if robot_radius > 0 and occ.size:
        dist = cv2.distanceTransform(occ, cv2.DIST_L2, 5) * grid.resolution
        ok &= dist > robot_radius
    return ok


def _snap(ok: np.ndarray, rc: tuple[int, int], max_cells: float) -> tuple[int, int] | None:
    rows, cols = np.nonzero(ok)
    if len(rows) == 0:
        return None
    d2 = (rows - rc[0]) ** 2 + (cols - rc[1]) ** 2
    i = int(np.argmin(d2))
    return (int(rows[i]), int(cols[i])) if d2[i] <= max_cells ** 2 else None


def astar(ok: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]] | None:
    """The shortest 8-connected path of `ok` cells (no corner cutting), or None."""
    H, W = ok.shape
    gr, gc = goal
    g = np.full(H * W, np.inf)
    parent = np.full(H * W, -1, np.int64)
    s = start[0] * W + start[1]
    g[s] = 0.0
    okf = ok.ravel()
    heap = [(0.0, s)]
    steps = ((0, 1, 1.0), (1, 0, 1.0), (0, -1, 1.0), (-1, 0, 1.0),
             (1, 1, SQRT2), (1, -1, SQRT2), (-1, 1, SQRT2), (-1, -1, SQRT2))
    goal_i = gr * W + gc
    closed = np.zeros(H * W, bool)
    while heap:
        _, i = heapq.heappop(heap)
        if closed[i]:
            continue
        if i == goal_i:
            break
        closed[i] = True
        r, c = divmod(i, W)
        gi = g[i]
        for dr, dc, cost in steps:
            rr, cc = r + dr, c + dc
            if rr < 0 or rr >= H or cc < 0 or cc >= W:
                continue
            j = rr * W + cc
            if not okf[j] or closed[j]:
                continue
            if dr and dc and not (okf[r * W + cc] and okf[rr * W + c]):
                continue  # no squeezing between two blocked cells diagonally
            ng = gi + cost
            if ng < g[j]:
                g[j] = ng
                parent[j] = i
                dy, dx = abs(rr - gr), abs(cc - gc)
                h = (dx + dy) + (SQRT2 - 2.0) * min(dx, dy)
                heapq.heappush(heap, (ng + h, j))
    if not np.isfinite(g[goal_i]):
        return None
    out, i = [], goal_i
    while i != -1:
        out.append(divmod(int(i), W))
        i = parent[i]
    return out[::-1]


def _clear(ok: np.ndarray, a, b) -> bool:
    n = int(max(abs(b[0] - a[0]), abs(b[1] - a[1])) * 2) + 1
    t = np.linspace(0.0, 1.0, n + 1)
    r = np.rint(a[0] + (b[0] - a[0]) * t).astype(np.int64)
    c = np.rint(a[1] + (b[1] - a[1]) * t).astype(np.int64)
    return bool(ok[r, c].all())


def shorten(ok: np.ndarray, cells: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """String pulling: from each corner, straight to the farthest later cell in sight."""
    if len(cells) <= 2:
        return list(cells)
    out, i = [cells[0]], 0
    while i < len(cells) - 1:
        j = len(cells) - 1
        while j > i + 1 and not _clear(ok, cells[i], cells[j]):
            j -= 1
        out.append(cells[j])
        i = j
    return out


def plan(grid: GridImage, start_xy, goal_xy, robot_radius: float, unknown: bool = False,
         start_snap: float = 0.5, goal_snap: float = 1.5) -> GridPath:
    """A path on `grid` from a grid-frame point to another (NoPath with the reason)."""
    if grid.states.size == 0:
        raise NoPath("the map's grid is empty")
    ok = traversable(grid, robot_radius, unknown)
    r = grid.resolution
    s_rc, g_rc = grid.cell_of(start_xy), grid.cell_of(goal_xy)
    s = _snap(ok, s_rc, start_snap / r)
    if s is None:
        raise NoPath(f"no free cell within {start_snap} m of the start (it is outside the observed free space, or "
                     f"closer than grid.robot_radius {robot_radius} m to obstacles)")
    g = _snap(ok, g_rc, goal_snap / r)
    if g is None:
        raise NoPath(f"no free cell within {goal_snap} m of the goal (not observed free yet, or walled in)")
    cells = astar(ok, s, g)
    if cells is None:
        raise NoPath("the goal is not reachable from the start through free cells (a closed door, or space not "
                     "observed yet between them)")
    short = shorten(ok, cells)
    rc = np.array(short, np.float64)
    pts = np.column_stack([grid.origin[0] + (rc[:, 1] + 0.5) * r, grid.origin[1] + (rc[:, 0] + 0.5) * r])
    length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
    sp = np.array([grid.origin[0] + (s[1] + 0.5) * r, grid.origin[1] + (s[0] + 0.5) * r])
    gp = np.array([grid.origin[0] + (g[1] + 0.5) * r, grid.origin[1] + (g[0] + 0.5) * r])
    return GridPath(np.array(short, np.int64), pts, length, float(np.linalg.norm(sp - np.asarray(start_xy[:2]))),
                    float(np.linalg.norm(gp - np.asarray(goal_xy[:2]))))
