"""Exact, vectorized ray casting of axis-aligned rectangles (quads) with a z-buffer.

A quad lies in the plane `X[axis] = c`, faces `sign` × axis and spans a rectangle in the two
other world axes. For a pinhole camera the inverse depth 1/z of a plane is affine in the pixel
coordinates, so each quad is rasterised exactly by:

1. back-face culling (closed solids and inward-facing room walls only show one side),
2. clipping its corners against the near plane and projecting them (the projected polygon is
   convex), culling quads whose pixel bounding box is empty,
3. inside that bounding box only: per-row [lo, hi] column intervals from the polygon edges,
   and an inverse-depth buffer test `1/z > wbuf` (keep the nearest hit).

Shading is deferred: from the winning quad id and depth of every pixel, the world hit point
is rebuilt and mapped to the texture atlas, sampled in one `cv2.remap` (bilinear).
Depth is z in the camera frame (along the optical axis), not ray length.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np

NEAR = 0.02  # metres; nothing nearer than this is drawn
EPS_PX = 1e-3  # pixels on a shared edge belong to both quads: no cracks


@dataclass
class RenderResult:
    """One rendered view. `surface` is the internal quad index + 1 (0 = nothing hit)."""

    rgb: np.ndarray  # H×W×3 uint8 BGR
    depth: np.ndarray  # H×W float32 metres (z in camera frame), 0 = nothing hit
    labels: np.ndarray  # H×W uint8 semantic class ids (see CLASS_NAMES)
    instances: np.ndarray  # H×W int32 object instance ids, 0 = none (wall/floor/ceiling)
    surface: np.ndarray  # H×W int32 quad id + 1, 0 = none
    incidence: np.ndarray | None = None  # H×W float32 |cos| ray/normal angle (render(incidence=True))

    @property
    def image(self) -> np.ndarray:
        return self.rgb


class QuadSet:
    """The scene's quads as flat arrays, plus the texture atlas they map into."""

    def __init__(self, axis, c, sign, lo, hi, label, instance, texmap, atlas, detail=None, detail_offsets=None):
        self.axis = np.asarray(axis, np.int64)
        self.c = np.asarray(c, np.float64)
        self.sign = np.asarray(sign, np.float64)
        self.lo = np.asarray(lo, np.float64).reshape(-1, 3)
        self.hi = np.asarray(hi, np.float64).reshape(-1, 3)
        n = len(self.axis)
        # corners (b0,d0) (b1,d0) (b1,d1) (b0,d1) in the plane
        bax = np.where(self.axis == 0, 1, 0)
        dax = np.where(self.axis == 2, 1, 2)
        corners = np.zeros((n, 4, 3))
        ar = np.arange(n)
        for k, (bb, dd) in enumerate(((0, 0), (1, 0), (1, 1), (0, 1))):
            corners[ar, k, self.axis] = self.c
            corners[ar, k, bax] = np.where(bb, self.hi[ar, bax], self.lo[ar, bax])
            corners[ar, k, dax] = np.where(dd, self.hi[ar, dax], self.lo[ar, dax])
        self.corners = corners
        # per-id tables (index 0 = background)
        self.label_of = np.concatenate([[0], np.asarray(label)]).astype(np.uint8)
        self.instance_of = np.concatenate([[0], np.asarray(instance)]).astype(np.int32)
        self.axis_of = np.concatenate([[2], self.axis]).astype(np.int8)
        # texmap rows (ox, sx, oy, sy): atlas_x = ox + sx * P[b], atlas_y = oy + sy * P[d]
        # (b axis is y for x-walls, else x; d axis is y for floors/ceilings, else z)
        tm = np.asarray(texmap, np.float32).reshape(n, 4)
        if detail_offsets is None:
            detail_offsets = np.zeros((n, 2 * len(DETAIL_OCTAVES)), np.float32)
        tm = np.concatenate([tm, (self.axis == 0)[:, None], (self.axis == 2)[:, None], detail_offsets], 1)
        self.tex = np.concatenate([np.zeros((1, tm.shape[1])), tm]).astype(np.float32)
        self.tex[0, 0] = self.tex[0, 2] = 1.0
        self.tex_cols = [np.ascontiguousarray(self.tex[:, k]) for k in range(self.tex.shape[1])]
        self.detail = detail  # uint8 random table for the fine detail, None = no detail
        self.atlas = atlas

    def __len__(self) -> int:
        return len(self.axis)


class _CamCache:
    def __init__(self, camera):
        W, H = camera.width, camera.height
        self.us = np.arange(W, dtype=np.float64)
        self.vs = np.arange(H, dtype=np.float64)
        self.us32 = self.us.astype(np.float32)
        self.xn = ((self.us - camera.cx) / camera.fx).astype(np.float32)
        self.yn = ((self.vs - camera.cy) / camera.fy).astype(np.float32)


def _clip_near(P: np.ndarray, near: float) -> np.ndarray:
    """Sutherland–Hodgman clip of a polygon (k×3, camera frame) to z >= near."""
    out = []
    k = len(P)
    for i in range(k):
        a, b = P[i], P[(i + 1) % k]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out) if out else np.zeros((0, 3))


def _edge_jobs(pu: np.ndarray, pv: np.ndarray, which, W: int, H: int) -> list:
    """Pixel boxes and the edge half-planes that cut them, for convex polygons (n×k)."""
    u0 = np.maximum(0, np.ceil(pu.min(1) - EPS_PX)).astype(np.int64)
    u1 = np.minimum(W - 1, np.floor(pu.max(1) + EPS_PX)).astype(np.int64)
    v0 = np.maximum(0, np.ceil(pv.min(1) - EPS_PX)).astype(np.int64)
    v1 = np.minimum(H - 1, np.floor(pv.max(1) + EPS_PX)).astype(np.int64)
    ex = np.roll(pu, -1, 1) - pu
    ey = np.roll(pv, -1, 1) - pv
    area = (pu * np.roll(pv, -1, 1) - pv * np.roll(pu, -1, 1)).sum(1)
    s = np.where(area > 0, 1.0, -1.0)[:, None]
    L = np.hypot(ex, ey)
    good = L > 1e-12
    L = np.where(good, L, 1.0)
    ea, eb = -s * ey / L, s * ex / L
    ec = -(ea * pu + eb * pv)
    # an edge matters only if its half-plane does not hold the whole box
    m = (np.minimum(ea * u0[:, None], ea * u1[:, None]) + np.minimum(eb * v0[:, None], eb * v1[:, None]) + ec)
    cuts = good & (m < 0)
    jobs = []
    nonempty = (u0 <= u1) & (v0 <= v1)
    E = np.stack([ea, eb, ec], -1).tolist()
    cl = cuts.tolist()
    for i in np.flatnonzero(nonempty).tolist():
        edges = [e for e, c in zip(E[i], cl[i]) if c]
        jobs.append((int(which[i]), int(u0[i]), int(u1[i]), int(v0[i]), int(v1[i]), edges))
    return jobs


# Fine surface detail ("plaster grain"): value noise locked to world coordinates, faded out as
# the pixel footprint approaches the noise cell (so nothing aliases far away). It gives ORB
# sharp, repeatable, non-periodic blobs when the camera is close (0.5–2 m), where the stored
# textures (5–12 mm texels) are magnified and soft. The noise is a bilinear lookup
# (cv2.remap) into one 4096² table of random black/white cells (binary values give crisper,
# more cornery grain than uniform ones); every quad and octave reads its own random window
# of it (a 16 m period at the finest cell: larger than any surface).
DETAIL_SIZE = 4096
DETAIL_OCTAVES = ((0.004, 18.0), (0.011, 14.0))  # (cell m, amplitude in grey levels)


def detail_table(seed: int) -> np.ndarray:
    rng = np.random.default_rng([seed, 0xD37A11])
    return rng.integers(0, 2, (DETAIL_SIZE, DETAIL_SIZE), dtype=np.uint8) * np.uint8(255)


def detail_offsets(seed: int, n: int) -> np.ndarray:
    """Per quad and octave random windows into the detail table (n × 2·octaves)."""
    rng = np.random.default_rng([seed, 0x0FF5E7])
    return rng.uniform(0, DETAIL_SIZE, (n, 2 * len(DETAIL_OCTAVES))).astype(np.float32)


class _Workspace:
    """Scratch buffers for one image size, reused frame after frame. (Fresh multi-megabyte
    temporaries make glibc hand memory back to the OS and page-fault it in again every frame,
    which doubled the render time.)"""

    def __init__(self, H: int, W: int):
        f = lambda: np.empty((H, W), np.float32)  # noqa: E731
        self.wbuf = np.zeros((H, W), np.float32)
        self.a, self.b, self.c, self.d, self.e, self.g = f(), f(), f(), f(), f(), f()
        self.Dx, self.Dy, self.Dz, self.Px, self.Py, self.Pz = f(), f(), f(), f(), f(), f()
        self.Pb, self.Pd, self.bY, self.dY, self.foot, self.delta = f(), f(), f(), f(), f(), f()
        self.m1 = np.empty((H, W), bool)
        self.m2 = np.empty((H, W), bool)
        self.n = np.empty((H, W), np.uint8)
        self.img = np.empty((H, W, 3), np.uint8)
        self.d3 = np.empty((H, W, 3), np.float32)


class Rasterizer:
    def __init__(self, quads: QuadSet):
        self.q = quads
        self._cams: dict = {}
        self._local = threading.local()

    def _cam(self, camera) -> _CamCache:
        key = (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)
        cc = self._cams.get(key)
        if cc is None:
            if len(self._cams) > 8:
                self._cams.clear()
            cc = self._cams[key] = _CamCache(camera)
        return cc

    def _ws(self, H: int, W: int) -> _Workspace:
        ws = getattr(self._local, "ws", None)
        if ws is None or ws.wbuf.shape != (H, W):
            ws = self._local.ws = _Workspace(H, W)
        return ws

    def visibility(self, pose: np.ndarray, camera, ws: _Workspace | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Inverse-depth buffer (float32, 0 = nothing) and quad-id buffer (int32, 0 = nothing).
        The inverse-depth buffer belongs to the workspace when `ws` is given."""
        q = self.q
        W, H = camera.width, camera.height
        fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
        cc = self._cam(camera)
        R = np.asarray(pose, np.float64)[:3, :3]
        C = np.asarray(pose, np.float64)[:3, 3]

        if ws is None:
            ws = _Workspace(H, W)
        wbuf = ws.wbuf
        wbuf.fill(0.0)
        ibuf = np.zeros((H, W), np.int32)

        rel = C[q.axis] - q.c
        cand = np.nonzero(rel * q.sign > 1e-9)[0]  # camera on the quad's front side
        if len(cand) == 0:
            return wbuf, ibuf
        Xc = (q.corners[cand] - C) @ R  # (n,4,3) camera-frame corners
        z = Xc[..., 2]
        keep = z.max(1) > NEAR
        cand, Xc, z = cand[keep], Xc[keep], z[keep]
        allfront = z.min(1) > NEAR
        zs = np.where(allfront[:, None], z, 1.0)
        u = fx * Xc[..., 0] / zs + cx
        v = fy * Xc[..., 1] / zs + cy
        # frustum cull (only decisive for all-front quads; the others are clipped below)
        off = allfront & ((u.max(1) < -0.5) | (u.min(1) > W - 0.5) | (v.max(1) < -0.5) | (v.min(1) > H - 0.5))
        keep = ~off
        cand, Xc, u, v, allfront = cand[keep], Xc[keep], u[keep], v[keep], allfront[keep]

        # inverse depth w = d_a / (c - C_a), d_a = R[a,0] xn + R[a,1] yn + R[a,2]
        a = q.axis[cand]
        den = q.c[cand] - C[a]
        Au = R[a, 0] / fx / den
        Av = R[a, 1] / fy / den
        W0 = (R[a, 2] - R[a, 0] * cx / fx - R[a, 1] * cy / fy) / den

        # polygons: all-front quads in one go, near-clipped ones one by one
        jobs = []
        idx_front = np.nonzero(allfront)[0]
        if len(idx_front):
            jobs += _edge_jobs(u[idx_front], v[idx_front], idx_front, W, H)
        for j in np.nonzero(~allfront)[0]:
            P = _clip_near(Xc[j], NEAR)
            if len(P) < 3:
                continue
            pu = fx * P[:, 0] / P[:, 2] + cx
            pv = fy * P[:, 1] / P[:, 2] + cy
            jobs += _edge_jobs(pu[None], pv[None], [j], W, H)

        vs = cc.vs
        us32 = cc.us32
        Au, Av, W0 = Au.tolist(), Av.tolist(), W0.tolist()
        ids = (cand + 1).tolist()
        for j, u0, u1, v0, v1, edges in jobs:
            vv = vs[v0:v1 + 1]
            lo = hi = None
            for ea, eb, ec in edges:
                if ea > 1e-9:
                    t = (-(eb * vv + ec) - EPS_PX) / ea
                    lo = t if lo is None else np.maximum(lo, t)
                elif ea < -1e-9:
                    t = (-(eb * vv + ec) - EPS_PX) / ea
                    hi = t if hi is None else np.minimum(hi, t)
                else:  # horizontal edge: restricts rows
                    bad = eb * vv + ec < -EPS_PX
                    if lo is None:
                        lo = np.full(len(vv), float(u0))
                    lo = np.where(bad, np.inf, lo)
            if lo is not None or hi is not None:
                if lo is None:
                    lo = np.full(len(vv), float(u0))
                if hi is None:
                    hi = np.full(len(vv), float(u1))
                rows = np.flatnonzero(lo <= hi)
                if len(rows) == 0:
                    continue
                r0, r1 = rows[0], rows[-1]
                lo, hi, vv = lo[r0:r1 + 1], hi[r0:r1 + 1], vv[r0:r1 + 1]
                v0, v1 = v0 + r0, v0 + r1
                cu0 = max(u0, int(np.ceil(lo.min())))
                cu1 = min(u1, int(np.floor(hi.max())))
                if cu0 > cu1:
                    continue
                u0, u1 = cu0, cu1
                full = bool(lo.max() <= u0 and hi.min() >= u1)
            else:
                full = True
            h, w = v1 - v0 + 1, u1 - u0 + 1
            cols = us32[u0:u1 + 1]
            wsub = wbuf[v0:v1 + 1, u0:u1 + 1]
            isub = ibuf[v0:v1 + 1, u0:u1 + 1]
            w2 = ws.a[:h, :w]
            np.add((np.float32(Au[j]) * cols)[None, :], (Av[j] * vv + W0[j]).astype(np.float32)[:, None], out=w2)
            m = np.greater(w2, wsub, out=ws.m1[:h, :w])
            if not full:
                m2 = ws.m2[:h, :w]
                np.greater_equal(cols[None, :], lo.astype(np.float32)[:, None], out=m2)
                m &= m2
                np.less_equal(cols[None, :], hi.astype(np.float32)[:, None], out=m2)
                m &= m2
            np.copyto(wsub, w2, where=m)
            np.copyto(isub, ids[j], where=m)
        return wbuf, ibuf

    def render(self, pose: np.ndarray, camera, rgb: bool = True, incidence: bool = False) -> RenderResult:
        q = self.q
        H, W = camera.height, camera.width
        cc = self._cam(camera)
        ws = self._ws(H, W)
        wbuf, ibuf = self.visibility(pose, camera, ws)
        R = np.asarray(pose, np.float64)[:3, :3]
        C = np.asarray(pose, np.float64)[:3, 3].astype(np.float32)
        hit = np.greater(ibuf, 0, out=ws.m1)
        depth = np.zeros((H, W), np.float32)
        np.divide(np.float32(1.0), wbuf, out=depth, where=hit)
        labels = np.take(q.label_of, ibuf)
        instances = np.take(q.instance_of, ibuf)
        if not (rgb or incidence):
            return RenderResult(np.zeros((H, W, 3), np.uint8), depth, labels, instances, ibuf)

        f32 = np.float32
        Rf = R.astype(np.float32)
        xn, yn = cc.xn[None, :], cc.yn[:, None]
        col = lambda k, out: np.take(q.tex_cols[k], ibuf, out=out)  # noqa: E731  per-pixel table column
        # world ray per unit depth D = R @ [xn, yn, 1]; hit point P = C + z * D
        Dx, Dy, Dz = ws.Dx, ws.Dy, ws.Dz
        for i, Dk in enumerate((Dx, Dy, Dz)):
            np.add(Rf[i, 0] * xn, Rf[i, 1] * yn + Rf[i, 2], out=Dk)
        bY, dY, ta = ws.bY, ws.dY, ws.a
        col(4, bY)  # 1 where the surface normal is along x
        col(5, dY)  # 1 where it is along z (else along y)
        # |D.n| and |D|^2
        Dn, D2 = ws.e, ws.g
        np.subtract(Dx, Dy, out=Dn)
        Dn *= bY
        np.subtract(Dz, Dy, out=ta)
        ta *= dY
        Dn += ta
        Dn += Dy
        np.abs(Dn, out=Dn)
        np.multiply(Dx, Dx, out=D2)
        D2 += np.multiply(Dy, Dy, out=ta)
        D2 += np.multiply(Dz, Dz, out=ta)
        inc = None
        if incidence:
            inc = np.sqrt(D2)
            np.divide(Dn, inc, out=inc)
            inc[~hit] = 0.0
        if not rgb:
            return RenderResult(np.zeros((H, W, 3), np.uint8), depth, labels, instances, ibuf, inc)

        Px, Py, Pz = ws.Px, ws.Py, ws.Pz
        for i, (Dk, Pk) in enumerate(((Dx, Px), (Dy, Py), (Dz, Pz))):
            np.multiply(depth, Dk, out=Pk)
            Pk += C[i]
        Pb, Pd = ws.Pb, ws.Pd
        # the quad's in-plane coordinates of the hit point: Pb = x or y, Pd = z or y
        np.subtract(Py, Px, out=Pb)
        Pb *= bY
        Pb += Px
        np.subtract(Py, Pz, out=Pd)
        Pd *= dY
        Pd += Pz
        mapx, mapy = ws.c, ws.d
        col(0, mapx)
        mapx += np.multiply(col(1, ta), Pb, out=ta)
        col(2, mapy)
        mapy += np.multiply(col(3, ta), Pd, out=ta)
        if q.detail is None:
            img = cv2.remap(q.atlas, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            return RenderResult(img, depth, labels, instances, ibuf, inc)
        img = cv2.remap(q.atlas, mapx, mapy, cv2.INTER_LINEAR, dst=ws.img, borderMode=cv2.BORDER_REPLICATE)

        # footprint of a pixel on the surface (m), stretched by the incidence angle:
        # foot = z |D|^2 / (fx max(|D.n|, 0.25 |D|))
        foot = ws.foot
        np.sqrt(D2, out=foot)
        foot *= f32(0.25)
        np.maximum(Dn, foot, out=ta)
        ta *= f32(camera.fx)
        np.multiply(depth, D2, out=foot)
        foot /= ta
        np.maximum(foot, f32(1e-6), out=foot)
        delta = ws.delta
        delta.fill(0.0)
        wgt, mx, my, term = ws.a, ws.b, ws.c, ws.d
        any_detail = False
        for k, (cell, amp) in enumerate(DETAIL_OCTAVES):
            # full strength at >= 3 pixels per cell, none at <= 1.5
            np.divide(f32(cell), foot, out=wgt)
            wgt -= f32(1.5)
            np.clip(wgt, 0.0, 1.5, out=wgt)
            if not wgt.any():
                continue
            any_detail = True
            inv = f32(1.0 / cell)
            np.multiply(Pb, inv, out=mx)
            mx += col(6 + 2 * k, term)
            np.multiply(Pd, inv, out=my)
            my += col(7 + 2 * k, term)
            n = cv2.remap(q.detail, mx, my, cv2.INTER_LINEAR, dst=ws.n, borderMode=cv2.BORDER_WRAP)
            cv2.subtract(n, 128, dst=term, dtype=cv2.CV_32F)
            term *= wgt
            term *= f32(amp / 1.5 / 128.0)
            delta += term
        if not any_detail:
            return RenderResult(img.copy(), depth, labels, instances, ibuf, inc)
        out = cv2.add(img, cv2.merge([delta, delta, delta], dst=ws.d3), dtype=cv2.CV_8U)
        return RenderResult(out, depth, labels, instances, ibuf, inc)
