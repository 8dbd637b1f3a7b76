"""The global occupancy grid of one map, assembled from its keyframes' local grids at their
optimised poses (RTAB-Map's OccupancyGrid::assemble, written from its description;
docs/grid.md).

The grid frame: z along the map's up direction (the mean up of its oldest `grid.frame_nodes`
keyframes whose up came from a floor (their own, or the session's mean of them) or an
accelerometer, else of all), x along the map's x axis
made horizontal, z = 0 on their median floor. `map_to_grid` is that rigid transform (grid ←
map). A local grid is placed by warping its cell image with the 2-D affine map of
`map_to_grid @ pose @ T_cam_local` (nearest cell, so no holes at any rotation) into a patch of
the global grid in absolute cell indices.

Cells keep counts, not clamped log-odds: `hits` (keyframes that saw an obstacle there) and
`misses` (keyframes that saw it free). A cell's probability is the sigmoid of hits ·
logodds(prob_hit) + misses · logodds(prob_miss), clamped to [prob_clamping_min, max]:
unknown with no count, occupied above `occupancy_thr`, else free. Counts make the assembly
order-free and exactly reversible: a keyframe whose optimised pose moved more than
`grid.update_error` is taken out at its old placement and added at its new one, and a new
keyframe is added, so after a loop closure the grid is the one assembled from scratch from
the corrected poses (with update_error 0 bit for bit; with the default, keyframes that moved
less than 1 cm keep their placement). A change of the grid frame (one of its keyframes moved)
rebuilds the grid. Cells within `grid.footprint_radius` of a keyframe's position are free in
the image (the camera was there; RTAB-Map's GridGlobal/FootprintRadius), whatever their counts.

"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..config import GridConfig
from .local import FREE, OCCUPIED, LocalGrid

#: State values of an assembled grid (ROS nav_msgs/OccupancyGrid's).
G_UNKNOWN, G_FREE, G_OCCUPIED = -1, 0, 100

_GROW = 64  # cells of margin when the grid's arrays grow


def logodds(p: float) -> float:
    return math.log(p / (1.0 - p))


def grid_frame(poses: np.ndarray, T_cam_local: np.ndarray) -> np.ndarray:
    """map_to_grid (grid ← map, 4×4) from keyframe poses (N, 4, 4) and their local frames."""
    T = poses @ T_cam_local
    up = T[:, :3, 2].sum(axis=0)
    up /= np.linalg.norm(up)
    ex = np.array([1.0, 0.0, 0.0])
    ex = ex - (ex @ up) * up
    if np.linalg.norm(ex) < 0.3:  # the map's x nearly vertical: its z made horizontal
        ex = np.array([0.0, 0.0, 1.0]) - up[2] * up
    ex /= np.linalg.norm(ex)
    ey = np.cross(up, ex)
    M = np.eye(4)
    M[0, :3], M[1, :3], M[2, :3] = ex, ey, up
    M[2, 3] = -float(np.median(T[:, :3, 3] @ up))
    return M


@dataclass
class GridImage:
    """An assembled grid: `states` (H, W) int8, row 0 at the lowest y: -1 unknown, 0 free,
    100 occupied; `origin` (x, y) of cell [0, 0]'s lower-left corner in the grid frame (m);
    `map_to_grid` grid ← map (4×4)."""

    states: np.ndarray
    resolution: float
    origin: tuple[float, float]
    map_to_grid: np.ndarray
    keyframes: int = 0
    #: what was made of this image (REST's encoded answers), dropped with it when the grid changes
    encoded: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def width(self) -> int:
        return int(self.states.shape[1])

    @property
    def height(self) -> int:
        return int(self.states.shape[0])

    def cell_of(self, xy) -> tuple[int, int]:
        """(row, column) of a grid-frame point (may be outside)."""
        return (int(math.floor((xy[1] - self.origin[1]) / self.resolution)),
                int(math.floor((xy[0] - self.origin[0]) / self.resolution)))

    def to_grid(self, p_map) -> np.ndarray:
        """Map-frame points (..., 3) in the grid frame."""
        p = np.asarray(p_map, np.float64)
        return p @ self.map_to_grid[:3, :3].T + self.map_to_grid[:3, 3]

    def resampled(self, resolution: float) -> "GridImage":
        """The same grid at another resolution, on cells aligned to the grid frame's origin:
        coarser cells take the most telling state of the cells they cover (occupied, then
        free, then unknown), finer ones the state of the cell they lie in."""
        r = float(resolution)
        if abs(r - self.resolution) < 1e-9:
            return self
        x0 = math.floor(self.origin[0] / r + 1e-9)
        y0 = math.floor(self.origin[1] / r + 1e-9)
        x1 = math.ceil((self.origin[0] + self.width * self.resolution) / r - 1e-9)
        y1 = math.ceil((self.origin[1] + self.height * self.resolution) / r - 1e-9)
        W, H = max(1, x1 - x0), max(1, y1 - y0)
        rank = np.array([0, 1, 2], np.int8)  # unknown, free, occupied
        src = np.where(self.states == G_OCCUPIED, 2, np.where(self.states == G_FREE, 1, 0)).astype(np.int8)
        out = np.zeros((H, W), np.int8)
        if r > self.resolution:  # coarser: every source cell into the target cell of its centre
            iy, ix = np.mgrid[0:self.height, 0:self.width]
            tx = np.floor((self.origin[0] + (ix + 0.5) * self.resolution) / r).astype(np.int64) - x0
            ty = np.floor((self.origin[1] + (iy + 0.5) * self.resolution) / r).astype(np.int64) - y0
            ok = (tx >= 0) & (tx < W) & (ty >= 0) & (ty < H)
            np.maximum.at(out, (ty[ok], tx[ok]), src[ok])
        else:  # finer: each target cell takes the source cell of its centre
            ty, tx = np.mgrid[0:H, 0:W]
            sx = np.floor(((x0 + tx + 0.5) * r - self.origin[0]) / self.resolution).astype(np.int64)
            sy = np.floor(((y0 + ty + 0.5) * r - self.origin[1]) / self.resolution).astype(np.int64)
            ok = (sx >= 0) & (sx < self.width) & (sy >= 0) & (sy < self.height)
            out[ok] = src[sy[ok], sx[ok]]
        states = np.array([G_UNKNOWN, G_FREE, G_OCCUPIED], np.int8)[rank[out]]
        return GridImage(states, r, (x0 * r, y0 * r), self.map_to_grid, self.keyframes)


class GlobalGrid:
    """One map's grid, kept up to date by `update` (new, moved and removed keyframes only)."""

    def __init__(self, config: GridConfig, resolution: float | None = None):
        self.config = config
        self.resolution = float(resolution or config.cell_size)
        self._clear()

    def _clear(self) -> None:
        """Empty: no frame, no keyframe placed, no counts (the config and resolution stay)."""
        self.map_to_grid: np.ndarray | None = None
        self._frame_key: tuple | None = None  # (frame node ids, their poses at the frame's making)
        self._pids = np.zeros(0, np.int64)  # the keyframes placed, ascending ...
        self._pposes = np.zeros((0, 4, 4))  # ... at these poses (taking one out warps it again: the same patch)
        self._grid_of: dict[int, LocalGrid] = {}  # ... with these local grids
        self.hits = np.zeros((0, 0), np.int32)
        self.misses = np.zeros((0, 0), np.int32)
        self.ox = self.oy = 0  # absolute cell index of [0, 0]
        self.rebuilds = 0
        self.placements = 0  # local grids placed (added) so far
        self._image: GridImage | None = None  # the last image, until the grid changes

    # -- which keyframes moved --------------------------------------------------------------------
    def _moved(self, old: np.ndarray, new: np.ndarray) -> np.ndarray:
        ue = self.config.update_error
        dt = np.linalg.norm(old[:, :3, 3] - new[:, :3, 3], axis=1)
        cos = (np.einsum("nij,nij->n", old[:, :3, :3], new[:, :3, :3]) - 1.0) / 2.0
        ang = np.arccos(np.clip(cos, -1.0, 1.0))
        if ue <= 0:
            return np.any(old != new, axis=(1, 2))
        return (dt > ue) | (ang > ue)

    def _frame_for(self, ids: np.ndarray, poses: np.ndarray, good: np.ndarray) -> tuple:
        use = np.flatnonzero(good) if good.any() else np.arange(len(ids))
        use = use[: max(1, self.config.frame_nodes)]
        return ids[use], poses[use]

    def update(self, ids, poses, grids: Mapping[int, LocalGrid], known: np.ndarray | None = None,
               good: np.ndarray | None = None, on_plan: Callable[[int], None] | None = None) -> dict:
        """Bring the grid to these keyframes (ids ascending) at these poses (N, 4, 4); `grids`
        holds the local grid of each (those without one are left out). `known` (the sorted ids
        that have one) and `good` (per id: its up came from a floor or an accelerometer) save
        looking each up (a 20k-keyframe map: ~40 ms); `on_plan` is told how many local grids
        it is about to place or take out. Returns counts of what it did; only the keyframes
        new, moved or gone are touched."""
        ids = np.asarray(ids, np.int64)
        poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
        if known is None:
            keep = np.fromiter((int(n) in grids for n in ids), bool, len(ids))
        else:
            keep = np.isin(ids, known, assume_unique=True)
        if not keep.all():
            ids, poses = ids[keep], poses[keep]
            good = None if good is None else np.asarray(good, bool)[keep]
        stats = {"added": 0, "moved": 0, "removed": 0, "rebuilt": False}
        if len(ids) == 0:
            self._clear()
            return stats
        if good is None:
            good = np.fromiter((grids[int(n)].up_source != "config" for n in ids), bool, len(ids))
        fids, fposes = self._frame_for(ids, poses, good)
        key_ok = (self._frame_key is not None and np.array_equal(self._frame_key[0], fids)
                  and not self._moved(self._frame_key[1], fposes).any())
        if not key_ok:
            rebuilds = self.rebuilds + 1
            self._clear()
            self.rebuilds = rebuilds
            self.map_to_grid = grid_frame(fposes, np.stack([grids[int(n)].T_cam_local for n in fids]))
            self._frame_key = (fids, fposes)
            stats["rebuilt"] = True
        pids, pposes = self._pids, self._pposes  # placed: sorted ids, the poses they were placed at
        gone = np.setdiff1d(pids, ids, assume_unique=True)
        common, i_new, i_old = np.intersect1d(ids, pids, assume_unique=True, return_indices=True)
        moved = self._moved(pposes[i_old], poses[i_new]) if len(common) else np.zeros(0, bool)
        fresh = ~np.isin(ids, pids, assume_unique=True)
        stats.update(added=int(fresh.sum()), moved=int(moved.sum()), removed=len(gone))
        full = stats["rebuilt"]
        if not full and 2 * (len(gone) + moved.sum()) > len(pids):
            # most keyframes moved (a loop closure): adding them all to empty counts is half the
            # work of taking each out and adding it again, and the same counts
            rebuilds, frame, key = self.rebuilds + 1, self.map_to_grid, self._frame_key
            self._clear()
            self.rebuilds, self.map_to_grid, self._frame_key = rebuilds, frame, key
            stats["rebuilt"] = full = True
        if on_plan is not None:
            on_plan(len(ids) if full else len(gone) + 2 * int(moved.sum()) + int(fresh.sum()))
        placed = poses.copy()
        if full:
            self._place(ids, poses, grids)
        else:
            if len(gone):
                i = np.searchsorted(pids, gone)
                self._apply(pposes[i], [self._grid_of.pop(n) for n in gone.tolist()], -1)
            k = np.flatnonzero(moved)
            if len(k):
                self._apply(pposes[i_old[k]], [self._grid_of[int(n)] for n in common[k]], -1)
                self._place(common[k], poses[i_new[k]], grids)
            i = np.flatnonzero(fresh)
            if len(i):
                self._place(ids[i], poses[i], grids)
            still = ~moved  # moved too little to place again: they stay where they were placed
            placed[i_new[still]] = pposes[i_old[still]]
        self._pids, self._pposes = ids.copy(), placed
        if stats["added"] or stats["moved"] or stats["removed"] or stats["rebuilt"]:
            self._image = None
        return stats

    # -- placing local grids --------------------------------------------------------------------------
    def _affines(self, poses: np.ndarray, gs: list[LocalGrid]) -> tuple[np.ndarray, np.ndarray]:
        """For K keyframes at `poses` (K, 4, 4) with local grids `gs`: the 2×3 affine maps
        (K, 2, 3) of each local grid's pixel (u, v) to its patch of absolute global cells,
        and the patches' boxes (K, 4): x0, y0, x1, y1 (inclusive), all in one go."""
        assert self.map_to_grid is not None  # (`update` makes the frame before it places a keyframe)
        K = len(gs)
        Tcl = np.stack([g.T_cam_local for g in gs])
        T = self.map_to_grid @ poses @ Tcl
        A, b = T[:, :2, :2], T[:, :2, 3]
        r = self.resolution
        cs = np.array([g.cell_size for g in gs])
        o = np.array([[(g.origin_x + 0.5) * g.cell_size, (g.origin_y + 0.5) * g.cell_size] for g in gs])
        hw = np.array([g.shape for g in gs], np.float64)
        M = np.empty((K, 2, 3))
        M[:, :, :2] = A * (cs / r)[:, None, None]
        M[:, :, 2] = np.einsum("kij,kj->ki", A, o) / r + b / r - 0.5
        # local pixel (u, v) -> absolute global cell coordinates (cell centres at integers)
        h, w = hw[:, 0], hw[:, 1]
        cu = np.stack([np.full(K, -0.5), w - 0.5, np.full(K, -0.5), w - 0.5], axis=1)
        cv = np.stack([np.full(K, -0.5), np.full(K, -0.5), h - 0.5, h - 0.5], axis=1)
        cx = M[:, 0, :1] * cu + M[:, 0, 1:2] * cv + M[:, 0, 2:]
        cy = M[:, 1, :1] * cu + M[:, 1, 1:2] * cv + M[:, 1, 2:]
        box = np.floor(np.stack([cx.min(1), cy.min(1), cx.max(1), cy.max(1)], axis=1) + 0.5).astype(np.int64)
        return M, box

    def _ensure(self, x0: int, y0: int, x1: int, y1: int) -> None:
        """Grow the arrays to hold absolute cells [x0, x1) × [y0, y1)."""
        H, W = self.hits.shape
        if H and x0 >= self.ox and y0 >= self.oy and x1 <= self.ox + W and y1 <= self.oy + H:
            return
        nx0 = min(x0, self.ox) - _GROW if H else x0 - _GROW
        ny0 = min(y0, self.oy) - _GROW if H else y0 - _GROW
        nx1 = max(x1, self.ox + W) + _GROW if H else x1 + _GROW
        ny1 = max(y1, self.oy + H) + _GROW if H else y1 + _GROW
        hits = np.zeros((ny1 - ny0, nx1 - nx0), np.int32)
        misses = np.zeros_like(hits)
        if H:
            hits[self.oy - ny0:self.oy - ny0 + H, self.ox - nx0:self.ox - nx0 + W] = self.hits
            misses[self.oy - ny0:self.oy - ny0 + H, self.ox - nx0:self.ox - nx0 + W] = self.misses
        self.hits, self.misses, self.ox, self.oy = hits, misses, nx0, ny0

    def _apply(self, poses: np.ndarray, gs: list[LocalGrid], sign: int) -> None:
        """Add (sign +1) or take out (-1) the local grids `gs` at `poses`: the geometry of all at
        once (`_affines`), the arrays grown once, then each grid's cell image warped (nearest
        cell: no holes at any rotation, the same patch every time for the same pose) and
        counted in."""
        if not gs:
            return
        M, box = self._affines(np.asarray(poses, np.float64).reshape(-1, 4, 4), gs)
        self._ensure(int(box[:, 0].min()), int(box[:, 1].min()), int(box[:, 2].max()) + 1, int(box[:, 3].max()) + 1)
        M[:, 0, 2] -= box[:, 0]
        M[:, 1, 2] -= box[:, 1]
        box[:, 0::2] -= self.ox
        box[:, 1::2] -= self.oy
        hits, misses = self.hits, self.misses
        warp, nearest, const = cv2.warpAffine, cv2.INTER_NEAREST, cv2.BORDER_CONSTANT
        for g, Mk, (x0, y0, x1, y1) in zip(gs, M, box.tolist()):
            patch = warp(g.cells, Mk, (x1 - x0 + 1, y1 - y0 + 1), flags=nearest, borderMode=const, borderValue=0)
            sy, sx = slice(y0, y1 + 1), slice(x0, x1 + 1)
            if sign > 0:
                hits[sy, sx] += patch == OCCUPIED
                misses[sy, sx] += patch == FREE
            else:
                hits[sy, sx] -= patch == OCCUPIED
                misses[sy, sx] -= patch == FREE

    def _place(self, ids: np.ndarray, poses: np.ndarray, grids: Mapping[int, LocalGrid]) -> None:
        gs = [grids[n] for n in ids.tolist()]
        self._apply(poses, gs, +1)
        self._grid_of.update(zip(ids.tolist(), gs))
        self.placements += len(gs)

    # -- the grid -------------------------------------------------------------------------------------
    @property
    def keyframes(self) -> int:
        return len(self._pids)

    def probabilities(self) -> np.ndarray:
        cfg = self.config
        L = self.hits * logodds(cfg.prob_hit) + self.misses * logodds(cfg.prob_miss)
        L = np.clip(L, logodds(cfg.prob_clamping_min), logodds(cfg.prob_clamping_max))
        return 1.0 / (1.0 + np.exp(-L))

    def _under_keyframes(self, map_to_grid: np.ndarray) -> np.ndarray:
        """Mask (array cells) within footprint_radius of a placed keyframe's position
        (`map_to_grid`: the grid's frame)."""
        cfg, r = self.config, self.resolution
        under = np.zeros(self.hits.shape, np.uint8)
        if cfg.footprint_radius <= 0 or not len(self._pids):
            return under.astype(bool)
        xy = self._pposes[:, :3, 3] @ map_to_grid[:2, :3].T + map_to_grid[:2, 3]
        col = np.floor(xy[:, 0] / r).astype(np.int64) - self.ox
        row = np.floor(xy[:, 1] / r).astype(np.int64) - self.oy
        ok = (row >= 0) & (row < under.shape[0]) & (col >= 0) & (col < under.shape[1])
        under[row[ok], col[ok]] = 1
        k = int(math.ceil(cfg.footprint_radius / r))
        yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
        disk = ((xx * xx + yy * yy) * r * r <= cfg.footprint_radius ** 2).astype(np.uint8)
        return cv2.dilate(under, disk) > 0

    def image(self) -> GridImage:
        """The grid's states over the box of its known cells (kept until the grid changes)."""
        if self._image is None:
            self._image = self._make_image()
        return self._image

    def _make_image(self) -> GridImage:
        M = self.map_to_grid
        if M is None:  # no keyframe yet
            return GridImage(np.full((0, 0), G_UNKNOWN, np.int8), self.resolution, (0.0, 0.0), np.eye(4), 0)
        under = self._under_keyframes(M)
        known = (self.hits > 0) | (self.misses > 0) | under
        if not known.any():
            return GridImage(np.full((0, 0), G_UNKNOWN, np.int8), self.resolution, (0.0, 0.0), M, 0)
        rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
        sy, sx = slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)
        cfg = self.config
        L = self.hits[sy, sx] * logodds(cfg.prob_hit) + self.misses[sy, sx] * logodds(cfg.prob_miss)
        L = np.clip(L, logodds(cfg.prob_clamping_min), logodds(cfg.prob_clamping_max))
        states = np.where(L > logodds(cfg.occupancy_thr), G_OCCUPIED, G_FREE).astype(np.int8)
        states[~known[sy, sx]] = G_UNKNOWN
        states[under[sy, sx]] = G_FREE  # the camera was there (GridGlobal/FootprintRadius)
        r = self.resolution
        return GridImage(states, r, ((self.ox + cols[0]) * r, (self.oy + rows[0]) * r), M.copy(), self.keyframes)

    def counts(self) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """(hits, misses, (ox, oy)) cropped to the known cells, for comparisons."""
        known = (self.hits > 0) | (self.misses > 0)
        if not known.any():
            return np.zeros((0, 0), np.int32), np.zeros((0, 0), np.int32), (0, 0)
        rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
        sy, sx = slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)
        return self.hits[sy, sx].copy(), self.misses[sy, sx].copy(), (self.ox + cols[0], self.oy + rows[0])
