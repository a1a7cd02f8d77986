"""prototype 2"""

from __future__ import annotations

from dataclasses import dataclass
from math import comb

import cv2
import numpy as np

from condtrack_cli.motion.robust import (
    MAD_TO_SIGMA,
    THETA_PRIOR_STD,
    GlobalMotion,
    MotionFit,
    RobustMotionSettings,
    Pyramid,
    build_pyramid,
    estimate_from_pyramids,
    frame_pyramid,
    robust_scale,
    robust_weights,
    usable_levels,
    warp_maps,
    _sample,
)
from condtrack_cli.types import Frame

MIN_LOCAL_SIDE = 32
MIN_WINDOW = 8
BLOCKS = 8
import os
PASSES = int(os.environ.get("PASSES", 3))
THRESHOLDS = 0.25 * 2.0 ** np.arange(10)


def local_levels(shape, levels):
    return min(levels, 1 + max(0, int(np.log2(min(shape) / MIN_LOCAL_SIDE))))


def local_model(settings):
    return "translation" if settings.model == "translation" else "affine"


#: basis monomials (a, b) of d/h per parameter group
_PHI = {"translation": ((0, 0),), "affine": ((0, 0), (1, 0), (0, 1))}


@dataclass(frozen=True)
class Layout:
    level: int
    block: int
    blocks: int
    shape: tuple  # node grid (hn, wn)

    @property
    def side(self):
        return self.block * self.blocks

    @property
    def origin(self):
        """level px of node 0 (x and y)."""
        return (self.block - 1) / 2 - (self.blocks % 2 == 0) * self.block / 2

    def offsets(self):
        return (np.arange(self.blocks) - (self.blocks - 1) / 2) * self.block


def layout(settings, level, shape):
    side = max(settings.local_window / 2**level, MIN_WINDOW)
    block = max(1, int(round(side / BLOCKS)))
    blocks = max(1, int(round(side / block)))
    h, w = shape
    return Layout(level, block, blocks, (-(-h // block) + 1, -(-w // block) + 1))


def global_flow(fit: MotionFit, shape) -> np.ndarray:
    map_x, map_y = warp_maps(fit.model, fit.theta, fit.origin, fit.length, shape)
    h, w = shape
    return np.dstack((map_x - np.arange(w, dtype=np.float32)[None, :], map_y - np.arange(h, dtype=np.float32)[:, None]))


def _pool(stack, lay: Layout, orders):
    """block sums of stack (h,w,C) times delta^p, for (p,q) in orders -> dict."""
    h, w, c = stack.shape
    hn, wn = lay.shape
    B = lay.block
    padded = np.zeros((hn * B, wn * B, c), stack.dtype)
    padded[:h, :w] = stack
    delta = np.arange(B, dtype=stack.dtype) - (B - 1) / 2
    dx = np.tile(delta, wn)[None, :, None]
    dy = np.tile(delta, hn)[:, None, None]
    out = {}
    for p, q in orders:
        f = padded
        if p:
            f = f * dx**p
        if q:
            f = f * dy**q
        if B == 1:
            out[p, q] = f if (p == 0 and q == 0) else np.zeros_like(f)
        else:
            out[p, q] = _area(f, (wn, hn)) * (B * B)
    return out


def _area(f, size):
    parts = [cv2.resize(np.ascontiguousarray(f[:, :, i:i + 4]), size, interpolation=cv2.INTER_AREA)
             for i in range(0, f.shape[2], 4)]
    parts = [p[:, :, None] if p.ndim == 2 else p for p in parts]
    return np.concatenate(parts, axis=2) if len(parts) > 1 else parts[0]


def _window(block_sums, lay: Layout, a, b):
    """window moments sum f (dx^a dy^b) from pooled block moments."""
    D = lay.offsets()
    anchor = (lay.blocks // 2, lay.blocks // 2)
    total = 0
    for p in range(a + 1):
        for q in range(b + 1):
            src = block_sums.get((p, q))
            if src is None:
                continue
            kx = (comb(a, p) * D ** (a - p)).astype(src.dtype)
            ky = (comb(b, q) * D ** (b - q)).astype(src.dtype)
            res = cv2.sepFilter2D(src, -1, kx, ky, anchor=anchor, borderType=cv2.BORDER_CONSTANT)
            if res.ndim == 2:
                res = res[:, :, None]
            total = total + res
    return total


def _to_pixels(nodes, lay: Layout, factor_nodes, shape, factor_pixels):
    """bilinear sample of node grid (hn,wn,C) at the pixels of a level of given shape."""
    h, w = shape
    spacing = factor_nodes * lay.block
    origin = factor_nodes * lay.origin
    mx = ((factor_pixels * np.arange(w) - origin) / spacing).astype(np.float32)
    my = ((factor_pixels * np.arange(h) - origin) / spacing).astype(np.float32)
    mx = np.broadcast_to(mx[None, :], (h, w))
    my = np.broadcast_to(my[:, None], (h, w))
    out = cv2.remap(nodes, np.ascontiguousarray(mx), np.ascontiguousarray(my), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out


def _linearise(prev, cur, flow, factor, settings):
    h, w, _ = prev.shape
    map_x = flow[:, :, 0] / factor + np.arange(w, dtype=np.float32)[None, :]
    map_y = flow[:, :, 1] / factor + np.arange(h, dtype=np.float32)[:, None]
    warped = cv2.remap(cur, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    inside = (map_x >= 0) & (map_x <= w - 1) & (map_y >= 0) & (map_y <= h - 1)
    textured = np.square(prev[:, :, 1]) + np.square(prev[:, :, 2]) >= settings.min_gradient ** 2
    valid = inside & textured
    valid[0] = valid[-1] = valid[:, 0] = valid[:, -1] = False
    r0 = warped[:, :, 0] - prev[:, :, 0]
    g = (0.5 / factor) * (warped[:, :, 1:] + prev[:, :, 1:])
    return r0, g, valid


def _median_from_counts(counts, n):
    """counts (..., J) of |r| <= THRESHOLDS, n (...) -> median |r| (log-interpolated)."""
    half = n[..., None] / 2
    above = counts >= half
    j = np.argmax(above, axis=-1)
    found = above.any(axis=-1)
    lower = np.take_along_axis(counts, np.maximum(j - 1, 0)[..., None], -1)[..., 0]
    lower = np.where(j == 0, 0.0, lower)
    upper = np.take_along_axis(counts, j[..., None], -1)[..., 0]
    frac = np.clip((n / 2 - lower) / np.maximum(upper - lower, 1e-9), 0, 1)
    median = THRESHOLDS[j] * 2.0 ** (frac - 1)
    return np.where(found, median, THRESHOLDS[-1])


def _scales(r0, valid, lay, settings):
    absr = np.abs(r0)
    v = valid.astype(np.float32)
    stack = np.dstack([v] + [v * (absr <= t) for t in THRESHOLDS]).astype(np.float32)
    sums = _window(_pool(stack, lay, [(0, 0)]), lay, 0, 0)
    n = sums[:, :, 0]
    med = _median_from_counts(sums[:, :, 1:], n)
    return np.where(n > 0, np.maximum(MAD_TO_SIGMA * med, settings.min_scale), settings.min_scale).astype(np.float32)


def _chol_solve(N, r):
    """N (p,p,n) SPD, r (p,n) -> x (p,n), L (p,p,n)."""
    p = N.shape[0]
    L = np.zeros_like(N)
    for j in range(p):
        s = N[j, j] - sum(L[j, k] ** 2 for k in range(j))
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, p):
            L[i, j] = (N[i, j] - sum(L[i, k] * L[j, k] for k in range(j))) / L[j, j]
    z = np.zeros_like(r)
    for i in range(p):
        z[i] = (r[i] - sum(L[i, k] * z[k] for k in range(i))) / L[i, i]
    x = np.zeros_like(r)
    for i in reversed(range(p)):
        x[i] = (z[i] - sum(L[k, i] * x[k] for k in range(i + 1, p))) / L[i, i]
    return x, L


def _inverse_entries(L, idx):
    """entries (i,j) for i,j in idx of N^-1 given Cholesky L."""
    p = L.shape[0]
    cols = {}
    for i in idx:
        z = np.zeros((p,) + L.shape[2:])
        for a in range(p):
            e = 1.0 if a == i else 0.0
            z[a] = (e - sum(L[a, k] * z[k] for k in range(a))) / L[a, a]
        cols[i] = z
    return {(i, j): (cols[i] * cols[j]).sum(0) for i in idx for j in idx}


def _normal_equations(gg_sums, gy_sums, lay, model):
    """assemble N (p,p,n...), rhs (p,n...) from pooled block moments."""
    phis = _PHI[model]
    h = lay.side / 2
    cache = {}

    def gg(a, b):
        if (a, b) not in cache:
            cache[a, b] = _window(gg_sums, lay, a, b)
        return cache[a, b]

    m = len(phis)
    p = 2 * m
    hn, wn = lay.shape
    N = np.empty((p, p, hn, wn))
    pair = {(0, 0): 0, (0, 1): 1, (1, 0): 1, (1, 1): 2}
    for ci in range(2):
        for i, (ai, bi) in enumerate(phis):
            for cj in range(2):
                for j, (aj, bj) in enumerate(phis):
                    a, b = ai + aj, bi + bj
                    N[ci * m + i, cj * m + j] = gg(a, b)[:, :, pair[ci, cj]] / h ** (a + b)
    rhs = np.empty((p, hn, wn))
    for i, (a, b) in enumerate(phis):
        mom = _window(gy_sums, lay, a, b) / h ** (a + b)
        rhs[i] = mom[:, :, 0]
        rhs[m + i] = mom[:, :, 1]
    return N, rhs


def compute_field(prev_pyr, cur_pyr, fit, settings, passes=PASSES):
    model = local_model(settings)
    orders_gg = [(0, 0)] if model == "translation" else [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]
    orders_gy = [(0, 0)] if model == "translation" else [(0, 0), (1, 0), (0, 1)]
    gfull = global_flow(fit, prev_pyr.base.shape)
    n_levels = len(prev_pyr.levels)
    nodes, prev_lay = None, None
    m = 1 if model == "translation" else 3
    for level in reversed(range(n_levels)):
        factor = 2**level
        prev, cur = prev_pyr.levels[level], cur_pyr.levels[level]
        shape = prev.shape[:2]
        lay = layout(settings, level, shape)
        gflow = np.ascontiguousarray(gfull[::factor, ::factor])
        if factor == 1:
            omega = fit.weights
        else:
            omega = cv2.resize(fit.weights, None, fx=1 / factor, fy=1 / factor, interpolation=cv2.INTER_AREA)
            omega = np.pad(omega, ((0, max(0, shape[0] - omega.shape[0])), (0, max(0, shape[1] - omega.shape[1]))), mode="edge")[:shape[0], :shape[1]]
        dom = omega >= 0.5
        if nodes is None:
            u4 = np.zeros(shape + (4,), np.float32)
        else:
            u4 = _to_pixels(nodes, prev_lay, 2 ** prev_lay.level, shape, factor)
        for i in range(passes):
            u = np.where(dom[:, :, None], u4[:, :, :2], u4[:, :, 2:])
            r0, g, valid = _linearise(prev, cur, gflow + u, factor, settings)
            sig_nodes = _scales(r0, valid, lay, settings)
            sig = _to_pixels(sig_nodes, lay, factor, shape, factor)
            w = (robust_weights(settings.robust_cost, r0, sig) * valid).astype(np.float64)
            gx, gy = g[:, :, 0].astype(np.float64), g[:, :, 1].astype(np.float64)
            y = gx * u[:, :, 0] + gy * u[:, :, 1] - r0
            lam = (sig_nodes.astype(np.float64) / THETA_PRIOR_STD) ** 2
            info = valid * (gx * gx + gy * gy)
            sup = _window(_pool(np.dstack((info * dom, info)), lay, [(0, 0)]), lay, 0, 0)
            dominant = sup[:, :, 0] >= 0.5 * sup[:, :, 1]
            fields = []
            for memb in (dom, ~dom):
                wm = w * memb
                wgx, wgy = wm * gx, wm * gy
                gg_stack = np.dstack((wgx * gx, wgx * gy, wgy * gy))
                gy_stack = np.dstack((wgx * y, wgy * y))
                N, rhs = _normal_equations(_pool(gg_stack, lay, orders_gg), _pool(gy_stack, lay, orders_gy), lay, model)
                for k in range(2 * m):
                    N[k, k] += lam
                theta, L = _chol_solve(N, rhs)
                fields.append(np.dstack((theta[0], theta[m])).astype(np.float32))
            nodes = np.dstack(fields)
            u4 = _to_pixels(nodes, lay, factor, shape, factor)
        prev_lay = lay
    t_nodes = np.where(dominant[:, :, None], nodes[:, :, :2], nodes[:, :, 2:])
    return gfull, t_nodes, lay


def exact_local_motion(prev_gray, cur_gray, xy, settings, passes=PASSES):
    model = local_model(settings)
    phis = _PHI[model]
    m = len(phis)
    p = 2 * m
    levels_g = usable_levels(prev_gray.shape, settings.levels)
    n_levels = local_levels(prev_gray.shape, settings.levels)
    depth = max(levels_g, n_levels)
    prev_pyr, cur_pyr = build_pyramid(prev_gray, depth), build_pyramid(cur_gray, depth)
    fit = estimate_from_pyramids(Pyramid(prev_pyr.base, prev_pyr.levels[:levels_g]),
                                 Pyramid(cur_pyr.base, cur_pyr.levels[:levels_g]), settings)
    gfull = global_flow(fit, prev_gray.shape)
    xy = np.asarray(xy, np.float64)
    M = len(xy)
    t = np.zeros((M, 2))
    lin = np.zeros((M, 2, 2))  # du/dd, dimensionless
    for level in reversed(range(n_levels)):
        factor = 2**level
        prev, cur = prev_pyr.levels[level], cur_pyr.levels[level]
        hgt, wid = prev.shape[:2]
        lay = layout(settings, level, (hgt, wid))
        n = lay.side
        half = n / 2
        c = xy / factor  # level px
        start = np.ceil(c - half).astype(int)  # (M, 2)
        k = np.arange(n)
        sx = start[:, 0, None, None] + k[None, None, :]  # (M,1,n)
        sy = start[:, 1, None, None] + k[None, :, None]  # (M,n,1)
        sx, sy = np.broadcast_arrays(sx, sy)
        inframe = (sx >= 1) & (sx <= wid - 2) & (sy >= 1) & (sy <= hgt - 2)
        cx, cy = np.clip(sx, 0, wid - 1), np.clip(sy, 0, hgt - 1)
        pv = prev[cy, cx].astype(np.float64)  # (M,n,n,3)
        gl = gfull[::factor, ::factor][cy, cx].astype(np.float64)  # (M,n,n,2)
        d = np.stack((sx - c[:, 0, None, None], sy - c[:, 1, None, None]), -1)  # level px
        phi = np.stack([(d[..., 0] / half) ** a * (d[..., 1] / half) ** b for a, b in phis], -1)  # (M,n,n,m)
        textured = pv[..., 1] ** 2 + pv[..., 2] ** 2 >= settings.min_gradient**2
        for it in range(passes):
            u = t[:, None, None, :] + np.einsum("mij,mxyj->mxyi", lin, d * factor)
            pos = np.stack((sx, sy), -1) + (gl + u) / factor
            inside = (pos[..., 0] >= 0) & (pos[..., 0] <= wid - 1) & (pos[..., 1] >= 0) & (pos[..., 1] <= hgt - 1)
            cv = _sample(cur, pos.reshape(-1, 2).astype(np.float32)).reshape(pv.shape).astype(np.float64)
            r0 = cv[..., 0] - pv[..., 0]
            g = (0.5 / factor) * (cv[..., 1:] + pv[..., 1:])
            valid = inframe & inside & textured
            rm = np.where(valid, r0, np.nan).reshape(M, -1)
            med = np.nanmedian(rm, axis=1, keepdims=True) if valid.any() else None
            with np.errstate(all="ignore"):
                med = np.nanmedian(rm, axis=1, keepdims=True)
                mad = np.nanmedian(np.abs(rm - med), axis=1)
            sig = np.where(valid.reshape(M, -1).any(1), np.maximum(MAD_TO_SIGMA * np.nan_to_num(mad), settings.min_scale), settings.min_scale)
            w = robust_weights(settings.robust_cost, r0, sig[:, None, None]) * valid
            y = (g * u).sum(-1) - r0
            J = np.concatenate((g[..., :1] * phi, g[..., 1:] * phi), -1).reshape(M, -1, p)
            wf = w.reshape(M, -1)
            N = np.einsum("mki,mk,mkj->mij", J, wf, J) + ((sig / THETA_PRIOR_STD) ** 2)[:, None, None] * np.eye(p)
            b = np.einsum("mki,mk,mk->mi", J, wf, y.reshape(M, -1))
            theta = np.linalg.solve(N, b[..., None])[..., 0]
            t = np.stack((theta[:, 0], theta[:, m]), -1)
            if m == 3:
                lin = np.stack((theta[:, 1:3], theta[:, 4:6]), 1) / (half * factor)
    return t + np.stack([ _bilin(gfull[..., i], xy) for i in range(2)], -1)


def _bilin(img, xy):
    return _sample(np.ascontiguousarray(img[:, :, None]), xy.astype(np.float32))[:, 0].astype(np.float64)
