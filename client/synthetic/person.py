"""A person walking through the synthetic scene (issue 24): the scene's one dynamic thing.

The person is a textured box (legs, torso, a head: axis-aligned boxes of clothes and skin
fabric) labelled `person` (ADE20K-32 id 13) with an instance id of its own, walking to and
fro along a straight line on the floor at a steady pace (`Walk`). It moves between frames,
so it is what a static map must leave out: the camera's labels mark it `person`, its depth
and colour occlude the scene behind it like any other surface.

`Person.composite(result, pose, camera, t)` renders the person at time `t` into a rendered
view of the static scene (its own quads, shifted by the person's position, z-tested against
the scene's depth); only the pixels its box projects to are rendered (a crop of the camera).
`SyntheticDataset(..., person=True)` (or `open_dataset("synthetic:loop?person")`) adds it to
every frame along the trajectory's `PathSpec.person` walk, or along a `Walk` given; without
it the frames are the static scene's, bit for bit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..kernel.frames import PinholeCamera
from . import textures as tx
from .raster import NEAR, Rasterizer, RenderResult, detail_offsets
from .scene import TEXEL_OBJECT, _Builder, _pack, quad_set

PERSON = 13  # ADE20K-32 "person"
HEIGHT = 1.75  # m, head top
LEGS, SHOULDERS = 0.85, 1.5  # m: trousers up to LEGS, shirt up to SHOULDERS, head above
WIDTH, DEPTH, HEAD = 0.44, 0.28, 0.2  # m: across and along the walking direction, head side


@dataclass(frozen=True)
class Walk:
    """A walk to and fro along the floor from `start` to `end` ((x, y), metres) at `speed`
    (m/s), `phase` seconds into it at t = 0 (a phase of one leg's time starts at `end`)."""

    start: tuple
    end: tuple
    speed: float = 0.5
    phase: float = 0.0

    @property
    def length(self) -> float:
        return float(math.dist(self.start, self.end))

    def position(self, t: float) -> np.ndarray:
        """(x, y) of the body's centre at time t (s)."""
        a, b = np.asarray(self.start, float), np.asarray(self.end, float)
        if self.length <= 0 or self.speed <= 0:
            return a
        s = ((t + self.phase) * self.speed) % (2 * self.length)  # distance walked in this cycle
        return a + (b - a) * (s if s <= self.length else 2 * self.length - s) / self.length


class Person:
    """The walking person of one scene seed: its quads (in its own frame: feet centre at the
    origin, z up), textures and renderer. Build once and reuse (`SyntheticDataset` does)."""

    def __init__(self, walk: Walk, seed: int = 0, instance_id: int = 1000, detail: np.ndarray | None = None):
        self.walk = walk
        self.instance_id = int(instance_id)
        bd = _Builder([int(seed), 0x9E4503])  # its own textures: the scene's stay as they are
        dx, dy = np.subtract(walk.end, walk.start)
        across_x = abs(dy) > abs(dx)  # walking along y: the shoulders (WIDTH) along x
        wx, wy = (WIDTH, DEPTH) if across_x else (DEPTH, WIDTH)
        rng = bd.child_rng()
        shirt = tx.random_colour(rng, (70, 190), 0.7)
        trousers = tx.random_colour(rng, (35, 80), 0.4)
        skin = (125, 160, 200)  # BGR

        def fabric(colour):
            return lambda f, w, h, n: bd.region(tx.fabric, w, h, TEXEL_OBJECT, n, colour=colour)
        iid = self.instance_id
        bd.box((-wx / 2, -wy / 2, 0.0), (wx / 2, wy / 2, LEGS), PERSON, iid, fabric(trousers), skip=("-z", "+z"))
        bd.box((-wx / 2, -wy / 2, LEGS), (wx / 2, wy / 2, SHOULDERS), PERSON, iid, fabric(shirt), skip=("-z",))
        bd.box((-HEAD / 2, -HEAD / 2, SHOULDERS), (HEAD / 2, HEAD / 2, HEIGHT), PERSON, iid, fabric(skin),
               skip=("-z",))
        self.quads = quad_set(bd, _pack(bd.regions), detail, detail_offsets(int(seed) + 0x9E45, len(bd.quads)))
        self._raster = Rasterizer(self.quads)
        self.corners = np.array([[x, y, z] for x in (-wx / 2, wx / 2) for y in (-wy / 2, wy / 2)
                                 for z in (0.0, HEIGHT)])

    def position(self, t: float) -> np.ndarray:
        """World (x, y, 0) of the person's feet centre at time t (s)."""
        return np.append(self.walk.position(t), 0.0)

    def composite(self, r: RenderResult, pose: np.ndarray, camera: PinholeCamera, t: float,
                  rgb: bool = True) -> RenderResult:
        """The view `r` of the static scene (at camera-to-world `pose`) with the person at time
        t drawn in where it is nearer than the scene (`rgb` False: `r` has no colour image, as
        `render(rgb=False)` gives). `r` is not changed."""
        at = self.position(t)
        window = self._window(pose, camera, at)
        if window is None:
            return r
        u0, v0, u1, v1 = window
        crop = PinholeCamera(camera.fx, camera.fy, camera.cx - u0, camera.cy - v0, u1 - u0, v1 - v0)
        shifted = np.array(pose, np.float64)
        shifted[:3, 3] -= at  # the person's frame moves with it: the camera moves the other way
        p = self._raster.render(shifted, crop, rgb=rgb, incidence=r.incidence is not None)
        sub = (slice(v0, v1), slice(u0, u1))
        mine = (p.depth > 0) & ((r.depth[sub] <= 0) | (p.depth < r.depth[sub]))
        if not mine.any():
            return r
        out = replace(r, rgb=r.rgb.copy(), depth=r.depth.copy(), labels=r.labels.copy(), instances=r.instances.copy(),
                      surface=r.surface.copy(), incidence=None if r.incidence is None else r.incidence.copy())
        for name in ("rgb", "depth", "labels", "instances", "incidence"):
            dst = getattr(out, name)
            if dst is not None and (name != "rgb" or rgb):
                dst[sub][mine] = getattr(p, name)[mine]
        out.surface[sub][mine] = 0  # (not a quad of the scene)
        return out

    def _window(self, pose: np.ndarray, camera: PinholeCamera, at: np.ndarray):
        """(u0, v0, u1, v1): the pixels the person's box may cover (the whole image when it
        crosses the near plane), None when it is out of view."""
        R, C = np.asarray(pose, float)[:3, :3], np.asarray(pose, float)[:3, 3]
        X = (self.corners + at - C) @ R  # camera frame
        z = X[:, 2]
        W, H = camera.width, camera.height
        if z.max() <= NEAR:
            return None
        if z.min() <= NEAR:
            return 0, 0, W, H
        u = camera.fx * X[:, 0] / z + camera.cx
        v = camera.fy * X[:, 1] / z + camera.cy
        u0, u1 = max(0, int(math.floor(u.min())) - 1), min(W, int(math.ceil(u.max())) + 2)
        v0, v1 = max(0, int(math.floor(v.min())) - 1), min(H, int(math.ceil(v.max())) + 2)
        if u0 >= u1 or v0 >= v1:
            return None
        return u0, v0, u1, v1
