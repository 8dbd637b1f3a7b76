"""The synthetic indoor scene: a living room, an office and a hall, built from axis-aligned
quads and boxes with procedural textures.

World frame: z up, metres. Layout (interior dimensions, walls 0.1 m thick between spaces):

      y
    7.3 +-----------------------------------------------------+
        | hall: front door W, door E, 6 identical posters N    |
    5.1 +------+     +-----------+---------+     +-------------+
        |     x 2.0..3.2         |       x 8.0..9.2            |
        | living room            |  office                     |
        | door W, sofa, coffee   |  dining table + 4 chairs,   |
        | table, bookshelf,      +  shelf, sideboard, door E   |
        | chair, TV cabinet   y 1.8..3.2                       |
        |                        +                             |
      0 +---window---window------+------window-----------------+
        0                        6 6.1                       11.1  x

Doorways (open, 2.2 m high): living<->office at x 6..6.1, y 1.8..3.2; living<->hall at
x 2.0..3.2; office<->hall at x 8.0..9.2 (both through the wall y 5..5.1). Rooms are 2.6 m high.

Semantic class ids are those of the project's ADE20K-32 model (`CLASS_NAMES`); walls, floors
and ceilings have instance id 0, every object (door, window, painting, furniture, light) has
its own instance id, listed in `SyntheticScene.objects` with its world bounding box.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import textures as tx
from .raster import QuadSet, Rasterizer, RenderResult, detail_offsets, detail_table

CLASS_NAMES: dict[int, str] = {
    0: "other", 1: "wall", 4: "floor", 6: "ceiling", 9: "windowpane", 11: "cabinet", 13: "person", 15: "door",
    16: "table", 20: "chair", 23: "painting", 24: "sofa", 25: "shelf",
}  # (13 "person": only the walking person of `person.py`, when a dataset adds it)
OTHER, WALL, FLOOR, CEILING, WINDOW, CABINET, DOOR, TABLE, CHAIR, PAINTING, SOFA, SHELF = (
    0, 1, 4, 6, 9, 11, 15, 16, 20, 23, 24, 25)

HEIGHT = 2.6  # room height
DOOR_TOP = 2.2  # open doorways
PAD = 2  # texels of texture around every region (bilinear lookups never bleed)
ATLAS_WIDTH = 4096
TEXEL_WALL, TEXEL_FLOOR, TEXEL_CEILING, TEXEL_OBJECT = 0.008, 0.01, 0.0125, 0.005

LIGHT = np.array([-0.35, -0.5, 0.8]) / np.linalg.norm([-0.35, -0.5, 0.8])


def lambert(normal) -> float:
    """Half-Lambert shading of a surface orientation (ambient 0.65)."""
    return 0.65 + 0.35 * (0.5 + 0.5 * float(np.dot(normal, LIGHT)))


@dataclass(frozen=True)
class SceneObject:
    """A thing in the scene (not wall/floor/ceiling), with its world axis-aligned bounding box."""

    instance_id: int
    class_id: int
    name: str
    bbox_min: tuple
    bbox_max: tuple
    room: str

    @property
    def class_name(self) -> str:
        return CLASS_NAMES[self.class_id]

    @property
    def center(self) -> np.ndarray:
        return (np.asarray(self.bbox_min) + np.asarray(self.bbox_max)) / 2


@dataclass
class _Region:
    image: np.ndarray
    texel: float
    ox: int = 0
    oy: int = 0


def _flip(axis: int, sign: int) -> int:
    """+1 if the texture's x runs to the viewer's right along the quad's first in-plane axis."""
    return {(0, 1): 1, (0, -1): -1, (1, 1): -1, (1, -1): 1, (2, 1): 1, (2, -1): -1}[(axis, sign)]


def _others(axis: int) -> tuple[int, int]:
    return {0: (1, 2), 1: (0, 2), 2: (0, 1)}[axis]


class Builder:
    def __init__(self, seed: int):
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.regions: list[_Region] = []
        self.quads: list[dict] = []
        self.objects: list[SceneObject] = []
        self.next_instance = 1

    # -- textures
    def child_rng(self) -> np.random.Generator:
        return np.random.default_rng(self.rng.integers(1 << 62))

    def region(self, gen: Callable, w_m: float, h_m: float, texel: float, normal, rng=None, **kw) -> int:
        rng = rng or self.child_rng()
        w = int(math.ceil(w_m / texel)) + 1 + 2 * PAD
        h = int(math.ceil(h_m / texel)) + 1 + 2 * PAD
        img = gen(rng, h, w, texel, **kw)
        img = tx.shade(img, lambert(normal), rng, texel)
        self.regions.append(_Region(img, texel))
        return len(self.regions) - 1

    # -- geometry
    def quad(self, axis, c, sign, r1, r2, region, label, instance=0, origin=None):
        """Quad in plane X[axis]=c facing sign*axis, spanning r1 x r2 in the other two axes
        (x,y,z order). `origin` = (b0, b1, d1) extent the region's texture covers (default:
        the quad itself), so pieces of one wall share one continuous texture."""
        b, d = _others(axis)
        lo, hi = [0.0] * 3, [0.0] * 3
        lo[axis] = hi[axis] = c
        lo[b], hi[b] = r1
        lo[d], hi[d] = r2
        ob0, ob1, od1 = origin if origin is not None else (r1[0], r1[1], r2[1])
        self.quads.append(dict(axis=axis, c=c, sign=sign, lo=lo, hi=hi, region=region, label=label,
                               instance=instance, flip=_flip(axis, sign), ob=(ob0 if _flip(axis, sign) > 0 else ob1),
                               od=od1))

    def box(self, lo, hi, label, instance, face_tex: Callable, skip=("-z",)):
        """Axis-aligned box; face_tex(face, w_m, h_m, normal) -> region id. Faces named
        '+x','-x','+y','-y','+z','-z' (bottom skipped by default: boxes stand on the floor)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        for axis in range(3):
            b, d = _others(axis)
            for sign in (1, -1):
                name = ("+" if sign > 0 else "-") + "xyz"[axis]
                if name in skip:
                    continue
                c = hi[axis] if sign > 0 else lo[axis]
                normal = np.zeros(3)
                normal[axis] = sign
                reg = face_tex(name, hi[b] - lo[b], hi[d] - lo[d], normal)
                self.quad(axis, c, sign, (lo[b], hi[b]), (lo[d], hi[d]), reg, label, instance)

    def new_object(self, class_id, name, lo, hi, room) -> int:
        iid = self.next_instance
        self.next_instance += 1
        self.objects.append(SceneObject(iid, class_id, name, tuple(float(x) for x in lo),
                                        tuple(float(x) for x in hi), room))
        return iid

    # -- architecture
    def wall(self, axis, c, sign, span, openings=(), gen=tx.wall, label=WALL):
        """A full-height wall face with doorway openings [(b0, b1, top)], one texture."""
        normal = np.zeros(3)
        normal[axis] = sign
        reg = self.region(gen, span[1] - span[0], HEIGHT, TEXEL_WALL, normal)
        origin = (span[0], span[1], HEIGHT)
        b = span[0]
        for o0, o1, top in sorted(openings):
            if o0 > b:
                self.quad(axis, c, sign, (b, o0), (0.0, HEIGHT), reg, label, 0, origin)
            self.quad(axis, c, sign, (o0, o1), (top, HEIGHT), reg, label, 0, origin)
            b = o1
        if b < span[1]:
            self.quad(axis, c, sign, (b, span[1]), (0.0, HEIGHT), reg, label, 0, origin)

    def doorway(self, axis, c0, c1, b0, b1, top=DOOR_TOP):
        """The reveal of an opening through a thick wall (normal `axis`, from c0 to c1)."""
        b = _others(axis)[0]  # the horizontal in-wall axis (x or y)
        def jamb_tex():
            return self.region(tx.wall, c1 - c0, top, TEXEL_WALL, np.eye(3)[b])
        r = jamb_tex()
        rng_c = (c0, c1)
        # jambs: planes X[b] = b0 (facing +b) and b1 (facing -b); their in-plane axes are
        # (axis, z) when b is x/y and axis is y/x
        self.quad(b, b0, 1, *self._jamb_ranges(axis, b, rng_c, top), r, WALL)
        self.quad(b, b1, -1, *self._jamb_ranges(axis, b, rng_c, top), jamb_tex(), WALL)
        # lintel underside and threshold
        xr, yr = ((c0, c1), (b0, b1)) if axis == 0 else ((b0, b1), (c0, c1))
        self.quad(2, top, -1, xr, yr, self.region(tx.wall, xr[1] - xr[0], yr[1] - yr[0], TEXEL_WALL, (0, 0, -1)), WALL)
        self.quad(2, 0.0, 1, xr, yr, self.region(tx.wood, xr[1] - xr[0], yr[1] - yr[0], TEXEL_FLOOR, (0, 0, 1)), FLOOR)

    @staticmethod
    def _jamb_ranges(axis, b, rng_c, top):
        # quad on plane X[b]: its in-plane axes are _others(b); one is `axis`, the other z
        o = _others(b)
        return (rng_c, (0.0, top)) if o[0] == axis else ((0.0, top), rng_c)

    # -- wall-mounted things
    def door(self, room, axis, c, sign, b0, b1, height=2.05, colour=None):
        rng = self.child_rng()
        colour = colour or [(215, 215, 210), (60, 95, 140), (90, 90, 95), (150, 110, 70),
                            (40, 70, 110)][int(rng.integers(5))]
        normal = np.zeros(3)
        normal[axis] = sign
        cas = 0.08
        lo, hi = np.zeros(3), np.zeros(3)
        b, d = _others(axis)
        lo[b], hi[b], lo[d], hi[d] = b0 - cas, b1 + cas, 0.0, height + cas
        lo[axis], hi[axis] = sorted((c, c + sign * 0.09))
        iid = self.new_object(DOOR, f"door_{sum(o.class_id == DOOR for o in self.objects) + 1}", lo, hi, room)
        rc = self.region(tx.casing, b1 - b0 + 2 * cas, height + cas, TEXEL_OBJECT, normal, rng, door_colour=colour)
        self.quad(axis, c + sign * 0.012, sign, (b0 - cas, b1 + cas), (0.0, height + cas), rc, DOOR, iid)
        rp = self.region(tx.door_panel, b1 - b0, height, TEXEL_OBJECT, normal, rng, colour=colour)
        self.quad(axis, c + sign * 0.02, sign, (b0, b1), (0.0, height), rp, DOOR, iid)
        # handle: a rosette plate and a lever (small box)
        hb = b1 - 0.09 if rng.random() < 0.5 else b0 + 0.09
        rm = self.region(tx.metal, 0.06, 0.22, TEXEL_OBJECT, normal, rng)
        self.quad(axis, c + sign * 0.026, sign, (hb - 0.03, hb + 0.03), (0.88, 1.10), rm, DOOR, iid)
        blo, bhi = np.zeros(3), np.zeros(3)
        blo[axis], bhi[axis] = sorted((c + sign * 0.026, c + sign * 0.085))
        lever = 0.13 if hb < (b0 + b1) / 2 else -0.13
        blo[b], bhi[b] = sorted((hb, hb + lever))
        blo[d], bhi[d] = 0.98, 1.01
        self.box(blo, bhi, DOOR, iid,
                 lambda f, w, h, n: self.region(tx.metal, w, h, TEXEL_OBJECT, n, colour=(40, 40, 45)), skip=())

    def window(self, room, axis, c, sign, b0, b1, z0, z1, panes=2):
        normal = np.zeros(3)
        normal[axis] = sign
        fr = 0.06
        b, d = _others(axis)
        lo, hi = np.zeros(3), np.zeros(3)
        lo[b], hi[b], lo[d], hi[d] = b0 - fr - 0.08, b1 + fr + 0.08, z0 - 0.1, z1 + fr
        lo[axis], hi[axis] = sorted((c, c + sign * 0.2))
        iid = self.new_object(WINDOW, f"window_{sum(o.class_id == WINDOW for o in self.objects) + 1}", lo, hi, room)
        rf = self.region(tx.window_frame, b1 - b0 + 2 * fr, z1 - z0 + 2 * fr, TEXEL_OBJECT, normal)
        self.quad(axis, c + sign * 0.01, sign, (b0 - fr, b1 + fr), (z0 - fr, z1 + fr), rf, WINDOW, iid)
        rg = self.region(tx.glass, b1 - b0, z1 - z0, TEXEL_OBJECT, normal)
        origin = (b0, b1, z1)
        mull = 0.05
        pw = (b1 - b0 - (panes - 1) * mull) / panes
        for k in range(panes):
            p0 = b0 + k * (pw + mull)
            self.quad(axis, c + sign * 0.015, sign, (p0, p0 + pw), (z0, z1), rg, WINDOW, iid, origin)
        # sill
        slo, shi = np.zeros(3), np.zeros(3)
        slo[axis], shi[axis] = sorted((c, c + sign * 0.2))
        slo[b], shi[b] = b0 - fr - 0.08, b1 + fr + 0.08
        slo[d], shi[d] = z0 - 0.1, z0 - fr
        self.box(slo, shi, WINDOW, iid, lambda f, w, h, n: self.region(tx.window_frame, w, h, TEXEL_OBJECT, n),
                 skip=("-z", ("-" if sign > 0 else "+") + "xyz"[axis]))

    def painting(self, room, axis, c, sign, b0, b1, z0, z1, regions=None, name="painting"):
        normal = np.zeros(3)
        normal[axis] = sign
        fr = 0.04
        b, d = _others(axis)
        lo, hi = np.zeros(3), np.zeros(3)
        lo[b], hi[b], lo[d], hi[d] = b0 - fr, b1 + fr, z0 - fr, z1 + fr
        lo[axis], hi[axis] = sorted((c, c + sign * 0.025))
        iid = self.new_object(PAINTING, f"{name}_{sum(o.class_id == PAINTING for o in self.objects) + 1}", lo, hi, room)
        if regions is None:
            regions = (self.region(tx.picture_frame, b1 - b0 + 2 * fr, z1 - z0 + 2 * fr, TEXEL_OBJECT, normal),
                       self.region(tx.painting, b1 - b0, z1 - z0, TEXEL_OBJECT, normal))
        self.quad(axis, c + sign * 0.012, sign, (b0 - fr, b1 + fr), (z0 - fr, z1 + fr), regions[0], PAINTING, iid)
        self.quad(axis, c + sign * 0.022, sign, (b0, b1), (z0, z1), regions[1], PAINTING, iid)
        return regions

    def ceiling_light(self, room, x, y, size=0.6):
        lo = (x - size / 2, y - size / 2, HEIGHT - 0.04)
        hi = (x + size / 2, y + size / 2, HEIGHT)
        n_lights = sum(o.name.startswith("ceiling_light") for o in self.objects)
        iid = self.new_object(OTHER, f"ceiling_light_{n_lights + 1}", lo, hi, room)
        def tex(f, w, h, n):
            if f == "-z":
                return self.region(tx.light_panel, w, h, TEXEL_OBJECT, n)
            return self.region(tx.metal, w, h, TEXEL_OBJECT, n, colour=(200, 200, 200))
        self.box(lo, hi, OTHER, iid, tex, skip=("+z",))

    # -- furniture
    def table(self, room, x0, y0, x1, y1, h, name="table"):
        iid = self.new_object(TABLE, name, (x0, y0, 0), (x1, y1, h), room)
        rng = self.child_rng()
        colour = tx.WOODS[int(rng.integers(len(tx.WOODS)))]
        def tex(f, w, hh, n):
            return self.region(tx.wood, w, hh, TEXEL_OBJECT, n, colour=colour)
        self.box((x0, y0, h - 0.04), (x1, y1, h), TABLE, iid, tex, skip=())
        leg = 0.05
        for lx in (x0 + 0.04, x1 - 0.04 - leg):
            for ly in (y0 + 0.04, y1 - 0.04 - leg):
                self.box((lx, ly, 0), (lx + leg, ly + leg, h - 0.04), TABLE, iid, tex, skip=("-z", "+z"))

    def chair(self, room, cx, cy, back: str):
        """Chair centred at (cx, cy); `back` = side of the backrest ('+x','-x','+y','-y')."""
        s = 0.42
        x0, y0, x1, y1 = cx - s / 2, cy - s / 2, cx + s / 2, cy + s / 2
        iid = self.new_object(CHAIR, f"chair_{sum(o.class_id == CHAIR for o in self.objects) + 1}",
                              (x0, y0, 0), (x1, y1, 0.92), room)
        rng = self.child_rng()
        colour = tx.random_colour(rng, (50, 170), 0.7)
        def tex(f, w, h, n):
            return self.region(tx.fabric if f == "+z" else tx.wood, w, h, TEXEL_OBJECT, n, colour=colour)
        self.box((x0, y0, 0.42), (x1, y1, 0.47), CHAIR, iid, tex, skip=())
        leg = 0.035
        for lx in (x0 + 0.01, x1 - 0.01 - leg):
            for ly in (y0 + 0.01, y1 - 0.01 - leg):
                self.box((lx, ly, 0), (lx + leg, ly + leg, 0.42), CHAIR, iid, tex, skip=("-z", "+z"))
        t = 0.04
        blo, bhi = [x0, y0, 0.47], [x1, y1, 0.92]
        ax = "xy".index(back[1])
        if back[0] == "+":
            blo[ax] = bhi[ax] - t
        else:
            bhi[ax] = blo[ax] + t
        self.box(blo, bhi, CHAIR, iid, tex, skip=("-z",))

    def sofa(self, room, x0, y0, x1, y1, back: str):
        iid = self.new_object(SOFA, "sofa", (x0, y0, 0), (x1, y1, 0.85), room)
        rng = self.child_rng()
        colour = tx.FABRICS[int(rng.integers(len(tx.FABRICS)))]
        ax = "xy".index(back[1])
        def tex(f, w, h, n):
            cushions = 3 if f in ("+z", "+x", "-x", "+y", "-y") and max(w, h) > 1.2 else 0
            return self.region(tx.fabric, w, h, TEXEL_OBJECT, n, colour=colour, cushions=cushions)
        self.box((x0, y0, 0), (x1, y1, 0.42), SOFA, iid, tex)
        lo, hi = [x0, y0, 0.42], [x1, y1, 0.85]
        if back[0] == "+":
            lo[ax] = hi[ax] - 0.22
        else:
            hi[ax] = lo[ax] + 0.22
        self.box(lo, hi, SOFA, iid, tex)
        oth = 1 - ax
        for end in (0, 1):
            alo, ahi = [x0, y0, 0.42], [x1, y1, 0.62]
            if end == 0:
                ahi[oth] = alo[oth] + 0.18
            else:
                alo[oth] = ahi[oth] - 0.18
            self.box(alo, ahi, SOFA, iid, tex)

    def shelf(self, room, lo, hi, front: str, name="shelf"):
        iid = self.new_object(SHELF, name, lo, hi, room)
        rng = self.child_rng()
        colour = tx.WOODS[int(rng.integers(len(tx.WOODS)))]
        def tex(f, w, h, n):
            return self.region(tx.bookshelf_front if f == front else tx.wood, w, h, TEXEL_OBJECT, n, colour=colour)
        back = ("-" if front[0] == "+" else "+") + front[1]
        self.box(lo, hi, SHELF, iid, tex, skip=("-z", back))

    def cabinet(self, room, lo, hi, front: str, name="cabinet"):
        iid = self.new_object(CABINET, name, lo, hi, room)
        rng = self.child_rng()
        colour = tx.random_colour(rng, (60, 210), 0.4)
        def tex(f, w, h, n):
            return self.region(tx.cabinet_front if f == front else tx.wood, w, h, TEXEL_OBJECT, n, colour=colour)
        back = ("-" if front[0] == "+" else "+") + front[1]
        self.box(lo, hi, CABINET, iid, tex, skip=("-z", back))


# ------------------------------------------------------------------------------- the layout
ROOMS = {
    "living": ((0.0, 0.0, 0.0), (6.0, 5.0, HEIGHT)),
    "office": ((6.1, 0.0, 0.0), (11.1, 5.0, HEIGHT)),
    "hall": ((0.0, 5.1, 0.0), (11.1, 7.3, HEIGHT)),
}
DOORWAYS = {
    "living-office": ((6.0, 1.8, 0.0), (6.1, 3.2, DOOR_TOP)),
    "living-hall": ((2.0, 5.0, 0.0), (3.2, 5.1, DOOR_TOP)),
    "office-hall": ((8.0, 5.0, 0.0), (9.2, 5.1, DOOR_TOP)),
}


def _build(bd: Builder) -> None:
    H = HEIGHT
    # ---- living room: x 0..6, y 0..5
    bd.wall(0, 0.0, 1, (0.0, 5.0))  # west
    bd.wall(1, 0.0, 1, (0.0, 6.0))  # south (windows)
    bd.wall(1, 5.0, -1, (0.0, 6.0), [(2.0, 3.2, DOOR_TOP)])  # north, to the hall
    bd.wall(0, 6.0, -1, (0.0, 5.0), [(1.8, 3.2, DOOR_TOP)])  # east, to the office
    r = bd.region(_floor_living, 6.0, 5.0, TEXEL_FLOOR, (0, 0, 1))
    bd.quad(2, 0.0, 1, (0.0, 6.0), (0.0, 5.0), r, FLOOR)
    bd.quad(2, H, -1, (0.0, 6.0), (0.0, 5.0), bd.region(tx.ceiling, 6.0, 5.0, TEXEL_CEILING, (0, 0, -1)), CEILING)
    # ---- office: x 6.1..11.1, y 0..5
    bd.wall(0, 6.1, 1, (0.0, 5.0), [(1.8, 3.2, DOOR_TOP)])  # west, to the living room
    bd.wall(1, 0.0, 1, (6.1, 11.1))  # south (window)
    bd.wall(1, 5.0, -1, (6.1, 11.1), [(8.0, 9.2, DOOR_TOP)])  # north, to the hall
    bd.wall(0, 11.1, -1, (0.0, 5.0))  # east (door)
    r = bd.region(tx.stone_tiles, 5.0, 5.0, TEXEL_FLOOR, (0, 0, 1))
    bd.quad(2, 0.0, 1, (6.1, 11.1), (0.0, 5.0), r, FLOOR)
    bd.quad(2, H, -1, (6.1, 11.1), (0.0, 5.0), bd.region(tx.ceiling, 5.0, 5.0, TEXEL_CEILING, (0, 0, -1)), CEILING)
    # ---- hall: x 0..11.1, y 5.1..7.3
    bd.wall(1, 5.1, 1, (0.0, 11.1), [(2.0, 3.2, DOOR_TOP), (8.0, 9.2, DOOR_TOP)])  # south
    bd.wall(1, 7.3, -1, (0.0, 11.1), gen=tx.plain_wall)  # north: the repeated posters
    bd.wall(0, 0.0, 1, (5.1, 7.3))  # west (front door)
    bd.wall(0, 11.1, -1, (5.1, 7.3))  # east (door)
    r = bd.region(_floor_hall, 11.1, 2.2, TEXEL_FLOOR, (0, 0, 1))
    bd.quad(2, 0.0, 1, (0.0, 11.1), (5.1, 7.3), r, FLOOR)
    bd.quad(2, H, -1, (0.0, 11.1), (5.1, 7.3), bd.region(tx.ceiling, 11.1, 2.2, TEXEL_CEILING, (0, 0, -1)), CEILING)
    # ---- doorway reveals
    bd.doorway(0, 6.0, 6.1, 1.8, 3.2)
    bd.doorway(1, 5.0, 5.1, 2.0, 3.2)
    bd.doorway(1, 5.0, 5.1, 8.0, 9.2)

    # ---- doors, windows, paintings
    bd.door("living", 0, 0.0, 1, 3.3, 4.2)
    bd.door("office", 0, 11.1, -1, 0.7, 1.6)
    bd.door("hall", 0, 0.0, 1, 5.7, 6.7, height=2.1)  # front door
    bd.door("hall", 0, 11.1, -1, 5.75, 6.65)
    bd.window("living", 1, 0.0, 1, 0.9, 2.2, 0.9, 2.1)
    bd.window("living", 1, 0.0, 1, 3.4, 4.7, 0.9, 2.1)
    bd.window("office", 1, 0.0, 1, 7.3, 9.3, 0.9, 2.1, panes=3)
    bd.painting("living", 0, 0.0, 1, 1.2, 2.4, 1.3, 2.0)  # above the sofa
    bd.painting("living", 1, 5.0, -1, 0.5, 1.5, 1.2, 1.9)
    bd.painting("living", 0, 6.0, -1, 0.5, 1.3, 1.2, 1.8)
    bd.painting("living", 0, 6.0, -1, 3.6, 4.6, 1.1, 1.9)
    bd.painting("office", 0, 6.1, 1, 0.4, 1.4, 1.2, 1.9)
    bd.painting("office", 1, 5.0, -1, 9.6, 10.8, 1.2, 1.9)
    bd.painting("office", 0, 11.1, -1, 3.0, 4.2, 1.35, 2.0)
    bd.painting("office", 0, 6.1, 1, 3.6, 4.6, 1.2, 1.8)
    bd.painting("hall", 1, 5.1, 1, 5.15, 6.25, 1.3, 1.9)
    # the deliberately repeated poster (same texture) along the hall's north wall
    rng = np.random.default_rng([bd.seed, 7])
    rep = (bd.region(tx.picture_frame, 0.98, 0.78, TEXEL_OBJECT, (0, -1, 0), rng),
           bd.region(tx.painting, 0.9, 0.7, TEXEL_OBJECT, (0, -1, 0), rng, style=0))
    for k in range(6):
        x = 1.0 + 1.6 * k
        bd.painting("hall", 1, 7.3, -1, x, x + 0.9, 1.25, 1.95, regions=rep, name="poster")

    # ---- furniture
    bd.sofa("living", 0.0, 0.7, 0.9, 2.9, back="-x")
    bd.table("living", 1.5, 1.4, 2.5, 2.3, 0.45, name="coffee_table")
    bd.shelf("living", (3.8, 4.62, 0.0), (5.6, 5.0, 2.0), front="-y", name="bookshelf")
    bd.cabinet("living", (5.5, 0.4, 0.0), (6.0, 1.4, 0.6), front="-x", name="tv_cabinet")
    bd.chair("living", 5.4, 3.9, back="+x")
    bd.table("office", 8.0, 1.7, 9.6, 2.7, 0.75, name="dining_table")
    for cx_, cy_, back in ((8.4, 1.45, "-y"), (9.2, 1.45, "-y"), (8.4, 2.95, "+y"), (9.2, 2.95, "+y")):
        bd.chair("office", cx_, cy_, back)
    bd.cabinet("office", (10.6, 2.8, 0.0), (11.1, 4.4, 0.9), front="-x", name="sideboard")
    bd.shelf("office", (6.4, 4.6, 0.0), (7.7, 5.0, 1.8), front="-y", name="office_shelf")
    bd.cabinet("hall", (5.0, 5.1, 0.0), (6.4, 5.45, 0.9), front="+y", name="shoe_cabinet")
    for room, x, y in (("living", 2.0, 2.5), ("living", 4.5, 2.5), ("office", 8.8, 2.2),
                       ("hall", 2.5, 6.2), ("hall", 5.5, 6.2), ("hall", 8.5, 6.2)):
        bd.ceiling_light(room, x, y, 0.5)


def _floor_living(rng, h, w, texel):
    img = tx.wood_planks(rng, h, w, texel)
    # a rug under the coffee table (floor x 1.1..3.3, y 0.9..2.8; texture rows run from y=5 down)
    tx.rug(img, rng, texel, PAD + int(1.1 / texel), PAD + int((5.0 - 2.8) / texel),
           PAD + int(3.3 / texel), PAD + int((5.0 - 0.9) / texel))
    return tx.finish(img, 0.5)


def _floor_hall(rng, h, w, texel):
    img = tx.concrete(rng, h, w, texel)
    # a long runner along the hall
    tx.rug(img, rng, texel, PAD + int(0.8 / texel), PAD + int(0.65 / texel),
           PAD + int(10.3 / texel), PAD + int(1.55 / texel))
    return tx.finish(img, 0.5)


# ------------------------------------------------------------------------------- the scene
class SyntheticScene:
    """The synthetic indoor scene for one seed: geometry, textures, objects and a renderer.

    `render(pose_c2w, camera)` returns a `RenderResult` (rgb BGR uint8, depth float32 z in
    metres, labels uint8, instances int32). Construct once and reuse (or use `get_scene(seed)`,
    which caches): the textures take ~0.5 s to generate.
    """

    rooms = ROOMS
    doorways = DOORWAYS
    height = HEIGHT

    def __init__(self, seed: int = 0):
        self.seed = int(seed)
        bd = Builder(self.seed)
        _build(bd)
        self.objects: list[SceneObject] = bd.objects
        self.atlas = pack_atlas(bd.regions)
        self.quads = quad_set(bd, self.atlas, detail_table(self.seed), detail_offsets(self.seed, len(bd.quads)))
        self._raster = Rasterizer(self.quads)

    # -- rendering
    def render(self, pose_c2w: np.ndarray, camera, rgb: bool = True, incidence: bool = False) -> RenderResult:
        """Render the view of an OpenCV pinhole camera at `pose_c2w` (4×4 camera-to-world).

        rgb=False skips the colour image (returned all zero; depth/labels are much cheaper);
        incidence=True also returns |cos| of the angle between each ray and surface normal."""
        return self._raster.render(np.asarray(pose_c2w, np.float64), camera, rgb=rgb, incidence=incidence)

    def cos_incidence(self, surface: np.ndarray, pose_c2w: np.ndarray, camera) -> np.ndarray:
        """|cos| of the angle between each pixel's ray and the normal of the surface it hits
        (`surface` = RenderResult.surface; 0 where nothing is hit)."""
        R = np.asarray(pose_c2w, np.float64)[:3, :3].astype(np.float32)
        xn = ((np.arange(camera.width) - camera.cx) / camera.fx).astype(np.float32)[None, :]
        yn = ((np.arange(camera.height) - camera.cy) / camera.fy).astype(np.float32)[:, None]
        Dx, Dy, Dz = (R[i, 0] * xn + (R[i, 1] * yn + R[i, 2]) for i in range(3))
        bY = np.take(self.quads.tex_cols[4], surface)  # normal along x
        dY = np.take(self.quads.tex_cols[5], surface)  # normal along z
        Dn = Dy + bY * (Dx - Dy) + dY * (Dz - Dy)
        out = np.abs(Dn) / np.sqrt(Dx * Dx + Dy * Dy + Dz * Dz)
        out[surface == 0] = 0.0
        return out

    # -- queries
    def objects_of_class(self, class_id: int) -> list[SceneObject]:
        return [o for o in self.objects if o.class_id == class_id]

    def object(self, instance_id: int) -> SceneObject:
        for o in self.objects:
            if o.instance_id == instance_id:
                return o
        raise KeyError(instance_id)

    def room_of(self, point) -> str | None:
        """The room (or 'doorway:<name>') containing a world point, None if outside."""
        p = np.asarray(point, float)
        for name, (lo, hi) in list(ROOMS.items()) + [("doorway:" + k, v) for k, v in DOORWAYS.items()]:
            if np.all(p >= lo) and np.all(p <= hi):
                return name
        return None

    def clearance(self, points) -> np.ndarray:
        """Distance (m) from each point (N×3) to the nearest scene surface (any quad)."""
        P = np.asarray(points, float).reshape(-1, 3)
        lo, hi = self.quads.lo, self.quads.hi
        out = np.empty(len(P))
        for i in range(0, len(P), 256):
            p = P[i:i + 256, None, :]
            dvec = p - np.clip(p, lo[None], hi[None])
            out[i:i + 256] = np.sqrt((dvec ** 2).sum(-1)).min(1)
        return out

    def inside_free_space(self, points, margin: float = 0.0) -> np.ndarray:
        """True for points inside a room or doorway and outside every object's box (+margin)."""
        P = np.asarray(points, float).reshape(-1, 3)
        inside = np.zeros(len(P), bool)
        for lo, hi in list(ROOMS.values()) + list(DOORWAYS.values()):
            inside |= np.all((P >= lo) & (P <= hi), 1)
        # each object's box tested on the points inside whose x lies within it (sorted by x)
        idx = np.flatnonzero(inside)
        idx = idx[np.argsort(P[idx, 0], kind="stable")]
        xs = P[idx, 0]
        for o in self.objects:
            lo, hi = np.subtract(o.bbox_min, margin), np.add(o.bbox_max, margin)
            near = idx[np.searchsorted(xs, lo[0], "left"):np.searchsorted(xs, hi[0], "right")]
            inside[near[np.all((P[near] >= lo) & (P[near] <= hi), 1)]] = False
        return inside


def pack_atlas(regions: list[_Region]) -> np.ndarray:
    """Shelf-pack the texture regions into one atlas (sets each region's ox, oy)."""
    order = sorted(range(len(regions)), key=lambda i: -regions[i].image.shape[0])
    x, y, shelf_h = 4, 0, 4  # keep (0..3, 0..3) black for 'nothing hit'
    placements = {}
    for i in order:
        h, w = regions[i].image.shape[:2]
        if w > ATLAS_WIDTH:
            raise ValueError(f"texture region {w} texels wide exceeds the atlas width {ATLAS_WIDTH}")
        if x + w > ATLAS_WIDTH:
            x, y, shelf_h = 0, y + shelf_h, 0
        placements[i] = (x, y)
        x += w
        shelf_h = max(shelf_h, h)
    total_h = y + shelf_h
    if total_h >= 32767:
        raise ValueError("texture atlas too tall for cv2.remap")
    atlas = np.zeros((total_h, ATLAS_WIDTH, 3), np.uint8)
    for i, (x, y) in placements.items():
        img = regions[i].image
        atlas[y:y + img.shape[0], x:x + img.shape[1]] = img
        regions[i].ox, regions[i].oy = x, y
    return atlas


def quad_set(bd: Builder, atlas: np.ndarray, detail: np.ndarray | None, offsets: np.ndarray | None) -> QuadSet:
    """A builder's quads as the renderer's `QuadSet`, their textures in `atlas` (packed by `pack_atlas`)."""
    q = bd.quads
    tex = []
    for d in q:
        reg = bd.regions[d["region"]]
        ox = reg.ox + PAD - d["flip"] * d["ob"] / reg.texel
        oy = reg.oy + PAD + d["od"] / reg.texel
        tex.append((ox, d["flip"] / reg.texel, oy, -1.0 / reg.texel))
    return QuadSet([d["axis"] for d in q], [d["c"] for d in q], [d["sign"] for d in q],
                   [d["lo"] for d in q], [d["hi"] for d in q], [d["label"] for d in q],
                   [d["instance"] for d in q], tex, atlas, detail, offsets)


_CACHE: dict[int, SyntheticScene] = {}
_LOCK = threading.Lock()


def get_scene(seed: int = 0) -> SyntheticScene:
    """The scene for `seed`, built once per process and cached (a few are kept)."""
    with _LOCK:
        sc = _CACHE.get(int(seed))
        if sc is None:
            if len(_CACHE) >= 4:
                _CACHE.pop(next(iter(_CACHE)))
            sc = _CACHE[int(seed)] = SyntheticScene(seed)
        return sc


def render(pose_c2w: np.ndarray, camera, scene: SyntheticScene | None = None, seed: int = 0) -> RenderResult:
    """Render a view of the (cached) scene for `seed`, or of `scene`."""
    return (scene or get_scene(seed)).render(pose_c2w, camera)
