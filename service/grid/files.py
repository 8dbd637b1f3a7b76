"""Grids and clouds as files: map_server PGM + YAML (and PNG, JSON) of an assembled grid, the
synthetic scene's true floor plan in the same frame, and the agreement of two grids.

PGM / PNG: occupied 0 (black), free 254, unknown 205, first row the grid's top (largest y),
as ROS map_server reads them with `negate: 0`, `occupied_thresh: 0.65`, `free_thresh: 0.196`.
The YAML's `origin` is [x, y, yaw] of the lower-left cell's corner in the grid frame; it
also carries `map_to_grid`, the row-major 4×4 transform grid ← map (the SLAM map frame, in
which the keyframe poses and REST positions are).
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from .assembly import G_FREE, G_OCCUPIED, G_UNKNOWN, GridImage

PGM_FREE, PGM_OCCUPIED, PGM_UNKNOWN = 254, 0, 205
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196


def grid_pixels(grid: GridImage) -> np.ndarray:
    """The grid as a uint8 image, top row = largest y (map_server's values)."""
    img = np.full(grid.states.shape, PGM_UNKNOWN, np.uint8)
    img[grid.states == G_FREE] = PGM_FREE
    img[grid.states == G_OCCUPIED] = PGM_OCCUPIED
    return np.ascontiguousarray(img[::-1])


def pgm_bytes(grid: GridImage) -> bytes:
    img = grid_pixels(grid)
    h, w = img.shape
    return f"P5\n{w} {h}\n255\n".encode() + img.tobytes()


def png_bytes(grid: GridImage) -> bytes:
    ok, buf = cv2.imencode(".png", grid_pixels(grid))
    if not ok:  # pragma: no cover
        raise ValueError("cannot encode the grid as PNG")
    return buf.tobytes()


def map_yaml_fields(grid: GridImage, image: str = "grid.pgm") -> dict:
    """map_server's YAML fields, plus `map_to_grid` (grid ← map, row-major 4×4)."""
    return {"image": image, "resolution": float(grid.resolution),
            "origin": [float(grid.origin[0]), float(grid.origin[1]), 0.0], "negate": 0,
            "occupied_thresh": OCCUPIED_THRESH, "free_thresh": FREE_THRESH,
            "map_to_grid": [float(v) for v in np.asarray(grid.map_to_grid).reshape(-1)]}


def map_yaml(grid: GridImage, image: str = "grid.pgm") -> str:
    f = map_yaml_fields(grid, image)
    m = ", ".join(f"{v:.9g}" for v in f["map_to_grid"])
    return (f"image: {f['image']}\nresolution: {f['resolution']:.9g}\n"
            f"origin: [{f['origin'][0]:.9g}, {f['origin'][1]:.9g}, 0.0]\nnegate: 0\n"
            f"occupied_thresh: {OCCUPIED_THRESH}\nfree_thresh: {FREE_THRESH}\nmap_to_grid: [{m}]\n")


def grid_json(grid: GridImage) -> dict:
    """The grid as ROS's nav_msgs/OccupancyGrid has it (data row-major from the origin cell,
    -1 unknown, 0 free, 100 occupied) with the YAML fields."""
    return {**map_yaml_fields(grid, ""), "width": grid.width, "height": grid.height, "keyframes": grid.keyframes,
            "data": grid.states.reshape(-1).astype(int).tolist()}


def write_grid(out_dir: str | Path, grid: GridImage, name: str = "grid") -> tuple[Path, Path]:
    """DIR/<name>.pgm and DIR/<name>.yaml."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pgm, yml = out / f"{name}.pgm", out / f"{name}.yaml"
    pgm.write_bytes(pgm_bytes(grid))
    yml.write_text(map_yaml(grid, pgm.name))
    return pgm, yml


def read_grid(yaml_path: str | Path) -> GridImage:
    """A grid written by `write_grid` (its PGM and YAML) read back."""
    import yaml

    y = yaml.safe_load(Path(yaml_path).read_text())
    pgm = Path(yaml_path).with_name(y["image"])
    img = cv2.imread(str(pgm), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise OSError(f"cannot read the grid image {pgm}")
    img = img[::-1]
    states = np.full(img.shape, G_UNKNOWN, np.int8)
    states[img == PGM_FREE] = G_FREE
    states[img == PGM_OCCUPIED] = G_OCCUPIED
    M = np.array(y.get("map_to_grid", np.eye(4).reshape(-1)), np.float64).reshape(4, 4)
    return GridImage(states, float(y["resolution"]), (float(y["origin"][0]), float(y["origin"][1])), M)


# -- the synthetic scene's floor plan ------------------------------------------------------------
def groundtruth_grid(scene, like: GridImage, world_from_map: np.ndarray, heights=(0.1, 0.3, 0.6, 1.0, 1.4, 1.8),
                     margin: float = 0.5) -> GridImage:
    """The scene's true floor plan on the cells of `like` (same frame, resolution and origin,
    extended by `margin` m): a cell is occupied when a wall or an object stands at its centre
    at any of `heights` above the floor, free when none does, unknown outside the building.
    `world_from_map` is the scene's world ← the SLAM map frame (the map's first keyframe's true
    pose times the inverse of its estimated one, or an alignment of the trajectories)."""
    r = like.resolution
    ext = int(round(margin / r))
    H, W = like.height + 2 * ext, like.width + 2 * ext
    ox, oy = like.origin[0] - ext * r, like.origin[1] - ext * r
    iy, ix = np.mgrid[0:H, 0:W]
    gx, gy = ox + (ix.ravel() + 0.5) * r, oy + (iy.ravel() + 0.5) * r
    grid_to_world = world_from_map @ np.linalg.inv(like.map_to_grid)
    occupied = np.zeros(H * W, bool)
    inside = np.zeros(H * W, bool)
    lo = np.min([v[0] for v in scene.rooms.values()], axis=0)
    hi = np.max([v[1] for v in scene.rooms.values()], axis=0)
    for z in heights:
        p = np.column_stack([gx, gy, np.full(len(gx), z), np.ones(len(gx))]) @ grid_to_world.T
        occupied |= ~scene.inside_free_space(p[:, :3])
        inside |= np.all((p[:, :2] >= lo[:2]) & (p[:, :2] <= hi[:2]), axis=1)
    states = np.where(occupied, G_OCCUPIED, G_FREE).astype(np.int8)
    states[~inside] = G_UNKNOWN
    return GridImage(states.reshape(H, W), r, (ox, oy), like.map_to_grid.copy())


def agreement(grid: GridImage, truth: GridImage, slack: int = 1) -> dict:
    """How many of `grid`'s observed cells (free or occupied) the truth agrees with: a cell
    agrees when a truth cell with its state lies within `slack` cells (a wall one cell off,
    from the cell size or a centimetre of drift, still agrees). Both on the same cells (same
    resolution, origins a whole number of cells apart)."""
    r = grid.resolution
    dx = int(round((grid.origin[0] - truth.origin[0]) / r))
    dy = int(round((grid.origin[1] - truth.origin[1]) / r))
    H, W = grid.states.shape
    t = np.full((H + 2 * slack, W + 2 * slack), G_UNKNOWN, np.int8)
    # the truth over grid's cells (plus slack), unknown beyond it
    ys, xs = dy - slack, dx - slack
    src_y0, src_x0 = max(0, ys), max(0, xs)
    src_y1, src_x1 = min(truth.height, ys + H + 2 * slack), min(truth.width, xs + W + 2 * slack)
    if src_y1 > src_y0 and src_x1 > src_x0:
        t[src_y0 - ys:src_y1 - ys, src_x0 - xs:src_x1 - xs] = truth.states[src_y0:src_y1, src_x0:src_x1]
    k = np.ones((2 * slack + 1, 2 * slack + 1), np.uint8)
    near_occ = cv2.dilate((t == G_OCCUPIED).astype(np.uint8), k)[slack:slack + H, slack:slack + W] > 0
    near_free = cv2.dilate((t == G_FREE).astype(np.uint8), k)[slack:slack + H, slack:slack + W] > 0
    occ, free = grid.states == G_OCCUPIED, grid.states == G_FREE
    ok_occ, ok_free = int((occ & near_occ).sum()), int((free & near_free).sum())
    n_occ, n_free = int(occ.sum()), int(free.sum())
    return {"observed": n_occ + n_free, "agree": (ok_occ + ok_free) / max(1, n_occ + n_free),
            "occupied": n_occ, "occupied_agree": ok_occ / max(1, n_occ),
            "free": n_free, "free_agree": ok_free / max(1, n_free)}


def write_map_files(store, out_dir: str | Path, config, voxel: float = 0.02, cloud: bool = True) -> dict[int, dict]:
    """Each map's grid (DIR/grid.pgm + grid.yaml) and cloud (DIR/cloud.ply) of a store; with
    several maps each file gets the map's id (grid_map1.pgm, ...). Returns {map id: {"grid":
    GridImage, "files": [paths]}}."""
    from .cloud import map_cloud, ply_bytes
    from .maps import MapGrids, NoMap

    out = Path(out_dir)
    grids = MapGrids(store, config)
    maps = sorted(m for m in grids.maps() if m >= 0)
    done: dict[int, dict] = {}
    for m in maps:
        suffix = "" if len(maps) == 1 else f"_map{m}"
        paths: list[Path] = []
        try:
            grid = grids.grid(m)
        except NoMap:
            continue
        paths += write_grid(out, grid, f"grid{suffix}")
        if cloud:
            ids, poses = grids.keyframes(m)
            P, C = map_cloud(store, ids, poses, voxel)
            if len(P):
                (out / f"cloud{suffix}.ply").write_bytes(ply_bytes(P, C))
                paths.append(out / f"cloud{suffix}.ply")
        done[m] = {"grid": grid, "files": paths}
    return done


def write_json(path: Path, data) -> None:
    path.write_text(json.dumps(data, indent=1) + "\n")
