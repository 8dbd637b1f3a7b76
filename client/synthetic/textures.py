"""Procedural surface textures for the synthetic scene.

Every generator takes a numpy `Generator`, the texture size in texels (h, w) and the texel
size in metres, and returns an h×w×3 uint8 BGR image. Content is sized in metres so the
look does not depend on the resolution. The textures are built to give ORB many distinctive,
repeatable corners at 0.5–6 m: multi-scale value noise (no periodic patterns) plus random
shapes whose sizes span 2 cm – 50 cm, drawn anti-aliased and pre-blurred by ~0.7 texel.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

AA = cv2.LINE_AA
SHIFT = 4  # cv2 drawing sub-pixel bits
ONE = 1 << SHIFT


# --------------------------------------------------------------------------- primitives
def value_noise(rng: np.random.Generator, h: int, w: int, cell: float) -> np.ndarray:
    """Smooth random field in [0, 1] (roughly) with features of `cell` texels."""
    cell = max(float(cell), 1.5)
    if cell > 12 and h > 8 and w > 8:
        # coarse noise: make it at a lower resolution, then upsample (bilinear is smooth enough)
        f = cell / 6.0
        small = value_noise(rng, max(2, int(np.ceil(h / f)) + 1), max(2, int(np.ceil(w / f)) + 1), 6.0)
        big = cv2.resize(small, (int(round(small.shape[1] * f)), int(round(small.shape[0] * f))),
                         interpolation=cv2.INTER_LINEAR)
        return big[:h, :w] if big.shape[0] >= h and big.shape[1] >= w else cv2.resize(small, (w, h))
    gh, gw = int(h / cell) + 3, int(w / cell) + 3
    g = rng.random((gh, gw), dtype=np.float32)
    big = cv2.resize(g, (int(np.ceil(gw * cell)), int(np.ceil(gh * cell))), interpolation=cv2.INTER_CUBIC)
    oy = int(rng.integers(0, int(big.shape[0] - h - cell) + 1)) if big.shape[0] - h > cell else 0
    ox = int(rng.integers(0, int(big.shape[1] - w - cell) + 1)) if big.shape[1] - w > cell else 0
    out = big[oy:oy + h, ox:ox + w]
    if out.shape != (h, w):  # tiny textures
        out = cv2.resize(big, (w, h), interpolation=cv2.INTER_LINEAR)
    return out


def fractal(rng, h, w, texel, scales_m=(0.8, 0.3, 0.1, 0.035), amps=(0.5, 0.3, 0.2, 0.12)) -> np.ndarray:
    """Zero-mean multi-octave value noise, scales given in metres."""
    acc = np.zeros((h, w), np.float32)
    for s, a in zip(scales_m, amps):
        acc += (value_noise(rng, h, w, s / texel) - 0.5) * (2 * a)
    return acc


def stretched_noise(rng, h, w, cell_along, cell_across, axis=1) -> np.ndarray:
    """Anisotropic noise (wood grain): long features along `axis` (1 = horizontal)."""
    if axis == 1:
        small = value_noise(rng, h, max(2, int(w * cell_across / cell_along)), cell_across)
        return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    small = value_noise(rng, max(2, int(h * cell_across / cell_along)), w, cell_across)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


def colorize(base_bgr, mod: np.ndarray, tint=None) -> np.ndarray:
    """base colour × (1 + mod) (+ optional per-channel tint field), clipped to uint8."""
    img = np.asarray(base_bgr, np.float32)[None, None, :] * (1.0 + mod[..., None])
    if tint is not None:
        img += tint
    return np.clip(img, 0, 255).astype(np.uint8)


def luminance(bgr) -> float:
    b, g, r = bgr
    return 0.114 * float(b) + 0.587 * float(g) + 0.299 * float(r)


def random_colour(rng, lum_range=(60, 200), sat=0.6) -> tuple:
    """A BGR colour with luminance in lum_range and saturation up to `sat`."""
    lo, hi = lum_range
    target = lo + (hi - lo) * rng.random()
    hb, hg, hr = rng.random(3).tolist()
    c = [target * (1 - sat) + sat * 255 * x for x in (hb, hg, hr)]
    k = target / max(luminance(c), 1.0)
    return tuple(min(255.0, max(0.0, x * k)) for x in c)


def contrasting(rng, base, min_delta=40, max_delta=110, sat=0.6) -> tuple:
    """A colour whose luminance differs from `base` by min_delta..max_delta grey levels."""
    L = luminance(base)
    delta = min_delta + (max_delta - min_delta) * rng.random()
    if L - delta < 15:
        sign = 1
    elif L + delta > 240:
        sign = -1
    else:
        sign = 1 if rng.random() < 0.5 else -1
    tgt = min(250.0, max(8.0, L + sign * delta))
    return random_colour(rng, (tgt, tgt), sat)


def _pts(p) -> np.ndarray:
    return np.round(np.asarray(p, np.float64) * ONE).astype(np.int32)


KINDS = ("rect", "ellipse", "poly", "star", "stroke", "ring", "tri", "cross")


def draw_shape(img, rng, cx, cy, size, colour, kind=None, r=None):
    """One random shape (in texel coordinates) of about `size` texels. `r`: 20 uniforms in
    [0, 1) that decide its form (drawn from `rng` when not given)."""
    if r is None:
        r = rng.random(20).tolist()
    kind = kind or KINDS[int(r[0] * len(KINDS))]
    col = tuple(int(c) for c in colour)
    ang = r[1] * math.pi
    if kind == "rect":
        a, b = size * (0.3 + 0.7 * r[2]) / 2, size * (0.3 + 0.7 * r[3]) / 2
        ca, sa = math.cos(ang), math.sin(ang)
        box = [(cx - a * ca + b * sa, cy - a * sa - b * ca), (cx + a * ca + b * sa, cy + a * sa - b * ca),
               (cx + a * ca - b * sa, cy + a * sa + b * ca), (cx - a * ca - b * sa, cy - a * sa + b * ca)]
        cv2.fillPoly(img, [_pts(box)], col, AA, SHIFT)
    elif kind == "ellipse":
        ax = (max(1, int(size * (0.2 + 0.3 * r[2]) * ONE)), max(1, int(size * (0.15 + 0.35 * r[3]) * ONE)))
        cv2.ellipse(img, (int(cx * ONE), int(cy * ONE)), ax, math.degrees(ang), 0, 360, col, -1, AA, SHIFT)
    elif kind in ("poly", "tri"):
        n = 3 if kind == "tri" else 4 + int(r[2] * 4)
        th = sorted(2 * math.pi * x for x in r[4:4 + n])
        rad = [size * 0.5 * (0.4 + 0.6 * x) for x in r[12:12 + n]]
        p = [(cx + q * math.cos(t), cy + q * math.sin(t)) for q, t in zip(rad, th)]
        cv2.fillPoly(img, [_pts(p)], col, AA, SHIFT)
    elif kind == "star":
        n = (4 + int(r[2] * 4)) * 2
        inner = 0.3 + 0.3 * r[3]
        p = [(cx + size * 0.5 * (1.0 if k % 2 == 0 else inner) * math.cos(ang + 2 * math.pi * k / n),
              cy + size * 0.5 * (1.0 if k % 2 == 0 else inner) * math.sin(ang + 2 * math.pi * k / n)) for k in range(n)]
        cv2.fillPoly(img, [_pts(p)], col, AA, SHIFT)
    elif kind == "stroke":
        n = 2 + int(r[2] * 3)
        x, y = cx, cy
        p = [(x, y)]
        for k in range(n - 1):
            x += size * 0.6 * (r[4 + 2 * k] - 0.5) * 2
            y += size * 0.6 * (r[5 + 2 * k] - 0.5) * 2
            p.append((x, y))
        t = max(1, int(size * (0.06 + 0.1 * r[3])))
        cv2.polylines(img, [_pts(p)], False, col, t, AA, SHIFT)
    elif kind == "ring":
        rad = max(2, int(size * (0.25 + 0.25 * r[2])))
        t = max(1, int(rad * (0.15 + 0.25 * r[3])))
        cv2.circle(img, (int(cx * ONE), int(cy * ONE)), rad * ONE, col, t, AA, SHIFT)
    elif kind == "cross":
        a = size * 0.5
        t = max(1, int(size * (0.1 + 0.12 * r[2])))
        ca, sa = math.cos(ang) * a, math.sin(ang) * a
        cv2.line(img, _pts((cx - ca, cy - sa)), _pts((cx + ca, cy + sa)), col, t, AA, SHIFT)
        cv2.line(img, _pts((cx + sa, cy - ca)), _pts((cx - sa, cy + ca)), col, t, AA, SHIFT)


def scatter(img, rng, texel, density, size_m=(0.02, 0.35), colour_fn=None, kinds=None, margin=0.0):
    """Sprinkle ~density shapes per m², sizes log-uniform in size_m (metres)."""
    h, w = img.shape[:2]
    area = h * w * texel * texel
    n = int(rng.poisson(density * area))
    if n == 0:
        return img
    lo, hi = np.log(size_m[0] / texel), np.log(size_m[1] / texel)
    sizes = np.exp(rng.uniform(lo, hi, n)).tolist()
    xs = rng.uniform(margin * w, (1 - margin) * w, n).tolist()
    ys = rng.uniform(margin * h, (1 - margin) * h, n).tolist()
    U = rng.random((n, 21)).tolist()
    for i in range(n):
        base = img[int(min(ys[i], h - 1)), int(min(xs[i], w - 1))].tolist()
        col = colour_fn(rng, base) if colour_fn else contrasting(rng, base)
        kind = kinds[int(U[i][20] * len(kinds))] if kinds else None
        draw_shape(img, rng, xs[i], ys[i], sizes[i], col, kind, U[i])
    return img


def soft_blotches(img, rng, texel, density, size_m, delta, tint=0.3):
    """Large soft stains: drawn at 1/4 resolution on a signed layer, blurred, added."""
    h, w = img.shape[:2]
    f = 4
    lh, lw = max(2, h // f + 1), max(2, w // f + 1)
    layer = np.zeros((lh, lw, 3), np.float32)
    n = int(rng.poisson(density * h * w * texel * texel))
    for _ in range(n):
        d = (rng.uniform(*delta)) * (1 if rng.random() < 0.5 else -1)
        col = tuple(float(d * (1 + tint * (x - 0.5) * 2)) for x in rng.random(3))
        size = np.exp(rng.uniform(np.log(size_m[0]), np.log(size_m[1]))) / texel / f
        draw_shape(layer, rng, rng.uniform(0, lw), rng.uniform(0, lh), size, col,
                   ("ellipse", "poly")[int(rng.random() * 2)])
    layer = cv2.GaussianBlur(layer, (0, 0), 0.04 / texel / f + 0.5)
    layer = cv2.resize(layer, (lw * f, lh * f), interpolation=cv2.INTER_LINEAR)[:h, :w]
    return np.clip(img.astype(np.float32) + layer, 0, 255).astype(np.uint8)


def finish(img, sigma=0.7):
    """Anti-alias: a light blur so the texture holds no frequency above ~1/2 texel⁻¹."""
    return cv2.GaussianBlur(img, (0, 0), sigma)


def shade(img, factor: float, rng=None, texel=0.01, amp=0.06):
    """Lambert-like constant shading × a soft, low-frequency lighting variation."""
    h, w = img.shape[:2]
    f = np.full((h, w), factor, np.float32)
    if rng is not None and amp > 0:
        f *= 1.0 + amp * (2 * value_noise(rng, h, w, 1.5 / texel) - 1)
    return np.clip(img.astype(np.float32) * f[..., None], 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- materials
PASTELS = [(200, 205, 215), (185, 200, 190), (170, 190, 210), (210, 200, 185), (195, 185, 200),
           (160, 175, 180), (205, 215, 205), (180, 170, 160), (215, 205, 200), (150, 170, 195)]
WOODS = [(60, 100, 150), (45, 80, 125), (80, 125, 170), (35, 60, 95), (95, 140, 180), (70, 90, 110)]
FABRICS = [(140, 90, 60), (70, 110, 70), (60, 60, 150), (110, 110, 110), (150, 130, 90), (90, 70, 120)]


def wall(rng, h, w, texel):
    """Painted plaster with stains and many stickers / stencils / scribbles at all scales."""
    base = PASTELS[int(rng.integers(len(PASTELS)))]
    base = tuple(np.clip(np.array(base) + rng.normal(0, 10, 3), 40, 235))
    mod = fractal(rng, h, w, texel, (1.2, 0.45, 0.15, 0.05, 0.02), (0.10, 0.09, 0.07, 0.05, 0.03))
    img = colorize(base, mod)
    # big soft blotches (stains, patches of a second paint)
    img = soft_blotches(img, rng, texel, 0.6, (0.25, 0.9), (15, 35))
    # crisp stencils at all scales
    scatter(img, rng, texel, 9.0, (0.12, 0.5))
    scatter(img, rng, texel, 22.0, (0.03, 0.14))
    return finish(img)


def plain_wall(rng, h, w, texel):
    """A calmer wall (the hall's long wall, where the repeated posters must dominate)."""
    base = (205, 210, 212)
    mod = fractal(rng, h, w, texel, (1.0, 0.3, 0.08, 0.03), (0.07, 0.06, 0.05, 0.04))
    img = colorize(base, mod)
    scatter(img, rng, texel, 8.0, (0.02, 0.2), lambda r, b: contrasting(r, b, 25, 70, 0.3))
    return finish(img)


def wood_planks(rng, h, w, texel, plank=(0.14, 0.2), length=(0.7, 1.6)):
    """Parquet planks along x (axis 1) with random tones, grain, seams and knots."""
    base = np.array(WOODS[int(rng.integers(len(WOODS)))], np.float32)
    grain = stretched_noise(rng, h, w, 0.5 / texel, 0.012 / texel) - 0.5
    grain2 = stretched_noise(rng, h, w, 0.2 / texel, 0.004 / texel) - 0.5
    img = np.empty((h, w, 3), np.float32)
    seam = max(1, int(round(0.004 / texel)))
    y = 0
    edges = []
    while y < h:
        pw = int(rng.uniform(*plank) / texel)
        x = -int(rng.uniform(0, length[1]) / texel)
        while x < w:
            pl = int(rng.uniform(*length) / texel)
            tone = base * rng.uniform(0.7, 1.3) + rng.normal(0, 8, 3)
            x0, x1, y1 = max(x, 0), min(x + pl, w), min(y + pw, h)
            if x1 > x0:
                sl = (slice(y, y1), slice(x0, x1))
                img[sl] = tone * (1 + 0.35 * grain[sl] + 0.2 * grain2[sl])[..., None]
                edges.append((x0, y, x1, y1))
            x += pl
        y += pw
    img = np.clip(img, 0, 255).astype(np.uint8)
    for x0, y0, x1, y1 in edges:
        cv2.rectangle(img, (x0, y0), (x1, y1), (25, 35, 45), seam)
    # knots and scuffs
    scatter(img, rng, texel, 6.0, (0.015, 0.06), lambda r, b: contrasting(r, b, 35, 70, 0.3), ("ellipse", "ring"))
    scatter(img, rng, texel, 2.0, (0.05, 0.25), lambda r, b: contrasting(r, b, 20, 50, 0.2), ("stroke",))
    return finish(img)


def rug(img, rng, texel, x0, y0, x1, y1):
    """Draw a patterned rug (border + random motifs) into a floor texture (texel coords)."""
    c1 = random_colour(rng, (60, 150), 0.8)
    c2 = contrasting(rng, c1, 50, 110, 0.8)
    cv2.rectangle(img, (x0, y0), (x1, y1), c1, -1)
    b = int(0.08 / texel)
    cv2.rectangle(img, (x0 + b, y0 + b), (x1 - b, y1 - b), c2, max(1, int(0.03 / texel)))
    sub = img[y0 + 2 * b:y1 - 2 * b, x0 + 2 * b:x1 - 2 * b]
    if sub.size:
        scatter(sub, rng, texel, 40.0, (0.04, 0.3), lambda r, bb: contrasting(r, bb, 40, 110, 0.8))
    # fringe
    for x in range(x0, x1, max(2, int(0.025 / texel))):
        cv2.line(img, (x, y0), (x, y0 - int(0.04 / texel)), c2, 1, AA)
        cv2.line(img, (x, y1), (x, y1 + int(0.04 / texel)), c2, 1, AA)


def stone_tiles(rng, h, w, texel):
    """Rows of stone tiles of random lengths and tones, with speckles and grout."""
    base = np.array(random_colour(rng, (110, 170), 0.25), np.float32)
    speck = fractal(rng, h, w, texel, (0.3, 0.08, 0.025), (0.12, 0.10, 0.08))
    img = np.empty((h, w, 3), np.float32)
    rects = []
    y = 0
    while y < h:
        th = int(rng.uniform(0.35, 0.6) / texel)
        x = -int(rng.uniform(0, 0.6) / texel)
        while x < w:
            tl = int(rng.uniform(0.3, 0.8) / texel)
            tone = base * rng.uniform(0.75, 1.25) + rng.normal(0, 10, 3)
            x0, x1, y1 = max(x, 0), min(x + tl, w), min(y + th, h)
            if x1 > x0:
                sl = (slice(y, y1), slice(x0, x1))
                img[sl] = tone * (1 + speck[sl])[..., None]
                rects.append((x0, y, x1, y1))
            x += tl
        y += th
    img = np.clip(img, 0, 255).astype(np.uint8)
    grout = tuple(float(c) for c in np.clip(base * 0.45, 0, 255))
    for x0, y0, x1, y1 in rects:
        cv2.rectangle(img, (x0, y0), (x1, y1), grout, max(1, int(0.006 / texel)))
    scatter(img, rng, texel, 10.0, (0.02, 0.12), lambda r, b: contrasting(r, b, 30, 80, 0.3))
    return finish(img)


def concrete(rng, h, w, texel):
    """Polished concrete / linoleum with speckles, patches and marks."""
    base = random_colour(rng, (120, 170), 0.15)
    mod = fractal(rng, h, w, texel, (1.0, 0.35, 0.1, 0.03, 0.012), (0.10, 0.10, 0.08, 0.06, 0.05))
    img = colorize(base, mod)
    img = soft_blotches(img, rng, texel, 1.0, (0.2, 0.8), (12, 30))
    scatter(img, rng, texel, 16.0, (0.02, 0.2), lambda r, b: contrasting(r, b, 35, 90, 0.4))
    return finish(img)


def ceiling(rng, h, w, texel):
    """Off-white ceiling with stains, cracks and fixtures (lower contrast than walls)."""
    base = (228, 230, 226)
    mod = fractal(rng, h, w, texel, (1.5, 0.5, 0.15, 0.04), (0.05, 0.05, 0.04, 0.03))
    img = colorize(base, mod)
    img = soft_blotches(img, rng, texel, 1.0, (0.2, 0.7), (12, 25))
    scatter(img, rng, texel, 5.0, (0.04, 0.3), lambda r, b: contrasting(r, b, 30, 70, 0.3))
    return finish(img)


def door_panel(rng, h, w, texel, colour=None):
    """A closed door leaf: grain, recessed panels with lit/shadowed bevels, a sign, scuffs."""
    colour = colour or [(215, 215, 210), (60, 95, 140), (90, 90, 95), (150, 110, 70),
                        (40, 70, 110)][int(rng.integers(5))]
    grain = stretched_noise(rng, h, w, 0.6 / texel, 0.015 / texel, axis=0) - 0.5
    grain2 = stretched_noise(rng, h, w, 0.25 / texel, 0.005 / texel, axis=0) - 0.5
    img = colorize(colour,
                   0.4 * grain + 0.25 * grain2 + fractal(rng, h, w, texel, (0.3, 0.06, 0.02), (0.08, 0.06, 0.04)))
    light = tuple(float(c) for c in np.clip(np.array(colour) * 1.35 + 25, 0, 255))
    dark = tuple(float(c) for c in np.array(colour) * 0.45)
    m = int(0.1 / texel)
    layout = [(1, 2), (2, 2), (1, 3), (1, 4)][int(rng.integers(4))]
    cols, rows = layout
    gw = (w - 2 * m - (cols - 1) * m) / cols
    heights = rng.dirichlet(np.ones(rows) * 3) * (h - 2 * m - (rows - 1) * m)
    t = max(2, int(0.012 / texel))
    y = m
    for r in range(rows):
        for c in range(cols):
            x0 = int(m + c * (gw + m))
            x1, y0, y1 = int(x0 + gw), int(y), int(y + heights[r])
            cv2.line(img, (x0, y0), (x1, y0), dark, t)
            cv2.line(img, (x0, y0), (x0, y1), dark, t)
            cv2.line(img, (x0, y1), (x1, y1), light, t)
            cv2.line(img, (x1, y0), (x1, y1), light, t)
            cv2.rectangle(img, (x0 + 2 * t, y0 + 2 * t), (x1 - 2 * t, y1 - 2 * t), dark, max(1, t // 2))
        y += heights[r] + m
    # a sign / label on the door, a poster or calendar, a kick plate
    if rng.random() < 0.8:
        sw, sh = int(rng.uniform(0.15, 0.3) / texel), int(rng.uniform(0.08, 0.2) / texel)
        sx, sy = int(rng.uniform(0.2, 0.8) * (w - sw)), int(h * rng.uniform(0.22, 0.32))
        sc = contrasting(rng, colour, 70, 140, 0.8)
        cv2.rectangle(img, (sx, sy), (sx + sw, sy + sh), sc, -1)
        sub = img[sy:sy + sh, sx:sx + sw]
        text(sub, rng, texel, contrasting(rng, sc, 80, 160, 0.2))
    pw, ph = int(rng.uniform(0.3, 0.45) / texel), int(rng.uniform(0.35, 0.55) / texel)
    px, py = int(rng.uniform(0.1, 0.9) * (w - pw)), int(h * rng.uniform(0.45, 0.6))
    poster = painting(rng, ph, pw, texel, style=int(rng.integers(3)))
    img[py:py + ph, px:px + pw] = poster[:max(0, min(ph, h - py)), :max(0, min(pw, w - px))]
    kick = int(0.18 / texel)
    kc = (150, 160, 170) if rng.random() < 0.5 else (60, 140, 180)
    img[h - kick:] = metal(rng, kick, w, texel, kc)
    scatter(img, rng, texel, 14.0, (0.02, 0.12), lambda r, b: contrasting(r, b, 30, 70, 0.3),
            ("stroke", "ellipse", "rect", "ring"))
    return finish(img)


def text(img, rng, texel, colour, line_h=0.025):
    """Text-like marks: rows of small random glyph blocks."""
    h, w = img.shape[:2]
    lh = max(3, int(line_h / texel))
    y = lh // 2
    while y + lh < h:
        x = lh // 2
        while x < w - lh:
            gl = int(rng.integers(1, 5)) * lh // 2
            if rng.random() < 0.8:
                draw_shape(img, rng, x + gl / 2, y + lh / 2, max(gl, lh) * 0.9, colour,
                           ("rect", "tri", "cross", "ring", "stroke")[int(rng.integers(5))])
            x += gl + lh // 2
        y += int(lh * 1.6)


def casing(rng, h, w, texel, door_colour):
    """Door frame / architrave: contrasting to the door, with mitred shadow lines."""
    L = luminance(door_colour)
    colour = (235, 238, 240) if L < 140 else (50, 60, 75)
    mod = fractal(rng, h, w, texel, (0.3, 0.05), (0.05, 0.04))
    img = colorize(colour, mod)
    t = max(1, int(0.01 / texel))
    for k in (0.3, 0.6):
        cv2.rectangle(img, (int(0.09 / texel * k), int(0.09 / texel * k)),
                      (w - 1 - int(0.09 / texel * k), h + 50), contrasting(rng, colour, 40, 80, 0.1), t, AA)
    scatter(img, rng, texel, 5.0, (0.01, 0.05), lambda r, b: contrasting(r, b, 30, 60, 0.2))
    return finish(img)


def metal(rng, h, w, texel, colour=None):
    colour = colour or [(60, 60, 65), (60, 150, 190), (180, 180, 185)][int(rng.integers(3))]
    mod = stretched_noise(rng, h, w, 0.1 / texel, 0.003 / texel) - 0.5
    img = colorize(colour, 0.3 * mod)
    return finish(img)


def window_frame(rng, h, w, texel):
    colour = (232, 235, 236) if rng.random() < 0.7 else (70, 75, 80)
    mod = fractal(rng, h, w, texel, (0.4, 0.08, 0.02), (0.04, 0.04, 0.03))
    img = colorize(colour, mod)
    scatter(img, rng, texel, 4.0, (0.01, 0.05), lambda r, b: contrasting(r, b, 30, 60, 0.2))
    return finish(img)


def glass(rng, h, w, texel):
    """A view through a window: sky gradient and clouds, trees and buildings, reflections."""
    yy = np.linspace(0, 1, h, dtype=np.float32)[:, None]
    sky_top, sky_bot = np.array([235, 190, 140], np.float32), np.array([250, 235, 215], np.float32)
    img = sky_top * (1 - yy[..., None]) + sky_bot * yy[..., None]
    img = np.broadcast_to(img, (h, w, 3)).copy()
    cloud = np.clip(fractal(rng, h, w, texel, (0.6, 0.2, 0.07), (0.6, 0.35, 0.2)) + 0.1, 0, 1)
    img = img * (1 - 0.6 * cloud[..., None]) + 250 * 0.6 * cloud[..., None]
    img = np.clip(img, 0, 255).astype(np.uint8)
    horizon = int(h * rng.uniform(0.45, 0.7))
    # buildings
    x = 0
    while x < w:
        bw = int(rng.uniform(0.15, 0.5) / texel)
        bh = int(rng.uniform(0.1, 0.5) * h)
        c = random_colour(rng, (70, 170), 0.3)
        cv2.rectangle(img, (x, horizon - bh), (x + bw, h), c, -1)
        ws = max(2, int(0.03 / texel))
        for yy_ in range(horizon - bh + ws, h - ws, 2 * ws + 1):
            for xx in range(x + ws, x + bw - ws, 2 * ws + 1):
                if rng.random() < 0.75:
                    cv2.rectangle(img, (xx, yy_), (xx + ws, yy_ + ws), contrasting(rng, c, 40, 100, 0.3), -1)
        x += bw + int(rng.uniform(0, 0.2) / texel)
    # trees
    n = int(rng.integers(2, 6))
    for _ in range(n):
        tx = rng.uniform(0, w)
        ty = horizon + rng.uniform(-0.05, 0.1) * h
        g = (float(rng.uniform(20, 60)), float(rng.uniform(80, 140)), float(rng.uniform(30, 70)))
        for _ in range(25):
            r = int(rng.uniform(0.03, 0.09) / texel)
            cv2.circle(img, (int(tx + rng.normal(0, 0.12 / texel)), int(ty + rng.normal(0, 0.1 / texel))), r,
                       tuple(np.clip(np.array(g) * rng.uniform(0.6, 1.4), 0, 255).tolist()), -1, AA)
    # reflections
    for _ in range(int(rng.integers(1, 4))):
        x0 = rng.uniform(0, w)
        d = rng.uniform(0.3, 1.0) * h
        overlay = img.copy()
        cv2.line(overlay, (int(x0), 0), (int(x0 - d), h), (255, 255, 255), int(rng.uniform(0.02, 0.08) / texel), AA)
        img = cv2.addWeighted(img, 0.8, overlay, 0.2, 0)
    return finish(cv2.GaussianBlur(img, (0, 0), 0.006 / texel))


def painting(rng, h, w, texel, style=None):
    """Canvas art: abstract shapes, a landscape or a colourful 'photo' — very high contrast."""
    style = style if style is not None else int(rng.integers(3))
    if style == 0:
        img = np.empty((h, w, 3), np.uint8)
        img[:] = random_colour(rng, (40, 220), 0.8)
        scatter(img, rng, texel, 60.0, (0.05, 0.5), lambda r, b: contrasting(r, b, 50, 150, 0.9))
        scatter(img, rng, texel, 150.0, (0.015, 0.06), lambda r, b: contrasting(r, b, 50, 150, 0.9))
    elif style == 1:
        img = np.empty((h, w, 3), np.uint8)
        y = 0
        while y < h:
            bh = int(rng.uniform(0.05, 0.3) * h) + 1
            img[y:y + bh] = random_colour(rng, (40, 230), 0.7)
            y += bh
        scatter(img, rng, texel, 80.0, (0.03, 0.3), lambda r, b: contrasting(r, b, 50, 140, 0.8),
                ("ellipse", "tri", "poly", "star"))
    else:
        f = [fractal(rng, h, w, texel, (0.3, 0.1, 0.03), (0.6, 0.4, 0.3)) for _ in range(3)]
        img = np.clip(128 + 220 * np.stack(f, -1), 0, 255).astype(np.uint8)
        scatter(img, rng, texel, 100.0, (0.02, 0.12), lambda r, b: contrasting(r, b, 60, 150, 0.9))
    return finish(img)


def picture_frame(rng, h, w, texel):
    colour = [(30, 30, 30), (40, 150, 200), (240, 240, 240), (40, 70, 110)][int(rng.integers(4))]
    mod = stretched_noise(rng, h, w, 0.3 / texel, 0.01 / texel) - 0.5
    img = colorize(colour, 0.3 * mod)
    return finish(img)


def wood(rng, h, w, texel, colour=None, along=1):
    colour = colour if colour is not None else WOODS[int(rng.integers(len(WOODS)))]
    grain = stretched_noise(rng, h, w, 0.4 / texel, 0.008 / texel, axis=along) - 0.5
    grain2 = stretched_noise(rng, h, w, 0.15 / texel, 0.003 / texel, axis=along) - 0.5
    img = colorize(colour, 0.35 * grain + 0.2 * grain2 + fractal(rng, h, w, texel, (0.3, 0.08), (0.08, 0.05)))
    scatter(img, rng, texel, 12.0, (0.01, 0.08), lambda r, b: contrasting(r, b, 35, 80, 0.3),
            ("ellipse", "ring", "stroke", "rect"))
    return finish(img)


def cabinet_front(rng, h, w, texel, colour=None):
    """Cabinet doors and drawers: outlines, bevels, knobs, a few objects/stickers."""
    colour = colour if colour is not None else (random_colour(rng, (60, 220), 0.35))
    img = wood(rng, h, w, texel, colour, along=0)
    dark = tuple(float(c) for c in np.array(colour) * 0.35)
    light = tuple(float(c) for c in np.clip(np.array(colour) * 1.3 + 30, 0, 255))
    n = max(1, int(round(w * texel / rng.uniform(0.35, 0.6))))
    t = max(1, int(0.006 / texel))
    dw = w / n
    drawers = rng.random() < 0.5
    for i in range(n):
        x0, x1 = int(i * dw) + t, int((i + 1) * dw) - t
        if drawers:
            k = int(rng.integers(2, 5))
            for j in range(k):
                y0, y1 = int(j * h / k) + t, int((j + 1) * h / k) - t
                cv2.rectangle(img, (x0, y0), (x1, y1), dark, t)
                cv2.line(img, (x0 + t, y0 + t), (x1 - t, y0 + t), light, t)
                cv2.rectangle(img, (int((x0 + x1) / 2 - 0.05 / texel), int((y0 + y1) / 2 - 0.01 / texel)),
                              (int((x0 + x1) / 2 + 0.05 / texel), int((y0 + y1) / 2 + 0.01 / texel)), dark, -1)
        else:
            cv2.rectangle(img, (x0, t), (x1, h - t), dark, t)
            cv2.rectangle(img, (x0 + int(0.05 / texel), int(0.05 / texel)),
                          (x1 - int(0.05 / texel), h - int(0.05 / texel)), light, t)
            kx = x1 - int(0.05 / texel) if i % 2 == 0 else x0 + int(0.05 / texel)
            cv2.circle(img, (kx, int(h * 0.45)), max(2, int(0.015 / texel)), dark, -1, AA)
    scatter(img, rng, texel, 8.0, (0.02, 0.12), lambda r, b: contrasting(r, b, 50, 120, 0.8))
    return finish(img)


def bookshelf_front(rng, h, w, texel, colour=None):
    """Open bookshelf seen from the front: boards and rows of books of random size/colour."""
    colour = colour if colour is not None else WOODS[int(rng.integers(len(WOODS)))]
    img = wood(rng, h, w, texel, colour)
    board = max(2, int(0.025 / texel))
    side = max(2, int(0.03 / texel))
    nrows = max(1, int(round(h * texel / rng.uniform(0.33, 0.4))))
    rh = (h - board) / nrows
    back = tuple(float(c) for c in np.array(colour) * 0.3)
    for r in range(nrows):
        y0, y1 = int(r * rh) + board, int((r + 1) * rh)
        cv2.rectangle(img, (side, y0), (w - side, y1), back, -1)
        x = side + int(rng.uniform(0, 0.1) / texel)
        while x < w - side - 2:
            if rng.random() < 0.1:  # a gap or a leaning object
                x += int(rng.uniform(0.03, 0.15) / texel)
                continue
            bw = max(2, int(rng.uniform(0.018, 0.065) / texel))
            bh = int((y1 - y0) * rng.uniform(0.55, 0.95))
            bx1 = min(x + bw, w - side)
            bc = random_colour(rng, (30, 220), 0.85)
            cv2.rectangle(img, (x, y1 - bh), (bx1 - 1, y1), bc, -1)
            # title bands
            for _ in range(int(rng.integers(0, 4))):
                yb = int(y1 - bh * rng.uniform(0.1, 0.9))
                cv2.rectangle(img, (x, yb), (bx1 - 1, yb + max(1, int(0.01 / texel))),
                              contrasting(rng, bc, 60, 140, 0.5), -1)
            x = bx1 + (1 if rng.random() < 0.5 else 0)
    return finish(img)


def fabric(rng, h, w, texel, colour=None, cushions=0):
    colour = colour if colour is not None else FABRICS[int(rng.integers(len(FABRICS)))]
    weave = fractal(rng, h, w, texel, (0.4, 0.1, 0.02, 0.008), (0.08, 0.08, 0.06, 0.06))
    img = colorize(colour, weave)
    dark = tuple(float(c) for c in np.array(colour) * 0.5)
    t = max(1, int(0.008 / texel))
    if cushions:
        cw = w / cushions
        for i in range(cushions):
            cv2.rectangle(img, (int(i * cw) + t, t), (int((i + 1) * cw) - t, h - t), dark, t, AA)
    # pattern: stripes or blotches differing per piece
    scatter(img, rng, texel, 25.0, (0.02, 0.15), lambda r, b: contrasting(r, b, 30, 80, 0.7))
    return finish(img)


def light_panel(rng, h, w, texel):
    img = np.full((h, w, 3), 250, np.uint8)
    t = max(1, int(0.03 / texel))
    cv2.rectangle(img, (0, 0), (w - 1, h - 1), (150, 150, 150), t)
    n = int(rng.integers(2, 5))
    for i in range(1, n):
        x = int(i * w / n)
        cv2.line(img, (x, 0), (x, h), (200, 200, 200), max(1, t // 2))
    return finish(img)
