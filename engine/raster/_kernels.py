"""numba kernels of the CPU rasterizer: tile binning, compositing forward, hand-derived backward.

Imported lazily by ``engine.raster.cpu`` (numba is optional). The compositing kernels
are float32 and process the pixels of a tile in lockstep, branch-free, so that LLVM
vectorises the pixel loop (exp is a branch-free polynomial for the same reason).
``cache=True``: the compiled code is stored next to this file (or
in numba's user cache dir when that is read-only), so only the first process compiles.

Layout: all C cameras are processed by one call. Gaussian ``g`` of camera ``c`` has the
flat index ``c * N + g``. Tiles are numbered ``c * tiles_y * tiles_x + ty * tiles_x + tx``;
``offsets[tile]:offsets[tile + 1]`` is that tile's slice of ``ids`` (flat Gaussian indices,
front to back).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..numba_cache import install_cache_locator

install_cache_locator(__name__)

ALPHA_THRESHOLD = 1.0 / 255.0
TRANSMITTANCE_STOP = 1e-4
# power above log(255 * opacity) + margin means alpha < 1/255 for sure: skip exp()
LOG_MARGIN = 1e-4
N_GRAD = 6  # per-intersection gradient slots before the features: mx, my, ca, cb, cc, opacity


@njit(cache=True, nogil=True, inline="always")
def _ellipse_setup(A, B, C, L):
    """Per-Gaussian constants of the ellipse 0.5 [dx dy] [[A B] [B C]] [dx dy]^T <= L for
    ``_ellipse_yspan``, computed once per Gaussian rather than once per tile column:
    (usable, x half-width xe, y half-height ye, 2 L C, det, 1 / C, -B / C, dx of the
    topmost point)."""
    det = A * C - B * B
    if not (det > 0.0 and A > 0.0 and C > 0.0 and L > 0.0):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    xe = math.sqrt(2.0 * L * C / det)
    ye = math.sqrt(2.0 * L * A / det)
    inv_c = 1.0 / C
    return True, xe, ye, 2.0 * L * C, det, inv_c, -B * inv_c, -B * ye / A


@njit(cache=True, nogil=True, inline="always")
def _ellipse_yspan(mx, my, usable, xe, ye, two_lc, det, inv_c, nb_c, t, xa, xb):
    """y-interval (lo, hi) of the ellipse (constants from ``_ellipse_setup``) over the x-band
    xa <= x <= xb (lo > hi: the band misses it). Exact: the top / bottom of the band's
    slice is the ellipse's own top / bottom when that lies in the band, else a band edge."""
    if not usable:
        return -1e30, 1e30  # degenerate: no culling
    da = max(xa - mx, -xe)
    db = min(xb - mx, xe)
    if da > db:
        return 1.0, -1.0
    ra = math.sqrt(max(two_lc - det * da * da, 0.0)) * inv_c
    rb = math.sqrt(max(two_lc - det * db * db, 0.0)) * inv_c
    ca = nb_c * da
    cb = nb_c * db
    hi = ye if (da <= t and t <= db) else max(ca + ra, cb + rb)
    lo = -ye if (da <= -t and -t <= db) else min(ca - ra, cb - rb)
    return my + lo - 1e-3, my + hi + 1e-3


@njit(cache=True, nogil=True, inline="always")  # a call per Gaussian passed ~15 arguments
def _visit(g, means2d, conics, opac, radii_xy, tile_size, tiles_x, tiles_y, width, height,
           base, write, at, tile_out, span_out):
    """Tiles (and, per tile, the rows [r0, r1)) that Gaussian g can reach with alpha >= 1/255.
    Counts them, and writes them at ``at`` when ``write``."""
    mx = np.float64(means2d[g, 0])
    my = np.float64(means2d[g, 1])
    ry = np.float64(radii_xy[g, 1])
    x0, x1, y0, y1 = _bbox_tiles(g, means2d, radii_xy, tile_size, tiles_x, tiles_y)
    # power <= log(255 * opacity) <=> alpha >= 1/255 (margin for float32 rounding)
    L = math.log(max(np.float64(opac[g]), 1e-30) * 255.0) + LOG_MARGIN
    A = np.float64(conics[g, 0])
    B = np.float64(conics[g, 1])
    C = np.float64(conics[g, 2])
    usable, xe, ye, two_lc, det, inv_c, nb_c, t = _ellipse_setup(A, B, C, L)
    n = 0
    for tx in range(x0, x1):
        xa = tx * tile_size + 0.5
        xb = min((tx + 1) * tile_size, width) - 0.5
        lo, hi = _ellipse_yspan(mx, my, usable, xe, ye, two_lc, det, inv_c, nb_c, t, xa, xb)
        lo = max(lo, my - ry)
        hi = min(hi, my + ry)
        if lo > hi:
            continue
        # pixel rows whose centres lie in [lo, hi]
        p_lo = max(math.ceil(lo - 0.5), 0.0)
        p_hi = min(math.floor(hi - 0.5), height - 1.0)
        if p_lo > p_hi:
            continue
        ty0 = max(int(p_lo) // tile_size, y0)
        ty1 = min(int(p_hi) // tile_size + 1, y1)
        for ty in range(ty0, ty1):
            if write:
                r0 = max(int(p_lo) - ty * tile_size, 0)
                r1 = min(int(p_hi) - ty * tile_size + 1, tile_size)
                tile_out[at + n] = base + ty * tiles_x + tx
                span_out[at + n] = r0 | (r1 << 8)
            n += 1
    return n


@njit(cache=True, nogil=True, inline="always")
def _bbox_tiles(g, means2d, radii_xy, tile_size, tiles_x, tiles_y):
    mx = np.float64(means2d[g, 0])
    my = np.float64(means2d[g, 1])
    rx = np.float64(radii_xy[g, 0])
    ry = np.float64(radii_xy[g, 1])
    x0 = int(min(max(math.floor((mx - rx - 0.5) / tile_size), 0.0), tiles_x))
    x1 = int(min(max(math.floor((mx + rx - 0.5) / tile_size) + 1.0, 0.0), tiles_x))
    y0 = int(min(max(math.floor((my - ry - 0.5) / tile_size), 0.0), tiles_y))
    y1 = int(min(max(math.floor((my + ry - 0.5) / tile_size) + 1.0, 0.0), tiles_y))
    return x0, x1, y0, y1


@njit(cache=True, nogil=True)
def depth_order(radii_xy, depth_bits):
    """Flat indices c * N + g [V] int64 of the visible Gaussians (radii_xy [C*N,2] int32,
    x radius > 0), sorted by camera, then depth, stable (ties keep index order).
    depth_bits [C,N] uint32: the float32 depths' bit patterns. An LSD radix sort (4 passes
    of 8 bits) of order-preserving keys: 1.2 ms for 44k depths against 2.9 ms for the
    numpy argsort of int64 (bits, index) keys it replaces."""
    C, N = depth_bits.shape
    V = 0
    for i in range(C * N):
        if radii_xy[i, 0] > 0:
            V += 1
    order = np.empty(V, np.int64)
    tmp = np.empty(V, np.int64)
    keys = np.empty(V, np.uint32)
    ktmp = np.empty(V, np.uint32)
    hist = np.empty(257, np.int64)
    at = 0
    for c in range(C):
        n = 0
        for g in range(N):
            if radii_xy[c * N + g, 0] > 0:
                b = depth_bits[c, g]
                if b == np.uint32(0x80000000):
                    b = np.uint32(0)  # -0.0 ties with 0.0, as in a float sort
                # float order -> unsigned order: flip negatives entirely, set the sign bit
                # of the others
                keys[at + n] = ~b if (b >> np.uint32(31)) != 0 else b | np.uint32(0x80000000)
                order[at + n] = c * N + g
                n += 1
        if n == 0:
            continue
        for sh in range(0, 32, 8):
            shift = np.uint32(sh)
            hist[:] = 0
            for m in range(at, at + n):
                hist[np.int64((keys[m] >> shift) & np.uint32(255)) + 1] += 1
            if hist[np.int64((keys[at] >> shift) & np.uint32(255)) + 1] == n:
                continue  # every key has this digit: the pass would not move anything
            for d in range(1, 257):
                hist[d] += hist[d - 1]
            for m in range(at, at + n):
                d = np.int64((keys[m] >> shift) & np.uint32(255))
                j = at + hist[d]
                hist[d] += 1
                ktmp[j] = keys[m]
                tmp[j] = order[m]
            keys[at:at + n] = ktmp[at:at + n]
            order[at:at + n] = tmp[at:at + n]
        at += n
    return order


@njit(parallel=True, cache=True)
def bin_gaussians(means2d, conics, opac, radii_xy, order, n_per_cam, n_cams, tile_size,
                  tiles_x, tiles_y, width, height):
    """Tile lists. means2d [G,2], conics [G,3], opac [G], radii_xy [G,2] int32, order [V]
    int64: visible flat indices sorted by (camera, depth). A tile gets a Gaussian only if
    the Gaussian's alpha >= 1/255 ellipse covers one of its pixel centres (exact, not the
    bounding box). Returns offsets [C*T+1] int64, ids [M] int32 (front to back per tile)
    and spans [M] int32: the tile rows r0 | r1 << 8 that the Gaussian reaches."""
    n_tiles = tiles_x * tiles_y
    V = order.shape[0]
    # pass 1: bounding-box tile counts (an upper bound) -> slots per Gaussian (serial, with
    # the prefix sum: 0.4 ms; as a parallel loop it cost more CPU time than it saved wall)
    ub = _slot_starts(order, means2d, radii_xy, tile_size, tiles_x, tiles_y)
    tile_of = np.empty(ub[V], np.int64)
    span_of = np.empty(ub[V], np.int32)
    cnt = np.zeros(V, np.int64)
    # pass 2: the tiles the ellipse really reaches, written into those slots
    for k in prange(V):
        g = order[k]
        # (a 64-bit division per Gaussian is ~0.8 ms here: skipped for one camera)
        base = (g // n_per_cam) * n_tiles if n_cams > 1 else 0
        if tile_size == 8:  # a constant: its divisions become shifts (~1 ms of CPU here)
            cnt[k] = _visit(g, means2d, conics, opac, radii_xy, 8, tiles_x, tiles_y,
                            width, height, base, True, ub[k], tile_of, span_of)
        else:
            cnt[k] = _visit(g, means2d, conics, opac, radii_xy, tile_size, tiles_x, tiles_y,
                            width, height, base, True, ub[k], tile_of, span_of)
    return _sort_by_tile(order, ub, cnt, tile_of, span_of, n_cams * n_tiles)


@njit(cache=True, nogil=True)
def _slot_starts(order, means2d, radii_xy, tile_size, tiles_x, tiles_y):
    V = order.shape[0]
    ub = np.zeros(V + 1, np.int64)
    for k in range(V):
        x0, x1, y0, y1 = _bbox_tiles(order[k], means2d, radii_xy, tile_size, tiles_x, tiles_y)
        ub[k + 1] = ub[k] + max(x1 - x0, 0) * max(y1 - y0, 0)
    return ub


@njit(cache=True, nogil=True)
def _sort_by_tile(order, ub, cnt, tile_of, span_of, n_all_tiles):
    """Stable counting sort of the intersections by tile (the slots are already front to
    back). Its own serial function: inside ``bin_gaussians``' parallel=True body these
    loops measured ~2 ms more CPU time (320x240 / 50k; numba's parfor passes reshape them)."""
    V = order.shape[0]
    offsets = np.zeros(n_all_tiles + 1, np.int64)
    for k in range(V):
        for m in range(ub[k], ub[k] + cnt[k]):
            offsets[tile_of[m] + 1] += 1
    for i in range(1, offsets.shape[0]):
        offsets[i] += offsets[i - 1]
    fill = offsets[:-1].copy()
    M = offsets[-1]
    ids = np.empty(M, np.int32)
    spans = np.empty(M, np.int32)
    for k in range(V):
        g = order[k]
        for m in range(ub[k], ub[k] + cnt[k]):
            t = tile_of[m]
            j = fill[t]
            ids[j] = np.int32(g)
            spans[j] = span_of[m]
            fill[t] = j + 1
    return offsets, ids, spans


_F = np.float32
F0 = _F(0.0)
F1 = _F(1.0)
FHALF = _F(0.5)
F_THR = _F(ALPHA_THRESHOLD)
F_STOP = _F(TRANSMITTANCE_STOP)
F_QMAX = _F(7.0)        # exp(-7) < 1/255: anything beyond is skipped whatever the approximation
F_QSCALE = _F(1.0 / 16.0)
# Taylor coefficients of exp(-r), r in [0, 7/16]; the result is squared 4 times.
E1 = _F(-1.0)
E2 = _F(1.0 / 2.0)
E3 = _F(-1.0 / 6.0)
E4 = _F(1.0 / 24.0)
E5 = _F(-1.0 / 120.0)
E6 = _F(1.0 / 720.0)
E7 = _F(-1.0 / 5040.0)
N_FEAT = 4  # rgb + depth


@njit(cache=True, nogil=True, inline="always")
def exp_neg(q):
    """exp(-q) for float32 q in [0, 7], branch-free (vectorises; ~1e-6 relative error)."""
    r = q * F_QSCALE
    # Estrin's scheme: 4 dependent operations instead of Horner's 7 (the compositing loops
    # are bound by this chain's latency, not by their arithmetic throughput)
    r2 = r * r
    r4 = r2 * r2
    e = (F1 + E1 * r + (E2 + E3 * r) * r2) + ((E4 + E5 * r) + (E6 + E7 * r) * r2) * r4
    e = e * e
    e = e * e
    e = e * e
    return e * e


@njit(cache=True, nogil=True, inline="always")
def _row_span(span, tile_size):
    """Pixel slots [p0, p1) of the tile rows r0 | r1 << 8 that binning found reachable."""
    r0 = span & 255
    r1 = span >> 8
    # LLVM's vector loop takes >= 16 lanes; a lone short row would run scalar: widen it
    while (r1 - r0) * tile_size < 16 and (r1 - r0) < tile_size:
        if r1 < tile_size:
            r1 += 1
        else:
            r0 -= 1
    return np.uint64(r0 * tile_size), np.uint64(r1 * tile_size)  # unsigned: no wraparound checks


@njit(cache=True, nogil=True, error_model="numpy")
def _fwd_tile(tile, packed, spans, offsets, height, width, tile_size,
              tiles_x, n_tiles, amax, out_feat, out_alpha, final_t, last_i):
    ts2 = tile_size * tile_size
    c = tile // n_tiles
    t = tile - c * n_tiles
    ty = t // tiles_x
    tx = t - ty * tiles_x
    s = offsets[tile]
    n = offsets[tile + 1] - s
    y0 = ty * tile_size
    x0 = tx * tile_size
    pxs = np.empty(ts2, np.float32)
    pys = np.empty(ts2, np.float32)
    T = np.ones(ts2, np.float32)
    act = np.empty(ts2, np.int32)
    last = np.full(ts2, -1, np.int32)
    a0 = np.zeros(ts2, np.float32)
    a1 = np.zeros(ts2, np.float32)
    a2 = np.zeros(ts2, np.float32)
    a3 = np.zeros(ts2, np.float32)
    n_act = 0
    for p in range(ts2):
        py = y0 + p // tile_size
        px = x0 + p % tile_size
        pxs[p] = _F(px) + FHALF
        pys[p] = _F(py) + FHALF
        inside = 1 if (py < height and px < width) else 0
        act[p] = inside
        n_act += inside
    for i in range(n):
        k = s + i  # packed: this tile's Gaussians, contiguous and front to back
        gx = packed[k, 0]
        gy = packed[k, 1]
        ca = packed[k, 2]
        cb = packed[k, 3]
        cc = packed[k, 4]
        op = packed[k, 5]
        f0 = packed[k, 6]
        f1 = packed[k, 7]
        f2 = packed[k, 8]
        f3 = packed[k, 9]
        # only the tile rows within the Gaussian's y radius can reach alpha >= 1/255
        p0, p1 = _row_span(spans[s + i], tile_size)
        for p in range(p0, p1):
            dx = gx - pxs[p]
            dy = gy - pys[p]
            power = FHALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
            q = min(max(power, F0), F_QMAX)
            alpha = min(amax, op * exp_neg(q))
            tp = T[p]
            nt = tp * (F1 - alpha)
            ok = (power >= F0) and (alpha >= F_THR) and (act[p] != 0)
            use = ok and (nt > F_STOP)
            w = alpha * tp if use else F0
            a0[p] += w * f0
            a1[p] += w * f1
            a2[p] += w * f2
            a3[p] += w * f3
            T[p] = nt if use else tp
            last[p] = i if use else last[p]
            act[p] = 0 if (ok and not use) else act[p]
        # any pixel still open? (a separate scan keeps the loop above vectorisable)
        n_act = 0
        for p in range(ts2):
            if act[p] != 0:
                n_act = 1
                break
        if n_act == 0:
            break
    for p in range(ts2):
        py = y0 + p // tile_size
        px = x0 + p % tile_size
        if py < height and px < width:
            out_feat[c, py, px, 0] = a0[p]
            out_feat[c, py, px, 1] = a1[p]
            out_feat[c, py, px, 2] = a2[p]
            out_feat[c, py, px, 3] = a3[p]
            out_alpha[c, py, px] = F1 - T[p]
            final_t[c, py, px] = T[p]
            last_i[c, py, px] = last[p]


# ----------------------------------------------------------- 8x8 tiles (the default size)
# The same compositing as ``_fwd_tile`` / ``_bwd_tile``, specialised to 8x8 tiles: a tile's
# per-pixel state lives in ONE scratch array at compile-time offsets, and each reachable
# tile row is a fixed 8-lane loop (one AVX2 vector). With ten separate scratch arrays and a
# variable-length pixel loop LLVM emitted runtime alias checks and a loop prologue per
# Gaussian and tile, which cost more than the arithmetic: measured 1.47x (forward) and
# 1.36x (backward) less CPU time at 320x240 / 50k Gaussians. Results equal the generic
# kernels' to float32 rounding (FMA contraction), which tests/test_raster.py checks.
TS = 8
TS2 = 64
# forward state slots (float32, TS2 each): pixel x, y, transmittance, open, last index, 4 features
SPX, SPY, ST, SACT, SLAST, SA0, SA1, SA2, SA3 = 0, 64, 128, 192, 256, 320, 384, 448, 512

@njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract", "nsz", "arcp"})
def _fwd_tile8(tile, packed, spans, offsets, height, width, tiles_x, n_tiles, amax, out_feat, out_alpha,
               final_t, last_i):
    c = tile // n_tiles
    t = tile - c * n_tiles
    ty = t // tiles_x
    tx = t - ty * tiles_x
    s = offsets[tile]
    n = offsets[tile + 1] - s
    y0 = ty * TS
    x0 = tx * TS
    st = np.zeros(9 * TS2, np.float32)  # last index as float32: exact below 2**24 Gaussians per tile
    for p in range(TS2):
        py = y0 + p // TS
        px = x0 + p % TS
        st[SPX + p] = _F(px) + FHALF
        st[SPY + p] = _F(py) + FHALF
        st[ST + p] = F1
        st[SACT + p] = F1 if (py < height and px < width) else F0
        st[SLAST + p] = _F(-1.0)
    for i in range(n):
        k = s + i
        gx = packed[k, 0]
        gy = packed[k, 1]
        ca = packed[k, 2]
        cb = packed[k, 3]
        cc = packed[k, 4]
        op = packed[k, 5]
        f0 = packed[k, 6]
        f1 = packed[k, 7]
        f2 = packed[k, 8]
        f3 = packed[k, 9]
        fi = _F(i)
        sp = spans[k]
        r0 = sp & 255
        r1 = sp >> 8
        for r in range(r0, r1):
            base = r * TS
            for j in range(TS):
                p = base + j
                dx = gx - st[SPX + p]
                dy = gy - st[SPY + p]
                power = FHALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                q = min(max(power, F0), F_QMAX)
                alpha = min(amax, op * exp_neg(q))
                tp = st[ST + p]
                act = st[SACT + p]
                nt = tp * (F1 - alpha)
                # `&`, not `and`: no short circuit, so no conditional loads; every state
                # update is an exact arithmetic blend with a 0 / 1 mask rather than a
                # select of the old value, which LLVM turned into vmaskmovps stores
                # (microcoded on AMD Zen: they cost more than the exp)
                okf = F1 if ((power >= F0) & (alpha >= F_THR)) else F0
                okf = okf * act  # act is 0 or 1
                usef = okf if nt > F_STOP else F0
                au = alpha * usef  # alpha where it is composited, else exactly 0
                w = au * tp
                st[SA0 + p] += w * f0
                st[SA1 + p] += w * f1
                st[SA2 + p] += w * f2
                st[SA3 + p] += w * f3
                st[ST + p] = tp * (F1 - au)  # nt where used, tp exactly otherwise
                last = st[SLAST + p]
                st[SLAST + p] = last + (fi - last) * usef  # small integers: exact
                st[SACT + p] = act - okf + usef  # 0 where ok and not used, else unchanged
        if (i & 3) == 3:  # any pixel still open? (checked every 4th Gaussian: cheaper)
            any_act = False
            for p in range(TS2):
                if st[SACT + p] != F0:
                    any_act = True
                    break
            if not any_act:
                break
    for p in range(TS2):
        py = y0 + p // TS
        px = x0 + p % TS
        if py < height and px < width:
            out_feat[c, py, px, 0] = st[SA0 + p]
            out_feat[c, py, px, 1] = st[SA1 + p]
            out_feat[c, py, px, 2] = st[SA2 + p]
            out_feat[c, py, px, 3] = st[SA3 + p]
            out_alpha[c, py, px] = F1 - st[ST + p]
            final_t[c, py, px] = st[ST + p]
            last_i[c, py, px] = np.int32(st[SLAST + p])


@njit(cache=True, nogil=True, inline="always")
def _even_rows(span):
    """The tile rows [r0, r1) of span r0 | r1 << 8, widened by one row inside the 8x8 tile
    when their number is odd, so that they are visited two at a time: two independent 8-lane
    chains per loop body. The compositing loops are bound by the latency of one row's chain
    (power -> exp -> alpha -> transmittance), not by throughput; a second row in flight
    hides it. The added row lies outside the Gaussian's 1/255 ellipse (binning is exact and
    conservative), so it changes nothing."""
    r0 = span & 255
    r1 = span >> 8
    if (r1 - r0) & 1:
        if r1 < TS:
            r1 += 1
        else:
            r0 -= 1
    return r0, r1


# backward state slots: pixel x, y, transmittance, last index, final transmittance times
# dL/dalpha, dL/dfeature 0..3, and S = sum_k b_k dL/dfeature_k where b_k is feature k
# composited behind the current Gaussian. dL/dalpha_i needs the b_k only through S, so S
# is carried instead of b_0..b_3 (4 loads, 4 stores and 4 FMAs less per tile row).
BPX, BPY, BT, BLAST, BTVA, BV0, BV1, BV2, BV3, BS = [j * TS2 for j in range(10)]
# then, after them, one Gaussian's per-lane gradient sums (TS lanes each): mean x, y, conic
# a, b, c, opacity, features 0..3
GN = 10
GL = 2 * TS  # lanes: two tile rows at a time
BG = 10 * TS2 + GL  # (+ GL: room for the row pair of (r & 7) = 7 as far as LLVM knows)
GX, GY, GA, GB, GC, GO, GF0, GF1, GF2, GF3 = [BG + j * GL for j in range(GN)]


# No "reassoc" in the backward kernels' fastmath: with it, LLVM may reorder the per-Gaussian
# sums differently when rasterize_bwd (parallel) is compiled in this process than in the code
# numba caches for the next process, so a run on a cold numba cache gave other gradients (and,
# 200 demo steps later, 23,943 against 24,305 Gaussians) than every later run; without it the
# bits are the same either way (tests/test_compile_reproducible.py). Cost measured at
# 320x240 / 50k, load ~1: composite backward 9.0 -> 10.5 ms wall, forward + backward ~+1.6 ms
# (docs/experiments/rasterizer.md "Reproducible across numba's cache").
@njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract", "nsz", "arcp"})
def _bwd_tile8(tile, packed, spans, offsets, height, width, tiles_x, n_tiles, amax, final_t, last_i, v_feat,
               v_alpha, v_isect):
    c = tile // n_tiles
    t = tile - c * n_tiles
    ty = t // tiles_x
    tx = t - ty * tiles_x
    s = offsets[tile]
    n = offsets[tile + 1] - s
    if n == 0:
        return
    y0 = ty * TS
    x0 = tx * TS
    st = np.zeros(BG + GN * GL, np.float32)
    i_max = -1
    for p in range(TS2):
        py = y0 + p // TS
        px = x0 + p % TS
        st[BPX + p] = _F(px) + FHALF
        st[BPY + p] = _F(py) + FHALF
        st[BT + p] = F1
        st[BLAST + p] = _F(-1.0)
        if py < height and px < width:
            tfv = final_t[c, py, px]
            st[BT + p] = tfv
            lp = last_i[c, py, px]
            st[BLAST + p] = _F(lp)
            i_max = max(i_max, lp)
            st[BTVA + p] = tfv * v_alpha[c, py, px]
            st[BV0 + p] = v_feat[c, py, px, 0]
            st[BV1 + p] = v_feat[c, py, px, 1]
            st[BV2 + p] = v_feat[c, py, px, 2]
            st[BV3 + p] = v_feat[c, py, px, 3]
    for k in range(s + i_max + 1, s + n):  # never composited here: zero gradient
        for j in range(v_isect.shape[1]):
            v_isect[k, j] = F0
    for i in range(i_max, -1, -1):
        k = s + i
        gx = packed[k, 0]
        gy = packed[k, 1]
        ca = packed[k, 2]
        cb = packed[k, 3]
        cc = packed[k, 4]
        op = packed[k, 5]
        f0 = packed[k, 6]
        f1 = packed[k, 7]
        f2 = packed[k, 8]
        f3 = packed[k, 9]
        fi = _F(i)
        # per-lane gradient sums over the rows, reduced once per Gaussian below (summing
        # the 8 lanes after every row cost ~40 shuffles and adds per row)
        for j in range(GN * GL):
            st[BG + j] = F0
        r0, r1 = _even_rows(spans[k])
        for r in range(r0, r1, 2):
            base = (r & 7) * TS  # (& 7: tells LLVM the row slots never reach the BG slots)
            for j in range(2 * TS):
                p = base + j
                dx = gx - st[BPX + p]
                dy = gy - st[BPY + p]
                power = FHALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                q = min(max(power, F0), F_QMAX)
                vis = exp_neg(q)
                raw = op * vis
                alpha = min(amax, raw)
                # `&`, not `and`: no short circuit, hence no masked (conditional) loads
                ok = (power >= F0) & (alpha >= F_THR) & (fi <= st[BLAST + p])
                ra = F1 / (F1 - alpha)
                tp = st[BT + p]
                # exact blend (okf is 0 or 1): a select with the loaded tp as one arm became
                # a masked store (vmaskmovps, microcoded on AMD Zen)
                okf = F1 if ok else F0
                tn = tp * (ra * okf + (F1 - okf))
                fac = alpha * tn if ok else F0
                v0 = st[BV0 + p]
                v1 = st[BV1 + p]
                v2 = st[BV2 + p]
                v3 = st[BV3 + p]
                fv = f0 * v0 + f1 * v1 + f2 * v2 + f3 * v3
                sb = st[BS + p]
                # = sum_k (f_k tn - b_k ra) v_k + T_final ra dL/dalpha
                v_a = tn * fv - ra * (sb - st[BTVA + p])
                st[GF0 + j] += fac * v0
                st[GF1 + j] += fac * v1
                st[GF2 + j] += fac * v2
                st[GF3 + j] += fac * v3
                st[BS + p] = sb + fac * fv
                st[BT + p] = tn
                v_sigma = -raw * v_a if (ok & (raw <= amax)) else F0
                # sums of v_sigma dx, v_sigma dy: the conic is applied once per Gaussian
                st[GX + j] += v_sigma * dx
                st[GY + j] += v_sigma * dy
                st[GA + j] += v_sigma * dx * dx
                st[GB + j] += v_sigma * dx * dy
                st[GC + j] += v_sigma * dy * dy
                st[GO + j] += v_sigma
        g_x = F0
        g_y = F0
        g_a = F0
        g_b = F0
        g_c = F0
        g_o = F0
        g_f0 = F0
        g_f1 = F0
        g_f2 = F0
        g_f3 = F0
        for j in range(GL):
            g_x += st[GX + j]
            g_y += st[GY + j]
            g_a += st[GA + j]
            g_b += st[GB + j]
            g_c += st[GC + j]
            g_o += st[GO + j]
            g_f0 += st[GF0 + j]
            g_f1 += st[GF1 + j]
            g_f2 += st[GF2 + j]
            g_f3 += st[GF3 + j]
        v_isect[k, 0] = ca * g_x + cb * g_y
        v_isect[k, 1] = cb * g_x + cc * g_y
        v_isect[k, 2] = FHALF * g_a
        v_isect[k, 3] = g_b
        v_isect[k, 4] = FHALF * g_c
        v_isect[k, 5] = -g_o / op if op > F0 else F0
        v_isect[k, 6] = g_f0
        v_isect[k, 7] = g_f1
        v_isect[k, 8] = g_f2
        v_isect[k, 9] = g_f3


@njit(parallel=True, cache=True)
def rasterize_fwd(packed, spans, offsets, n_cams, height, width, tile_size,
                  tiles_x, tiles_y, alpha_max, out_feat, out_alpha, final_t, last_i):
    """Front-to-back compositing, all pixels of a tile in lockstep (SIMD over pixels).
    packed [M,10] float32: per intersection (tile order, see ``pack``) mean x, y, conic a,
    b, c, opacity, 4 features; spans [M] int32: the tile rows r0 | r1 << 8 to visit.
    Outputs: out_feat [C,H,W,4], out_alpha [C,H,W], final_t [C,H,W] (transmittance left),
    last_i [C,H,W] int32 (index within the tile's list of the last Gaussian composited,
    -1 if none)."""
    n_tiles = tiles_x * tiles_y
    amax = _F(alpha_max)
    if tile_size == TS:
        for tile in prange(n_cams * n_tiles):
            _fwd_tile8(tile, packed, spans, offsets, height, width, tiles_x, n_tiles, amax,
                       out_feat, out_alpha, final_t, last_i)
    else:
        for tile in prange(n_cams * n_tiles):
            _fwd_tile(tile, packed, spans, offsets, height, width, tile_size,
                      tiles_x, n_tiles, amax, out_feat, out_alpha, final_t, last_i)


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"nsz"})  # no "reassoc": see _bwd_tile8
def _bwd_tile(tile, packed, spans, offsets, height, width, tile_size,
              tiles_x, n_tiles, amax, final_t, last_i, v_feat, v_alpha, v_isect):
    ts2 = tile_size * tile_size
    c = tile // n_tiles
    t = tile - c * n_tiles
    ty = t // tiles_x
    tx = t - ty * tiles_x
    s = offsets[tile]
    n = offsets[tile + 1] - s
    if n == 0:
        return
    y0 = ty * tile_size
    x0 = tx * tile_size
    pxs = np.empty(ts2, np.float32)
    pys = np.empty(ts2, np.float32)
    T = np.ones(ts2, np.float32)
    tfin = np.ones(ts2, np.float32)
    last = np.full(ts2, -1, np.int32)
    va = np.zeros(ts2, np.float32)
    v0 = np.zeros(ts2, np.float32)
    v1 = np.zeros(ts2, np.float32)
    v2 = np.zeros(ts2, np.float32)
    v3 = np.zeros(ts2, np.float32)
    b0 = np.zeros(ts2, np.float32)
    b1 = np.zeros(ts2, np.float32)
    b2 = np.zeros(ts2, np.float32)
    b3 = np.zeros(ts2, np.float32)
    i_max = -1
    for p in range(ts2):
        py = y0 + p // tile_size
        px = x0 + p % tile_size
        pxs[p] = _F(px) + FHALF
        pys[p] = _F(py) + FHALF
        if py < height and px < width:
            T[p] = final_t[c, py, px]
            tfin[p] = T[p]
            lp = last_i[c, py, px]
            last[p] = lp
            i_max = max(i_max, lp)
            va[p] = v_alpha[c, py, px]
            v0[p] = v_feat[c, py, px, 0]
            v1[p] = v_feat[c, py, px, 1]
            v2[p] = v_feat[c, py, px, 2]
            v3[p] = v_feat[c, py, px, 3]
    for k in range(s + i_max + 1, s + n):  # never composited here: zero gradient
        for j in range(v_isect.shape[1]):
            v_isect[k, j] = F0
    for i in range(i_max, -1, -1):
        k = s + i  # packed: this tile's Gaussians, contiguous and front to back
        gx = packed[k, 0]
        gy = packed[k, 1]
        ca = packed[k, 2]
        cb = packed[k, 3]
        cc = packed[k, 4]
        op = packed[k, 5]
        f0 = packed[k, 6]
        f1 = packed[k, 7]
        f2 = packed[k, 8]
        f3 = packed[k, 9]
        g_x = F0
        g_y = F0
        g_a = F0
        g_b = F0
        g_c = F0
        g_o = F0
        g_f0 = F0
        g_f1 = F0
        g_f2 = F0
        g_f3 = F0
        p0, p1 = _row_span(spans[s + i], tile_size)
        for p in range(p0, p1):
            dx = gx - pxs[p]
            dy = gy - pys[p]
            power = FHALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
            q = min(max(power, F0), F_QMAX)
            vis = exp_neg(q)
            raw = op * vis
            alpha = min(amax, raw)
            ok = (power >= F0) and (alpha >= F_THR) and (i <= last[p])
            ra = F1 / (F1 - alpha)
            tp = T[p]
            tn = tp * ra if ok else tp
            fac = alpha * tn if ok else F0
            v_a = (f0 * tn - b0[p] * ra) * v0[p] + (f1 * tn - b1[p] * ra) * v1[p] \
                + (f2 * tn - b2[p] * ra) * v2[p] + (f3 * tn - b3[p] * ra) * v3[p] \
                + tfin[p] * ra * va[p]
            g_f0 += fac * v0[p]
            g_f1 += fac * v1[p]
            g_f2 += fac * v2[p]
            g_f3 += fac * v3[p]
            b0[p] += fac * f0
            b1[p] += fac * f1
            b2[p] += fac * f2
            b3[p] += fac * f3
            T[p] = tn
            v_sigma = -raw * v_a if (ok and raw <= amax) else F0
            g_x += v_sigma * (ca * dx + cb * dy)
            g_y += v_sigma * (cb * dx + cc * dy)
            g_a += v_sigma * dx * dx
            g_b += v_sigma * dx * dy
            g_c += v_sigma * dy * dy
            g_o += v_sigma
        k = s + i
        v_isect[k, 0] = g_x
        v_isect[k, 1] = g_y
        v_isect[k, 2] = FHALF * g_a
        v_isect[k, 3] = g_b
        v_isect[k, 4] = FHALF * g_c
        v_isect[k, 5] = -g_o / op if op > F0 else F0
        v_isect[k, 6] = g_f0
        v_isect[k, 7] = g_f1
        v_isect[k, 8] = g_f2
        v_isect[k, 9] = g_f3


@njit(parallel=True, cache=True)
def rasterize_bwd(packed, spans, offsets, n_cams, height, width, tile_size,
                  tiles_x, tiles_y, alpha_max, final_t, last_i, v_feat, v_alpha, v_isect):
    """Back-to-front replay of each pixel from its final transmittance and last index
    (gsplat's rasterize_to_pixels backward), pixels of a tile in lockstep. v_feat
    [C,H,W,4], v_alpha [C,H,W] are the output gradients; v_isect [M, 10] receives the
    per-intersection gradients w.r.t. (mean x, mean y, conic a, b, c, opacity, feats 0..3)."""
    n_tiles = tiles_x * tiles_y
    amax = _F(alpha_max)
    if tile_size == TS:
        for tile in prange(n_cams * n_tiles):
            _bwd_tile8(tile, packed, spans, offsets, height, width, tiles_x, n_tiles, amax,
                       final_t, last_i, v_feat, v_alpha, v_isect)
    else:
        for tile in prange(n_cams * n_tiles):
            _bwd_tile(tile, packed, spans, offsets, height, width, tile_size,
                      tiles_x, n_tiles, amax, final_t, last_i, v_feat, v_alpha, v_isect)


@njit(parallel=True, cache=True)
def pack(means2d, conics, opac, feats, ids, packed):
    """packed[k] = (mean x, y, conic a, b, c, opacity, feats 0..3) of Gaussian ids[k]: the
    compositing kernels then read each tile's Gaussians contiguously instead of gathering
    them from all over memory twice (forward and backward)."""
    for k in prange(ids.shape[0]):
        g = ids[k]
        packed[k, 0] = means2d[g, 0]
        packed[k, 1] = means2d[g, 1]
        packed[k, 2] = conics[g, 0]
        packed[k, 3] = conics[g, 1]
        packed[k, 4] = conics[g, 2]
        packed[k, 5] = opac[g]
        packed[k, 6] = feats[g, 0]
        packed[k, 7] = feats[g, 1]
        packed[k, 8] = feats[g, 2]
        packed[k, 9] = feats[g, 3]


@njit(cache=True, nogil=True, inline="always")
def _split_record(dst, k, g, means2d, conics, opac, rgb, z, n_per_cam):
    """dst[k] = ``pack``'s record of projected Gaussian g (G = C * N index) from
    ``pack_split``'s inputs."""
    dst[k, 0] = means2d[g, 0]
    dst[k, 1] = means2d[g, 1]
    dst[k, 2] = conics[g, 0]
    dst[k, 3] = conics[g, 1]
    dst[k, 4] = conics[g, 2]
    dst[k, 5] = opac[g % n_per_cam]
    dst[k, 6] = rgb[g, 0]
    dst[k, 7] = rgb[g, 1]
    dst[k, 8] = rgb[g, 2]
    dst[k, 9] = z[g]


@njit(parallel=True, cache=True)
def pack_split(means2d, conics, opac, rgb, z, n_per_cam, ids, packed):
    """``pack`` for ``rasterization``'s fused path: the features come as rgb [G,3] and
    depth z [G] (G = C * N) and the opacities once per Gaussian, opac [N], not per camera
    (no torch concatenation or expansion, and none of their backward).

    Two passes (round 4): the Gaussians' records are first assembled in index order (five
    sequential streams), then gathered per intersection (one 40-byte record each). Gathering
    straight from the five arrays cost five cache misses per intersection: 2.3 -> 1.4 ms at
    320x240 / 50k (130k intersections) inside a forward+backward, whose other stages leave
    those arrays out of cache. With fewer intersections than Gaussians (small views, most
    Gaussians culled) the direct gather is kept."""
    G = means2d.shape[0]
    M = ids.shape[0]
    if M < G:  # few intersections per Gaussian (small views): the record pass would cost more
        for k in prange(M):
            _split_record(packed, k, ids[k], means2d, conics, opac, rgb, z, n_per_cam)
        return
    rec = np.empty((G, 10), np.float32)
    for g in prange(G):
        _split_record(rec, g, g, means2d, conics, opac, rgb, z, n_per_cam)
    for k in prange(M):
        g = ids[k]
        for j in range(10):
            packed[k, j] = rec[g, j]


@njit(cache=True, nogil=True)
def finish_image(out_feat, final_t, bg, depth_eps, out_rgb, out_depth):
    """After ``rasterize_fwd``: out_rgb [C,H,W,3] = colours over the background bg [C,3]
    (c + T bg), out_depth [C,H,W,1] = the expected depth (sum w z) / alpha where
    alpha > depth_eps, else 0 (alpha = 1 - T, the float32 value ``out_alpha`` holds)."""
    C, H, W, _ = out_feat.shape
    for c in range(C):
        b0 = bg[c, 0]
        b1 = bg[c, 1]
        b2 = bg[c, 2]
        for y in range(H):
            for x in range(W):
                t = final_t[c, y, x]
                out_rgb[c, y, x, 0] = out_feat[c, y, x, 0] + t * b0
                out_rgb[c, y, x, 1] = out_feat[c, y, x, 1] + t * b1
                out_rgb[c, y, x, 2] = out_feat[c, y, x, 2] + t * b2
                a = F1 - t
                out_depth[c, y, x, 0] = out_feat[c, y, x, 3] / a if a > depth_eps else F0


@njit(cache=True, nogil=True)
def finish_grads(v_rgb, v_alpha, v_depth, out_depth, final_t, bg, depth_eps, v_feat, v_alpha_raw):
    """Gradients of ``finish_image`` for ``rasterize_bwd``: v_rgb [C,H,W,3], v_alpha [C,H,W],
    v_depth [C,H,W] w.r.t. its outputs (out_depth [C,H,W,1] its depth) -> v_feat
    [C,H,W,4] and v_alpha_raw [C,H,W] w.r.t. the raw sums and alpha. d (c + (1 - alpha) bg)
    / d alpha = -bg; d (s / alpha) = ds / alpha - (s / alpha) dalpha / alpha."""
    C, H, W = final_t.shape
    for c in range(C):
        b0 = bg[c, 0]
        b1 = bg[c, 1]
        b2 = bg[c, 2]
        for y in range(H):
            for x in range(W):
                g0 = v_rgb[c, y, x, 0]
                g1 = v_rgb[c, y, x, 1]
                g2 = v_rgb[c, y, x, 2]
                v_feat[c, y, x, 0] = g0
                v_feat[c, y, x, 1] = g1
                v_feat[c, y, x, 2] = g2
                va = v_alpha[c, y, x] - (g0 * b0 + g1 * b1 + g2 * b2)
                a = F1 - final_t[c, y, x]
                if a > depth_eps:
                    gd = v_depth[c, y, x] / a
                    v_feat[c, y, x, 3] = gd
                    va -= gd * out_depth[c, y, x, 0]
                else:
                    v_feat[c, y, x, 3] = F0
                v_alpha_raw[c, y, x] = va


@njit(cache=True, nogil=True)
def scatter_grads(ids, v_isect, v_gauss):
    """v_gauss[ids[k]] += v_isect[k] (v_gauss [G, 6+D], zero-filled). Serial: a parallel
    gather per Gaussian through an inverse map measured 2.6x the CPU time (random reads of
    v_isect rows instead of one sequential pass)."""
    K = v_isect.shape[1]
    for k in range(ids.shape[0]):
        g = ids[k]
        for j in range(K):
            v_gauss[g, j] += v_isect[k, j]


# ------------------------------------------------------------------------------ projection
# EWA projection of N Gaussians into C cameras with a hand-derived backward, in float64
# (same rules as ``projection.project_gaussians``). float64 on purpose: the 2D covariance's
# determinant A C - B^2 cancels for thin Gaussians, the radii are ceil() of it (a float32
# rounding flips a radius, hence a tile list), and the tests hold the float64 path to
# 1e-10 of torch's float64 projection.
#
# SIMD over Gaussians (issue 13, round 4): per chunk of PROJ_CHUNK Gaussians the rotation
# times scale M = R(q) diag(s) goes to a [9, chunk] scratch, then for each camera one
# branch-free loop over the chunk (selects instead of `continue`, scalars instead of small
# scratch arrays, one read and one written array per stream) that LLVM vectorises 4 lanes
# wide; the natural log of the radius extent runs in a scalar loop of its own, once per
# Gaussian for all cameras. Same operations in the same order as the per-Gaussian scalar
# code it replaces, so the same bits: forward 3.75 -> 2.27 ms, backward 5.18 -> 3.83 ms at
# 50k Gaussians, one thread (320x240 benchmark scene).

PROJ_CHUNK = 256  # Gaussians per parallel work item (scratch arrays allocated once per item)


@njit(cache=True, nogil=True)
def _cam_table(viewmats, Ks, width, height):
    """[C, 8] float64: each camera's ``_cam_setup`` computed once per call rather than once
    per Gaussian and camera (four divisions each)."""
    C = viewmats.shape[0]
    out = np.empty((C, 8), np.float64)
    for c in range(C):
        v = _cam_setup(viewmats, Ks, c, width, height)
        for j in range(8):
            out[c, j] = v[j]
    return out


@njit(cache=True, nogil=True, inline="always")
def _cam_setup(viewmats, Ks, c, width, height):
    fx = np.float64(Ks[c, 0, 0])
    fy = np.float64(Ks[c, 1, 1])
    cx = np.float64(Ks[c, 0, 2])
    cy = np.float64(Ks[c, 1, 2])
    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    return (fx, fy, cx, cy, -(cx / fx + 0.3 * tan_x), (width - cx) / fx + 0.3 * tan_x,
            -(cy / fy + 0.3 * tan_y), (height - cy) / fy + 0.3 * tan_y)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _unit_quat(quats, n):
    """Normalised quaternion (w, x, y, z) and 1 / |q|; the identity and 0 if degenerate."""
    w = np.float64(quats[n, 0])
    x = np.float64(quats[n, 1])
    y = np.float64(quats[n, 2])
    z = np.float64(quats[n, 3])
    q2 = w * w + x * x + y * y + z * z
    ok = q2 > 1e-24
    inv = 1.0 / math.sqrt(q2 if ok else 1.0)
    return (w * inv if ok else 1.0, x * inv if ok else 0.0, y * inv if ok else 0.0,
            z * inv if ok else 0.0, inv if ok else 0.0)


@njit(cache=True, nogil=True, inline="always")
def _view_rt(viewmats, c):
    """Camera ``c``'s world-to-camera rotation, row-major, then translation (12 scalars)."""
    return (viewmats[c, 0, 0], viewmats[c, 0, 1], viewmats[c, 0, 2], viewmats[c, 1, 0],
            viewmats[c, 1, 1], viewmats[c, 1, 2], viewmats[c, 2, 0], viewmats[c, 2, 1],
            viewmats[c, 2, 2], viewmats[c, 0, 3], viewmats[c, 1, 3], viewmats[c, 2, 3])


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _cam_jacobian(means, n, rt, fx, fy, ulo, uhi, vlo, vhi, near, far):
    """Gaussian ``n``'s camera-space centre (px, py, pz), whether it lies in (near, far),
    1 / pz, the normalised image point (u, v) and its clamped copy (uc, vc), fx / pz, fy / pz
    and the rows of J R (the perspective Jacobian at the clamped point times the rotation),
    shared by ``project_fwd`` and ``project_bwd`` so both see the same operations in the same
    order (inlined: the chunk loops stay vectorised)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22, t0_, t1_, t2_ = rt
    mx = np.float64(means[n, 0])
    my = np.float64(means[n, 1])
    mz = np.float64(means[n, 2])
    px = r00 * mx + r01 * my + r02 * mz + t0_
    py = r10 * mx + r11 * my + r12 * mz + t1_
    pz = r20 * mx + r21 * my + r22 * mz + t2_
    inz = (pz > near) & (pz < far)
    iz = 1.0 / (pz if inz else 1.0)
    u = px * iz
    v = py * iz
    uc = min(max(u, ulo), uhi)
    vc = min(max(v, vlo), vhi)
    fxz = fx * iz
    fyz = fy * iz
    return (px, py, pz, iz, u, v, uc, vc, fxz, fyz,
            fxz * (r00 - uc * r20), fxz * (r01 - uc * r21), fxz * (r02 - uc * r22),
            fyz * (r10 - vc * r20), fyz * (r11 - vc * r21), fyz * (r12 - vc * r22))


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _quat_scale_soa(quats, scales, lo, hi, Ms):
    """Ms [9, chunk] <- M = R(q) diag(s) (row-major entries) of Gaussians lo..hi-1."""
    for n in range(lo, hi):
        i = n - lo
        w, x, y, z, _ = _unit_quat(quats, n)
        s0 = np.float64(scales[n, 0])
        s1 = np.float64(scales[n, 1])
        s2 = np.float64(scales[n, 2])
        Ms[0, i] = (1.0 - 2.0 * (y * y + z * z)) * s0
        Ms[1, i] = 2.0 * (x * y - w * z) * s1
        Ms[2, i] = 2.0 * (x * z + w * y) * s2
        Ms[3, i] = 2.0 * (x * y + w * z) * s0
        Ms[4, i] = (1.0 - 2.0 * (x * x + z * z)) * s1
        Ms[5, i] = 2.0 * (y * z - w * x) * s2
        Ms[6, i] = 2.0 * (x * z - w * y) * s0
        Ms[7, i] = 2.0 * (y * z + w * x) * s1
        Ms[8, i] = (1.0 - 2.0 * (x * x + y * y)) * s2


@njit(parallel=True, cache=True, error_model="numpy")
def project_fwd(means, quats, scales, opac, viewmats, Ks, width, height, near, far, eps2d,
                out_m2d, out_conic, out_z, out_radii):
    """means [N,3], quats [N,4] wxyz, scales [N,3], opac [N], viewmats [C,4,4], Ks [C,3,3]
    -> out_m2d [C,N,2], out_conic [C,N,3], out_z [C,N], out_radii [C,N,2] int32 (0 = culled).
    Depth-culled Gaussians get zero means2d / conics."""
    N = means.shape[0]
    C = viewmats.shape[0]
    cams = _cam_table(viewmats, Ks, width, height)
    for chunk in prange((N + PROJ_CHUNK - 1) // PROJ_CHUNK):
        lo = chunk * PROJ_CHUNK
        hi = min(N, lo + PROJ_CHUNK)
        Ms = np.empty((9, PROJ_CHUNK), np.float64)
        ext = np.empty(PROJ_CHUNK, np.float64)
        _quat_scale_soa(quats, scales, lo, hi, Ms)
        for n in range(lo, hi):  # scalar (log): the radius extent, once for all cameras
            op = np.float64(opac[n])
            ext[n - lo] = min(3.33, math.sqrt(2.0 * math.log(op * 255.0))) if op >= ALPHA_THRESHOLD else -1.0
        for c in range(C):
            fx = cams[c, 0]
            fy = cams[c, 1]
            cx = cams[c, 2]
            cy = cams[c, 3]
            rt = _view_rt(viewmats, c)
            for n in range(lo, hi):
                i = n - lo
                (px, py, pz, iz, u, v, uc, vc, fxz, fyz,
                 a0, a1, a2, b0, b1, b2) = _cam_jacobian(means, n, rt, fx, fy, cams[c, 4], cams[c, 5],
                                                         cams[c, 6], cams[c, 7], near, far)
                inz = (pz > near) & (pz < far)
                u2 = fx * u + cx
                v2 = fy * v + cy
                ak0 = a0 * Ms[0, i] + a1 * Ms[3, i] + a2 * Ms[6, i]
                ak1 = a0 * Ms[1, i] + a1 * Ms[4, i] + a2 * Ms[7, i]
                ak2 = a0 * Ms[2, i] + a1 * Ms[5, i] + a2 * Ms[8, i]
                bk0 = b0 * Ms[0, i] + b1 * Ms[3, i] + b2 * Ms[6, i]
                bk1 = b0 * Ms[1, i] + b1 * Ms[4, i] + b2 * Ms[7, i]
                bk2 = b0 * Ms[2, i] + b1 * Ms[5, i] + b2 * Ms[8, i]
                A = eps2d + ak0 * ak0 + ak1 * ak1 + ak2 * ak2
                B = ak0 * bk0 + ak1 * bk1 + ak2 * bk2
                Cc = eps2d + bk0 * bk0 + bk1 * bk1 + bk2 * bk2
                det = max(A * Cc - B * B, 1e-10)
                out_z[c, n] = pz
                out_m2d[c, n, 0] = u2 if inz else 0.0
                out_m2d[c, n, 1] = v2 if inz else 0.0
                out_conic[c, n, 0] = Cc / det if inz else 0.0
                out_conic[c, n, 1] = -B / det if inz else 0.0
                out_conic[c, n, 2] = A / det if inz else 0.0
                e = ext[i]
                rx = math.ceil(e * math.sqrt(A))
                ry = math.ceil(e * math.sqrt(Cc))
                keep = inz & (e > 0.0) & (rx > 0.0) & (ry > 0.0) & (rx < 1e9) & (ry < 1e9)
                keep = keep & (u2 + rx > 0.0) & (u2 - rx < width) & (v2 + ry > 0.0) & (v2 - ry < height)
                out_radii[c, n, 0] = np.int32(rx) if keep else 0
                out_radii[c, n, 1] = np.int32(ry) if keep else 0


@njit(parallel=True, cache=True, error_model="numpy")
def project_bwd(means, quats, scales, viewmats, Ks, width, height, near, far, eps2d,
                v_m2d, v_conic, v_z, v_means, v_quats, v_scales):
    """Gradients of project_fwd's means2d / conics / z w.r.t. means, quats and scales
    (v_means [N,3], v_quats [N,4], v_scales [N,3] are written, not accumulated). The
    per-Gaussian loops write only the chunk's [12, chunk] scratch and a plain copy loop
    moves the result out: each written array costs LLVM a runtime alias check against
    every read one, and too many of those kept the loop scalar."""
    N = means.shape[0]
    C = viewmats.shape[0]
    cams = _cam_table(viewmats, Ks, width, height)
    for chunk in prange((N + PROJ_CHUNK - 1) // PROJ_CHUNK):
        lo = chunk * PROJ_CHUNK
        hi = min(N, lo + PROJ_CHUNK)
        Ms = np.empty((9, PROJ_CHUNK), np.float64)
        acc = np.zeros((12, PROJ_CHUNK), np.float64)  # dL/dM (9), dL/dmeans (3)
        tmp = np.empty((12, PROJ_CHUNK), np.float64)
        _quat_scale_soa(quats, scales, lo, hi, Ms)
        for c in range(C):
            fx = cams[c, 0]
            fy = cams[c, 1]
            ulo = cams[c, 4]
            uhi = cams[c, 5]
            vlo = cams[c, 6]
            vhi = cams[c, 7]
            rt = _view_rt(viewmats, c)
            r00, r01, r02, r10, r11, r12, r20, r21, r22, t0_, t1_, t2_ = rt
            for n in range(lo, hi):
                i = n - lo
                gz = np.float64(v_z[c, n])
                (px, py, pz, iz, u, v, uc, vc, fxz, fyz,
                 T00, T01, T02, T10, T11, T12) = _cam_jacobian(means, n, rt, fx, fy, ulo, uhi, vlo, vhi, near, far)
                inz = (pz > near) & (pz < far)
                m00 = Ms[0, i]
                m01 = Ms[1, i]
                m02 = Ms[2, i]
                m10 = Ms[3, i]
                m11 = Ms[4, i]
                m12 = Ms[5, i]
                m20 = Ms[6, i]
                m21 = Ms[7, i]
                m22 = Ms[8, i]
                a0 = T00 * m00 + T01 * m10 + T02 * m20
                a1 = T00 * m01 + T01 * m11 + T02 * m21
                a2 = T00 * m02 + T01 * m12 + T02 * m22
                b0 = T10 * m00 + T11 * m10 + T12 * m20
                b1 = T10 * m01 + T11 * m11 + T12 * m21
                b2 = T10 * m02 + T11 * m12 + T12 * m22
                A = eps2d + a0 * a0 + a1 * a1 + a2 * a2
                B = a0 * b0 + a1 * b1 + a2 * b2
                Cc = eps2d + b0 * b0 + b1 * b1 + b2 * b2
                det = A * Cc - B * B
                g0 = np.float64(v_conic[c, n, 0])
                g1 = np.float64(v_conic[c, n, 1])
                g2 = np.float64(v_conic[c, n, 2])
                big = det > 1e-10
                idet = 1.0 / (det if big else 1e-10)
                gdet = -(g0 * Cc - g1 * B + g2 * A) * idet * idet if big else 0.0
                gA = g2 * idet + gdet * Cc
                gB = -g1 * idet - 2.0 * gdet * B
                gC = g0 * idet + gdet * A
                ga0 = 2.0 * gA * a0 + gB * b0
                gb0 = 2.0 * gC * b0 + gB * a0
                ga1 = 2.0 * gA * a1 + gB * b1
                gb1 = 2.0 * gC * b1 + gB * a1
                ga2 = 2.0 * gA * a2 + gB * b2
                gb2 = 2.0 * gC * b2 + gB * a2
                gT0x = ga0 * m00 + ga1 * m01 + ga2 * m02
                gT0y = ga0 * m10 + ga1 * m11 + ga2 * m12
                gT0z = ga0 * m20 + ga1 * m21 + ga2 * m22
                gT1x = gb0 * m00 + gb1 * m01 + gb2 * m02
                gT1y = gb0 * m10 + gb1 * m11 + gb2 * m12
                gT1z = gb0 * m20 + gb1 * m21 + gb2 * m22
                tmp[0, i] = (T00 * ga0 + T10 * gb0) if inz else 0.0
                tmp[1, i] = (T00 * ga1 + T10 * gb1) if inz else 0.0
                tmp[2, i] = (T00 * ga2 + T10 * gb2) if inz else 0.0
                tmp[3, i] = (T01 * ga0 + T11 * gb0) if inz else 0.0
                tmp[4, i] = (T01 * ga1 + T11 * gb1) if inz else 0.0
                tmp[5, i] = (T01 * ga2 + T11 * gb2) if inz else 0.0
                tmp[6, i] = (T02 * ga0 + T12 * gb0) if inz else 0.0
                tmp[7, i] = (T02 * ga1 + T12 * gb1) if inz else 0.0
                tmp[8, i] = (T02 * ga2 + T12 * gb2) if inz else 0.0
                s0 = gT0x * r00 + gT0y * r01 + gT0z * r02
                s1 = gT1x * r10 + gT1y * r11 + gT1z * r12
                q0 = gT0x * r20 + gT0y * r21 + gT0z * r22
                q1 = gT1x * r20 + gT1y * r21 + gT1z * r22
                giz = fx * (s0 - uc * q0) + fy * (s1 - vc * q1)
                gu = fx * np.float64(v_m2d[c, n, 0])
                gv = fy * np.float64(v_m2d[c, n, 1])
                gu = gu + (-fxz * q0 if (u > ulo) & (u < uhi) else 0.0)
                gv = gv + (-fyz * q1 if (v > vlo) & (v < vhi) else 0.0)
                gpx = gu * iz
                gpy = gv * iz
                giz += gu * px + gv * py
                gpz = -giz * iz * iz
                tmp[9, i] = r20 * gz + ((r00 * gpx + r10 * gpy + r20 * gpz) if inz else 0.0)
                tmp[10, i] = r21 * gz + ((r01 * gpx + r11 * gpy + r21 * gpz) if inz else 0.0)
                tmp[11, i] = r22 * gz + ((r02 * gpx + r12 * gpy + r22 * gpz) if inz else 0.0)
            for j in range(12):
                for i in range(hi - lo):
                    acc[j, i] += tmp[j, i]
        for n in range(lo, hi):
            i = n - lo
            w, x, y, z, inv = _unit_quat(quats, n)
            tmp[0, i] = acc[9, i]
            tmp[1, i] = acc[10, i]
            tmp[2, i] = acc[11, i]
            R00 = 1.0 - 2.0 * (y * y + z * z)
            R01 = 2.0 * (x * y - w * z)
            R02 = 2.0 * (x * z + w * y)
            R10 = 2.0 * (x * y + w * z)
            R11 = 1.0 - 2.0 * (x * x + z * z)
            R12 = 2.0 * (y * z - w * x)
            R20 = 2.0 * (x * z - w * y)
            R21 = 2.0 * (y * z + w * x)
            R22 = 1.0 - 2.0 * (x * x + y * y)
            s0 = np.float64(scales[n, 0])
            s1 = np.float64(scales[n, 1])
            s2 = np.float64(scales[n, 2])
            tmp[7, i] = acc[0, i] * R00 + acc[3, i] * R10 + acc[6, i] * R20
            tmp[8, i] = acc[1, i] * R01 + acc[4, i] * R11 + acc[7, i] * R21
            tmp[9, i] = acc[2, i] * R02 + acc[5, i] * R12 + acc[8, i] * R22
            G00 = acc[0, i] * s0
            G01 = acc[1, i] * s1
            G02 = acc[2, i] * s2
            G10 = acc[3, i] * s0
            G11 = acc[4, i] * s1
            G12 = acc[5, i] * s2
            G20 = acc[6, i] * s0
            G21 = acc[7, i] * s1
            G22 = acc[8, i] * s2
            gw = 2.0 * (-z * G01 + y * G02 + z * G10 - x * G12 - y * G20 + x * G21)
            gx = 2.0 * (y * G01 + z * G02 + y * G10 - 2.0 * x * G11 - w * G12
                        + z * G20 + w * G21 - 2.0 * x * G22)
            gy = 2.0 * (-2.0 * y * G00 + x * G01 + w * G02 + x * G10 + z * G12
                        - w * G20 + z * G21 - 2.0 * y * G22)
            gzq = 2.0 * (-2.0 * z * G00 - w * G01 + x * G02 + w * G10 - 2.0 * z * G11
                         + y * G12 + x * G20 + y * G21)
            dot = w * gw + x * gx + y * gy + z * gzq
            tmp[3, i] = (gw - w * dot) * inv
            tmp[4, i] = (gx - x * dot) * inv
            tmp[5, i] = (gy - y * dot) * inv
            tmp[6, i] = (gzq - z * dot) * inv
        for n in range(lo, hi):
            i = n - lo
            for j in range(3):
                v_means[n, j] = tmp[j, i]
                v_scales[n, j] = tmp[7 + j, i]
            for j in range(4):
                v_quats[n, j] = tmp[3 + j, i]


# ------------------------------------------------------------------------- SH combination

@njit(parallel=True, cache=True)
def sh_combine_fwd(basis, coeffs, out):
    """out[c,n,d] = sum_k basis[c,n,k] * coeffs[n,k,d] (basis [C,N,K], coeffs [N,K',3])."""
    C, N, K = basis.shape
    for n in prange(N):
        for c in range(C):
            r = np.float64(0.0)
            g = np.float64(0.0)
            b = np.float64(0.0)
            for k in range(K):
                w = np.float64(basis[c, n, k])
                r += w * coeffs[n, k, 0]
                g += w * coeffs[n, k, 1]
                b += w * coeffs[n, k, 2]
            out[c, n, 0] = r
            out[c, n, 1] = g
            out[c, n, 2] = b


@njit(parallel=True, cache=True)
def sh_combine_bwd(basis, coeffs, v_out, v_basis, v_coeffs):
    """Gradients of sh_combine_fwd (v_coeffs [N,K,3] written for k < K, zero elsewhere)."""
    C, N, K = basis.shape
    for n in prange(N):
        for k in range(v_coeffs.shape[1]):
            for d in range(3):
                v_coeffs[n, k, d] = 0.0
        for c in range(C):
            g0 = np.float64(v_out[c, n, 0])
            g1 = np.float64(v_out[c, n, 1])
            g2 = np.float64(v_out[c, n, 2])
            for k in range(K):
                v_basis[c, n, k] = g0 * coeffs[n, k, 0] + g1 * coeffs[n, k, 1] + g2 * coeffs[n, k, 2]
                w = basis[c, n, k]
                v_coeffs[n, k, 0] += w * g0
                v_coeffs[n, k, 1] += w * g1
                v_coeffs[n, k, 2] += w * g2
