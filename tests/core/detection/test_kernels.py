"""The compiled kernels (app.core.detection.kernels) against the numpy/OpenCV code they replaced,
bit for bit, on random inputs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.core.detection import candidates as cand
from app.core.detection import kernels
from app.core.detection import targets as tg
from app.core.geometry import homography as hg

# --------------------------------------------------------------------------------------
# References: the numpy/OpenCV code each kernel replaced
# --------------------------------------------------------------------------------------


def _reference_blob_scores(padded: np.ndarray) -> np.ndarray:
    """Stage 1a through OpenCV calls: integral image, shifted differences, addWeighted."""
    se = np.ones((12, 12), np.uint8)
    h, w = padded.shape
    dil = cv2.dilate(padded, se, anchor=(6, 6))
    ero = cv2.erode(padded, se, anchor=(6, 6))
    tophat = cv2.subtract(cv2.erode(dil, se, anchor=(5, 5)), padded)
    integral = cv2.integral(tophat, sdepth=cv2.CV_32S)
    oh, ow = h - 11, w - 11
    strip = cv2.subtract(integral[12:], integral[:oh])
    sum12 = cv2.subtract(strip[:, 12:], strip[:, :ow])
    rows4 = cv2.subtract(integral[8 : h - 3], integral[4 : h - 7])
    sum4 = cv2.subtract(rows4[:, 8 : w - 3], rows4[:, 4 : w - 7])
    num = cv2.addWeighted(sum4, 1.0 / 16.0, sum12, -1.0 / 144.0, 0.0, dtype=cv2.CV_32F)
    den = cv2.add(cv2.subtract(dil, ero)[6 : h - 5, 6 : w - 5], 2.0, dtype=cv2.CV_32F)
    return cv2.divide(num, den)


def _reference_maxima(score: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    mask = cv2.compare(score, cv2.max(cv2.dilate(score, None), float(threshold) + 1e-6), cv2.CMP_GE)
    return np.nonzero(mask)


def _reference_screen_raw(raw: np.ndarray, classifier: cand.DiscClassifier) -> np.ndarray:
    w = raw.reshape(-1, 144).astype(np.float32)
    product = w @ classifier._w1_ext
    hidden = product[:, :-1]
    mean = product[:, -1] / np.float32(144)
    sq = np.einsum("ij,ij->i", w, w) - np.float32(144) * mean * mean
    inv = 1.0 / np.maximum(np.sqrt(np.maximum(sq, 0.0)), np.float32(1e-3))
    hidden -= mean[:, None] * classifier._w1_sum[None, :]
    hidden *= inv[:, None]
    hidden += classifier.screen_b1
    np.maximum(hidden, 0.0, out=hidden)
    return hidden @ classifier.screen_w2 + np.float32(classifier.screen_b2)


def _reference_clash_pairs(rows: np.ndarray, claims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = rows.shape[0]
    x = rows[:, 0]
    order = np.argsort(x, kind="stable")
    xs = x[order]
    r = rows[order, 2]
    lo = np.searchsorted(xs, xs - r, side="left")
    hi = np.searchsorted(xs, xs + r, side="right")
    cnt = hi - lo
    total = int(cnt.sum())
    a = order[np.repeat(np.arange(n), cnt)]
    b = order[np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(lo, cnt)]
    ahead = a < b
    a, b = a[ahead], b[ahead]
    d = rows[a, :2] - rows[b, :2]
    reach = np.where(claims[a], rows[a, 2], np.minimum(rows[a, 2], rows[b, 2]))
    close = np.einsum("ij,ij->i", d, d) < reach * reach
    return a[close], b[close]


def _reference_greedy(n: int, first: np.ndarray, second: np.ndarray, active: np.ndarray | None) -> np.ndarray:
    keep = np.ones(n, bool) if active is None else active.copy()
    if first.size == 0:
        return keep
    if active is not None:
        both = active[first] & active[second]
        first, second = first[both], second[both]
    for _ in range(n):
        hits = np.bincount(second, weights=keep[first], minlength=n)
        new = (hits == 0) if active is None else (hits == 0) & active
        if np.array_equal(new, keep):
            break
        keep = new
    return keep


def _reference_centroid_step(img: np.ndarray, centroid: np.ndarray, jac: np.ndarray, reach: float,
                             white: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    t = centroid.shape[0]
    f32 = np.float32
    j00, j01, j10, j11 = jac[..., 0, 0], jac[..., 0, 1], jac[..., 1, 0], jac[..., 1, 1]
    det = j00 * j11 - j01 * j10
    s = 1.0 / (det * tg.DISC_RADIUS)
    a = (np.array([j11, -j01, -j10, j00]) * s).astype(f32)[..., None, None]
    ext = reach * tg.DISC_RADIUS * np.sqrt((jac * jac).sum(axis=-1).max(axis=-1))
    k = int(np.ceil(ext.max())) + 1
    size = 2 * k + 1
    base = np.rint(centroid).astype(np.intp)
    pix8, valid = tg._windows_u8(img, base[..., 0].ravel() - k, base[..., 1].ravel() - k, size)
    pix8 = pix8.reshape(t, 4, size, size)
    if valid is not None:
        valid = valid.reshape(t, 4, size, size)
    offs = np.arange(-k, k + 1).astype(f32)
    off = (base - centroid).astype(f32)
    dx = off[..., 0, None, None] + offs[None, None, None, :]
    dy = off[..., 1, None, None] + offs[None, None, :, None]
    u = a[0] * dx + a[1] * dy
    v = a[2] * dx + a[3] * dy
    rho2 = u * u + v * v
    if white is None:
        ring = (rho2 >= f32(tg.REFINE_RING[0] ** 2)) & (rho2 <= f32(tg.REFINE_RING[1] ** 2))
        if valid is not None:
            ring &= valid
        white = tg._masked_median_u8(pix8.reshape(t * 4, -1), ring.reshape(t * 4, -1)).reshape(t, 4)
    pix = pix8.astype(f32)
    inner = rho2 <= f32(0.25)
    if valid is not None:
        inner &= valid
    black = (pix * inner).sum(axis=(2, 3)) / np.maximum(inner.sum(axis=(2, 3)), 1)
    taper = np.sqrt(rho2)
    np.subtract(f32(reach), taper, out=taper)
    taper *= f32(1.0 / tg.REFINE_TAPER)
    np.minimum(taper, f32(1.0), out=taper)
    np.maximum(taper, f32(0.0), out=taper)
    if valid is not None:
        taper *= valid
    weight = np.subtract(np.where(np.isfinite(white), white, 0.0).astype(f32)[..., None, None], pix, out=pix)
    np.maximum(weight, f32(0.0), out=weight)
    weight *= taper
    total = weight.sum(axis=(2, 3)).astype(np.float64)
    good = (total > 1e-6) & np.isfinite(white)
    safe = np.where(good, total, 1.0)
    mx = (weight.sum(axis=2) * dx[..., 0, :]).sum(axis=-1) / safe
    my = (weight.sum(axis=3) * dy[..., :, 0]).sum(axis=-1) / safe
    new = centroid.copy()
    new[..., 0] += np.where(good, mx, 0.0)
    new[..., 1] += np.where(good, my, 0.0)
    return new, np.where(good, total, 0.0), white - black, white


# The grouping as it was before its kernels (edge_sweep, edge_ranks_keep, group_graph):
# `_reference_group` is `targets._group`, vectorised.


def _reference_quad_geometry_ok(x: np.ndarray, y: np.ndarray, r: np.ndarray) -> np.ndarray:
    if x.shape[1] == 0:
        return np.zeros(0, bool)
    xn, yn = x[tg._NEXT], y[tg._NEXT]
    t = x * yn - xn * y
    area = 0.5 * (t[0] + t[1] + t[2] + t[3])
    rm = 0.25 * (r[0] + r[1] + r[2] + r[3])
    # sqrt(area) / radius is the same for every affine view of a card
    lo, hi = tg.SQRT_AREA_OVER_RADIUS[0] ** 2, tg.SQRT_AREA_OVER_RADIUS[1] ** 2
    ok = (area >= lo * rm * rm) & (area <= hi * rm * rm)
    ok &= r.max(axis=0) <= tg.RADIUS_RATIO_MAX * r.min(axis=0)
    ex, ey = xn - x, yn - y  # e[k] = p[k+1] - p[k]
    s2 = ex * ex + ey * ey
    ok &= s2.min(axis=0) >= tg.SIDE_RATIO_MIN**2 * s2.max(axis=0)
    exn, eyn, s2n = ex[tg._NEXT], ey[tg._NEXT], s2[tg._NEXT]
    cross = ex * eyn - ey * exn
    dot = ex * exn + ey * eyn
    # convex and turning like the layout; interior angle at every vertex in range
    ok &= ((cross > 0) & (dot * dot < tg._COS2_ANGLE * s2 * s2n)).all(axis=0)
    return ok


def _reference_edges(pts: np.ndarray, rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = pts.shape[0]
    order = np.argsort(pts[:, 0], kind="stable")
    # (ndarray.take: cheaper than fancy indexing, the more so on rows of 2-d arrays)
    xs, ys, rs = pts[:, 0].take(order), pts[:, 1].take(order), rad.take(order)
    reach = (1.5 * tg.EDGE_OVER_RADIUS[1]) * rs
    start = np.arange(1, n + 1)
    cnt = np.maximum(np.searchsorted(xs, xs + reach, side="right") - start, 0)
    total = int(cnt.sum())
    if total == 0:
        z = np.zeros(0, np.intp)
        return z, z
    # pairs (a, b) of positions in x order: b runs over start[a] .. start[a] + cnt[a] - 1
    a = np.repeat(np.arange(n), cnt)
    b = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt - start, cnt)
    ra, rb = np.repeat(rs, cnt), rs.take(b)  # (np.repeat: cheaper than gathering by a)
    dx, dy = xs.take(b) - np.repeat(xs, cnt), ys.take(b) - np.repeat(ys, cnt)
    d2 = dx * dx + dy * dy
    rs2 = ra + rb
    rs2 *= 0.5
    rs2 *= rs2
    ok = (rb <= tg.RADIUS_RATIO_MAX * ra) & (ra <= tg.RADIUS_RATIO_MAX * rb)
    ok &= (d2 >= tg.EDGE_OVER_RADIUS[0] ** 2 * rs2) & (d2 <= tg.EDGE_OVER_RADIUS[1] ** 2 * rs2)
    sel = np.flatnonzero(ok)
    a, b = order[a[sel]], order[b[sel]]
    if a.size == 0:
        return a, b
    deg = np.bincount(a, minlength=n) + np.bincount(b, minlength=n)
    crowded = deg > tg.EDGE_KEEP
    if crowded.any():
        # An edge goes when both its ends are crowded and neither ranks it among its
        # `EDGE_KEEP` most side-like (4.8 radii apart, equal radii).
        ca, cb = crowded[a], crowded[b]
        if (ca & cb).any():
            inc = np.flatnonzero(ca | cb)  # every edge of a crowded end
            s_inc = sel[inc]
            bad = (np.abs(np.log(d2[s_inc] / (23.04 * rs2[s_inc]))) * 0.5
                   + 0.5 * np.abs(np.log(rb[s_inc] / ra[s_inc])))
            m = inc.size
            ends = np.concatenate([a[inc], b[inc]])
            key = np.lexsort((np.concatenate([bad, bad]), ends))
            se = ends[key]
            rank = np.empty(2 * m, np.intp)
            rank[key] = np.arange(2 * m) - np.searchsorted(se, se, side="left")
            drop = np.zeros(a.size, bool)
            drop[inc] = (rank[:m] >= tg.EDGE_KEEP) & (rank[m:] >= tg.EDGE_KEEP) & ca[inc] & cb[inc]
            keep = ~drop
            a, b = a[keep], b[keep]
    return np.minimum(a, b), np.maximum(a, b)


def _reference_card_corners(pts: np.ndarray, rad: np.ndarray, i: np.ndarray, j: np.ndarray, l_: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    px, py = pts[:, 0], pts[:, 1]
    xi, yi = px[i], py[i]
    ax, ay = px[j] - xi, py[j] - yi
    bx, by = px[l_] - xi, py[l_] - yi
    cross = ax * by - ay * bx
    flip = cross < 0
    j, l_ = np.where(flip, l_, j), np.where(flip, j, l_)
    cross = np.abs(cross)
    dot = ax * bx + ay * by
    l1, l2 = ax * ax + ay * ay, bx * bx + by * by
    r2 = rad[i] ** 2
    short2 = np.minimum(l1, l2)
    ok = (dot * dot < tg._COS2_ANGLE * l1 * l2) & (short2 >= tg.SIDE_RATIO_MIN**2 * np.maximum(l1, l2))
    ok &= (cross >= tg.APEX_AREA_OVER_RADIUS[0] ** 2 * r2) & (cross <= tg.APEX_AREA_OVER_RADIUS[1] ** 2 * r2)
    return j, l_, short2, ok


def _reference_group(candidates: np.ndarray, img: np.ndarray | None = None, scale: float = 1.0
                     ) -> tuple[np.ndarray, tg._Graph | None]:
    empty = np.zeros((0, 4), np.intp)
    idx = tg._clean(candidates)
    n = idx.size
    if n < 3:
        return empty, None
    c = np.asarray(candidates, np.float64).take(idx, axis=0)
    pts, rad = c[:, :2].copy(), c[:, 2].copy()  # contiguous: for ndarray.take
    ea, eb = _reference_edges(pts, rad)
    dark = white = None
    if img is not None and ea.size:
        keep, dark, white = tg._side_test(pts, ea, eb, img, scale)
        ea, eb, white = ea[keep], eb[keep], white[keep]
    # adjacency in CSR form, both directions, each row sorted by neighbour index
    src = np.concatenate([ea, eb])
    dst = np.concatenate([eb, ea])
    key = np.argsort(src * n + dst)
    src, dst = src[key], dst[key]
    deg = np.bincount(src, minlength=n)
    row_end = np.cumsum(deg)
    # every apex pair: entries (first, second) of one row, first before second
    pos = np.arange(src.size)
    more = row_end[src] - pos - 1  # entries after this one in the same row
    tot = int(more.sum())
    if tot == 0:
        return empty, tg._Graph(idx=idx, pts=pts, rad=rad, src=src, dst=dst, dark=dark)
    first = np.repeat(pos, more)
    second = np.arange(tot) - np.repeat(np.cumsum(more) - more - pos - 1, more)
    i = src[first]
    j0 = dst[first]
    j, l_, short2, ok = _reference_card_corners(pts, rad, i, j0, dst[second])
    corners = corner_white = None
    if dark is not None:
        # completion's corners (any apex): similar radii at j and l too
        rj, rl = rad[j], rad[l_]
        sel = np.flatnonzero(ok & (rj <= tg.RADIUS_RATIO_MAX * rl) & (rl <= tg.RADIUS_RATIO_MAX * rj))
        corners = np.array([i[sel], j[sel], l_[sel]])
        white = np.concatenate([white, white])[key]
        corner_white = np.minimum(white[first[sel]], white[second[sel]])
    graph = tg._Graph(idx=idx, pts=pts, rad=rad, src=src, dst=dst, dark=dark, corners=corners,
                      corner_white=corner_white)
    if n < 4 or ea.size < 2:
        return empty, graph
    # the grouping's apex is the lowest index of its card: i < j, l
    sel = np.flatnonzero(ok & (j0 > i))
    if sel.size == 0:
        return empty, graph
    i, j, l_, short2 = i[sel], j[sel], l_[sel], short2[sel]
    px, py = pts[:, 0], pts[:, 1]
    predx, predy = px[j] + px[l_] - px[i], py[j] + py[l_] - py[i]
    # the fourth disc neighbours j: every neighbour of j near the prediction
    dj = deg[j]
    tot = int(dj.sum())
    t = np.repeat(np.arange(i.size), dj)
    k = dst[np.arange(tot) - np.repeat(np.cumsum(dj) - dj - (row_end[j] - dj), dj)]
    ex, ey = px[k] - predx[t], py[k] - predy[t]
    good = (ex * ex + ey * ey <= tg.FOURTH_TOLERANCE**2 * short2[t]) & (k > i[t]) & (k != l_[t])
    t, k = t[good], k[good]
    if t.size == 0:
        return empty, graph
    quads = np.array([i[t], j[t], k, l_[t]])  # (4, P)
    quads = quads[:, _reference_quad_geometry_ok(px.take(quads), py.take(quads), rad.take(quads))]
    return idx.take(quads.T), graph


# `targets._measures_from` as it was before `kernels.measure_stats` (one sort of the
# groups, each lifted by its own multiple of 1024: whole grey levels sort apart)


def _reference_measures_from(vals: np.ndarray, inside: np.ndarray, plan: tg._SamplePlan, cells: bool = True
                             ) -> tg._Measures:
    lift = np.repeat(1024.0 * np.arange(5), np.diff(plan.sorted_bounds)).astype(np.float32)
    p = vals.shape[0]
    s = vals.take(plan.sorted_index, axis=1)  # (ndarray.take: several times cheaper than fancy indexing)
    s += lift
    inside_edge = inside.take(plan.edge, axis=1)
    s[:, plan.sorted_bounds[4]:][~inside_edge] = np.inf  # outside the image: no evidence
    s.sort(axis=1)
    s -= lift
    # every order statistic at once (`_SamplePlan.stats_lo`), as `_quantile_sorted` would
    lo = s.take(plan.stats_lo, axis=1)
    q = lo + plan.stats_frac * (s.take(plan.stats_hi, axis=1) - lo)
    black, white = q[:, 0], q[:, 1]
    contrast = white - black
    c = np.maximum(contrast, 1e-3)
    uniformity = (q[:, 2] - q[:, 3]) / c
    white_low, gap_low, disc_max = ((q[:, 4:] - black[:, None]) / c[:, None]).T
    disc_means = (tg._mean(vals.take(plan.disc, axis=1), 2) - black[:, None]) / c[:, None]
    n_in = np.count_nonzero(inside_edge, axis=1)
    edge_med = s[np.arange(p), plan.sorted_bounds[4] + n_in // 2]
    edge_level = np.where(n_in >= 4, (edge_med - black) / c, 1.0)
    # Discs and code must be wholly in the image; the white margin mostly.
    valid = np.where(inside.take(plan.core, axis=1).all(axis=1), np.count_nonzero(inside, axis=1) / inside.shape[1],
                     0.0)
    dmax, dmin = disc_means.max(axis=1), disc_means.min(axis=1)
    cell_means = None
    if cells:
        # (P, n*n, S); fancy indexing, not take: its (n*n, S, P) memory layout carries into
        # the template fit, whose float32 sums depend on it
        cell_vals = (vals[:, plan.cells] - black[:, None, None]) / c[:, None, None]
        cell_means = tg._mean(cell_vals, 2)
    return tg._Measures(
        black=black, white=white, contrast=contrast, uniformity=uniformity,
        disc_level=dmax, disc_spread=dmax - dmin, disc_max=disc_max, white_low=white_low, gap_low=gap_low,
        edge_level=edge_level, valid=valid, cells=cell_means,
    )


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A random image with dark blobs of every size (plenty of maxima and ties)."""
    img = cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.uint8), (0, 0), float(rng.uniform(0.3, 3)))
    for _ in range(int(rng.integers(0, 12))):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.circle(img, c, int(rng.integers(1, 20)), int(rng.integers(0, 60)), -1)
    if rng.random() < 0.3:
        img[: h // 3] = 128  # flat: equal scores, plateaus of maxima
    return img


# --------------------------------------------------------------------------------------
# Stage 1
# --------------------------------------------------------------------------------------


def _reference_window_geometry(windows: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """`candidates.window_radius` then `window_centroid` as numpy chains on (N, 144) rows."""
    w = np.asarray(windows, dtype=np.float32).reshape(-1, 144)
    n = w.shape[0]
    prof = w @ cand._RINGS
    dark = prof[:, :2].min(axis=1)
    half = 0.5 * (dark + prof[:, 2:].max(axis=1))
    below = prof < half[:, None]
    first = np.where(below.all(axis=1), prof.shape[1], np.argmin(below, axis=1))
    k = np.minimum(np.maximum(first, 1), prof.shape[1] - 1)
    flat = prof.reshape(-1)
    p1_index = np.arange(0, n * prof.shape[1], prof.shape[1]) + k
    p0, p1 = flat[p1_index - 1], flat[p1_index]
    step = np.where(np.abs(p1 - p0) > 1e-6, p1 - p0, np.float32(1e-6))
    radius = cand._RING_MID[k - 1] + np.minimum(np.maximum((half - p0) / step, 0.0), 1.0)
    radius = (np.where(first == 0, 0.5, radius) * cand._RADIUS_GAIN).astype(np.float32)
    dark = half[:, None] - w
    np.maximum(dark, 0.0, out=dark)
    reach2 = ((radius + 1.0) ** 2)[:, None]
    offset = np.zeros((n, 2), np.float32)
    for it in range(iterations):
        if it == 0:
            d2 = cand._DIST2[None, :]
        else:
            d2 = (cand._DX[None, :] - offset[:, :1]) ** 2 + (cand._DY[None, :] - offset[:, 1:]) ** 2
        weight = dark * (d2 <= reach2)
        total = weight.sum(axis=1)
        ok = total > 1e-6
        new = (weight @ cand._DXY) / np.where(ok, total, 1.0)[:, None]
        offset = np.where(ok[:, None], np.minimum(np.maximum(new, -2.0), 2.0), offset).astype(np.float32)
    return offset, radius


def test_blob_kernels_match_opencv_bit_for_bit() -> None:
    rng = np.random.default_rng(11)
    ws = cand._Workspace()
    for _ in range(15):
        h, w = (int(s) for s in rng.integers(24, 300, 2))
        for level in cand.pyramid(_texture(rng, h, w)):
            padded = cand.pad_level(level)
            expected = _reference_blob_scores(padded)
            np.testing.assert_array_equal(cand.blob_scores(padded, ws), expected)
            for threshold in (0.25, 0.16, -2.0):
                ys, xs = _reference_maxima(expected, threshold)
                got = cand.local_maxima(expected, threshold, ws)
                np.testing.assert_array_equal(got[0], ys)
                np.testing.assert_array_equal(got[1], xs)
                gy, gx, blob = cand._blob_maxima(padded, threshold, ws)
                np.testing.assert_array_equal(blob, expected[ys, xs])
                np.testing.assert_array_equal(gy, ys)
                np.testing.assert_array_equal(gx, xs)


def test_gathered_screen_matches_the_numpy_screen() -> None:
    rng = np.random.default_rng(12)
    classifier = cand.load_default_classifier()
    for n in (1, 7, 300):
        padded = cand.pad_level(_texture(rng, 120, 160))
        ys = rng.integers(0, padded.shape[0] - 11, n)
        xs = rng.integers(0, padded.shape[1] - 11, n)
        raw = np.empty((n, 12, 12), np.uint8)
        flat = np.empty((n, 144), np.float32)
        sums, sums_sq = np.empty(n, np.int64), np.empty(n, np.int64)
        kernels.gather_windows(padded, ys, xs, raw, flat, sums, sums_sq)
        expected_raw = cand.extract_windows(padded, ys, xs)
        np.testing.assert_array_equal(raw, expected_raw)
        np.testing.assert_array_equal(flat, expected_raw.reshape(n, 144).astype(np.float32))
        np.testing.assert_array_equal(sums, expected_raw.reshape(n, -1).sum(axis=1))
        np.testing.assert_array_equal(sums_sq, (expected_raw.reshape(n, -1).astype(np.int64) ** 2).sum(axis=1))
        np.testing.assert_array_equal(cand._screen_gathered(flat, sums, sums_sq, classifier),
                                      _reference_screen_raw(raw, classifier))


def test_stage1_windows_unchanged_without_the_screen() -> None:
    rng = np.random.default_rng(13)
    classifier = cand.load_default_classifier()
    image = _texture(rng, 240, 320)
    s1 = cand.stage1_windows(image, classifier, apply_screen=False)
    np.testing.assert_array_equal(s1.screen, _reference_screen_raw(s1.windows, classifier))
    for lv, padded, pad, ys, xs, blob in cand.scan_levels(image, classifier.blob_thresholds):
        at = s1.level == lv
        np.testing.assert_array_equal(s1.windows[at], cand.extract_windows(padded, ys, xs))
        np.testing.assert_array_equal(s1.blob[at], blob)


@pytest.mark.parametrize("n", [0, 1, 2, 50, 400])
def test_suppression_kernels_match_numpy(n: int) -> None:
    rng = np.random.default_rng(n)
    for _ in range(10):
        rows = np.zeros((n, 4), np.float32)
        rows[:, :2] = rng.uniform(0, 100, (n, 2))
        if n > 4:  # ties along x, and coincident centres
            rows[: n // 4, 0] = np.round(rows[: n // 4, 0])
            rows[n // 2 : n // 2 + 2, :2] = rows[0, :2]
        rows[:, 2] = rng.uniform(0.5, 12, n)
        claims = rng.random(n) < 0.5
        first, second = cand._clash_pairs(rows, claims)
        if n >= 2:
            ef, es = _reference_clash_pairs(rows, claims)
            np.testing.assert_array_equal(first, ef)
            np.testing.assert_array_equal(second, es)
            assert first.dtype == np.intp and second.dtype == np.intp
        else:
            assert first.size == 0 and second.size == 0
        np.testing.assert_array_equal(cand._greedy(n, first, second), _reference_greedy(n, first, second, None))
        active = rng.random(n) < 0.6
        np.testing.assert_array_equal(cand._greedy(n, first, second, active),
                                      _reference_greedy(n, first, second, active))


# --------------------------------------------------------------------------------------
# Targets
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 5, 8, 9, 127, 128, 129, 256, 257, 1000, 1225, 5000])
def test_pairwise_sum_is_numpys_sum(n: int) -> None:
    rng = np.random.default_rng(n)
    a = (rng.standard_normal(n + 5) * 10 ** rng.uniform(-3, 3, n + 5)).astype(np.float32)
    assert np.float32(0.0) + kernels.pairwise_sum(a, 3, n) == a[3 : 3 + n].sum()


def test_centroid_step_matches_numpy() -> None:
    rng = np.random.default_rng(14)
    img = _texture(rng, 160, 200)
    for trial in range(40):
        t = int(rng.integers(1, 6))
        centroid = np.stack([rng.uniform(-3, 203, (t, 4)), rng.uniform(-3, 163, (t, 4))], axis=-1)
        if trial % 2:  # well inside: the windows are views, no mask
            centroid = np.stack([rng.uniform(30, 170, (t, 4)), rng.uniform(30, 130, (t, 4))], axis=-1)
        scale = rng.uniform(5, 60)
        jac = scale * (np.eye(2) + rng.uniform(-0.4, 0.4, (t, 4, 2, 2)))
        white = None
        if trial % 3 == 0:
            white = rng.uniform(100, 255, (t, 4)).round() / 2
            white[0, 0] = np.nan
        got = tg._centroid_step(img, centroid, jac, tg.REFINE_WINDOW + tg.REFINE_TAPER, white)
        expected = _reference_centroid_step(img, centroid, jac, tg.REFINE_WINDOW + tg.REFINE_TAPER, white)
        for g, e in zip(got, expected, strict=True):
            np.testing.assert_array_equal(g, e)


def _random_candidates(rng: np.random.Generator, trial: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Candidates (N, 4) in full-resolution pixels over a level-1 image (h, w): random
    points, and by turns a tight cluster (crowded edges), a grid (ties in x), card-like
    parallelograms of discs (rendered dark on white: they pass the side test), rows
    that `_clean` drops, float32."""
    img = cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.uint8), (0, 0), float(rng.uniform(0.5, 3)))
    n = int(rng.integers(0, 80))
    c = np.stack([rng.uniform(0, 2 * w, n), rng.uniform(0, 2 * h, n), rng.uniform(1, 8, n), rng.uniform(0, 1, n)], 1)
    if trial % 3 == 0 and n:
        k = min(n, 40)
        c[:k, :2] = rng.uniform(50, 90, (k, 2))
        c[:k, 2] = rng.uniform(2, 4, k)
    if trial % 4 == 1 and n > 3:
        c[:, 0] = 20 + 12 * (np.arange(n) % 7) + (trial % 8 == 1) * rng.uniform(-0.3, 0.3, n)
        c[:, 1] = 20 + 12 * (np.arange(n) // 7)
        c[:, 2] = 2.5
    if trial % 2 == 0:
        img = np.full((h, w), 200, np.uint8)
        rows = []
        for _ in range(int(rng.integers(1, 6))):
            origin, side = rng.uniform(20, 2 * w - 60, 2), rng.uniform(15, 60)
            axes = side * (np.eye(2) + rng.uniform(-0.3, 0.3, (2, 2)))
            for corner in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = origin + axes @ np.array(corner, float) + rng.uniform(-1, 1, 2)
                r = side * 0.125 / 0.6 * rng.uniform(0.7, 1.4)
                rows.append([p[0], p[1], r, rng.uniform()])
                cv2.circle(img, (int(p[0] / 2), int(p[1] / 2)), max(int(r / 2), 1), 30, -1)
        c = np.concatenate([c, np.array(rows)])[rng.permutation(n + len(rows))]
    if trial % 5 == 2 and n > 3:
        c[0, 0], c[1], c[3, 2] = np.nan, c[2], -1.0
    return (c.astype(np.float32) if trial % 7 == 3 else c), img


def test_grouping_kernels_match_numpy() -> None:
    """`targets._group` (edge_sweep, edge_ranks_keep, group_graph) against the
    vectorised grouping: the proposals and every field of the graph, bit for bit."""
    rng = np.random.default_rng(16)
    n_quads = n_corners = 0
    for trial in range(600):
        cands, img = _random_candidates(rng, trial, 120, 160)
        for level in (img, None):
            got, got_graph = tg._group(cands, level, 0.5)
            expected, expected_graph = _reference_group(cands, level, 0.5)
            np.testing.assert_array_equal(got, expected)
            assert got.dtype == expected.dtype and got.shape == expected.shape
            n_quads += expected.shape[0]
            if expected_graph is None:
                assert got_graph is None
                continue
            for name in ("idx", "pts", "rad", "src", "dst", "dark", "corners", "corner_white"):
                g, e = getattr(got_graph, name), getattr(expected_graph, name)
                assert (g is None) == (e is None), name
                if e is not None:
                    assert g.dtype == e.dtype and g.shape == e.shape, name
                    np.testing.assert_array_equal(g, e)
            n_corners += 0 if expected_graph.corners is None else expected_graph.corners.shape[1]
    assert n_quads > 500 and n_corners > 5000  # the search was exercised


def test_affine_points_match_numpy() -> None:
    rng = np.random.default_rng(17)
    for coef in (tg._corner_look_points(), tg._plan_affine(3), tg._plan_affine(4)):
        for s in (0, 1, 7, 40):
            pi, pj, pl = (rng.uniform(-50, 700, (s, 2)) for _ in range(3))
            xy = pi[:, None, :] + coef[None, :, :1] * (pj - pi)[:, None, :] + coef[None, :, 1:] * (pl - pi)[:, None, :]
            inside = ((xy >= -0.5) & (xy <= np.array([640 - 0.5, 480 - 0.5]))).all(axis=-1)
            got_xy, got_inside = kernels.affine_points(pi, pj, pl, coef, 640, 480)
            np.testing.assert_array_equal(got_xy, xy.astype(np.float32))
            np.testing.assert_array_equal(got_inside, inside)
            assert got_xy.dtype == np.float32 and got_xy.shape == xy.shape


def test_measure_stats_match_numpy() -> None:
    """`targets._measures_from` (`kernels.measure_stats`) against the vectorised
    measurements: every field, bit for bit, with samples outside the image (edge
    groups partly or wholly outside, core samples outside) and ties."""
    rng = np.random.default_rng(18)
    for n in (3, 4):
        plan = tg._plan(n)
        m = plan.points.shape[0]
        for trial in range(200):
            p = int(rng.integers(0, 6))
            levels = rng.integers(0, 256, 2)
            vals = rng.integers(min(levels), max(levels) + 1, (p, m)).astype(np.float32)
            inside = rng.random((p, m)) > rng.choice([0.0, 0.05, 0.5, 1.0])
            got = tg._measures_from(vals, inside, plan, cells=trial % 2 == 0)
            expected = _reference_measures_from(vals, inside, plan, cells=trial % 2 == 0)
            for name in expected.__dataclass_fields__:
                g, e = getattr(got, name), getattr(expected, name)
                if e is None:
                    assert g is None
                    continue
                assert g.dtype == e.dtype and g.shape == e.shape, name
                np.testing.assert_array_equal(g, e, err_msg=name)


@pytest.mark.parametrize("iterations", [1, 2, 3])
def test_window_geometry_kernels_match_numpy(iterations: int) -> None:
    """`ring_radius`, `centroid_weights`, `centroid_offset` (through `window_geometry`)
    against the numpy chains, on noise, noisy discs and flat windows."""
    rng = np.random.default_rng(iterations)
    for trial in range(60):
        n = int(rng.integers(0, 50))
        if trial % 3 == 0:
            w = rng.integers(0, 256, (n, 12, 12)).astype(np.uint8)
        elif trial % 3 == 1:
            yy, xx = np.mgrid[:12, :12] - 5.5 - rng.normal(0, 1, (2, 1, 1))
            r = rng.uniform(0.5, 6.0, (n, 1, 1))
            disc = np.where(np.hypot(yy, xx)[None] < r, 30.0, 200.0) + rng.normal(0, 8, (n, 12, 12))
            w = np.clip(disc, 0, 255).astype(np.uint8)
        else:
            w = np.full((n, 12, 12), rng.integers(0, 256), np.uint8)
        got = cand.window_geometry(w, iterations)
        expected = _reference_window_geometry(w, iterations) if n else got
        for g, e in zip(got, expected):
            assert g.dtype == e.dtype and g.shape == e.shape
            np.testing.assert_array_equal(g, e)


def _reference_jacobians(hs: np.ndarray, pts: np.ndarray) -> np.ndarray:
    x = hs[:, None, :, 0] * pts[None, :, 0, None] + hs[:, None, :, 1] * pts[None, :, 1, None] + hs[:, None, :, 2]
    w = x[..., 2, None, None]  # (P, K, 1, 1)
    return (hs[:, None, :2, :2] - x[..., :2, None] / w * hs[:, None, None, 2, :2]) / w


def _reference_ellipse_centres(hs: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    gh = hs[:, None, 2, :2]  # (P, 1, 2)
    w = gh[..., 0] * centres[None, :, 0] + gh[..., 1] * centres[None, :, 1] + hs[:, 2, 2, None]  # (P, K)
    w = np.where(np.abs(w) > 1e-12, w, 1e-12)
    k = (radius * radius) / w
    p = centres[None] - k[..., None] * gh  # (P, K, 2) the poles on the card
    x = hs[:, None, :, 0] * p[..., 0, None] + hs[:, None, :, 1] * p[..., 1, None] + hs[:, None, :, 2]  # (P, K, 3)
    z = x[..., 2:]
    z = np.where(np.abs(z) > 1e-12, z, 1e-12)
    return x[..., :2] / z


def test_homography_point_kernels_match_numpy() -> None:
    """`jacobians` and `ellipse_centres` (through `homography.jacobians`,
    `homography.ellipse_centres`) against the numpy broadcasts, on the homographies of
    random quadrilaterals, degenerate ones and non-finite entries included."""
    from app.core.markers import DISC_CENTRES, DISC_RADIUS

    rng = np.random.default_rng(7)
    for trial in range(40):
        p = int(rng.integers(0, 12))
        quads = rng.uniform(0, 640, (p, 4, 2))
        if trial % 4 == 1 and p:
            quads[0] = quads[0, :1]  # all four corners at one point
        hs = hg.homographies(quads)
        if trial % 4 == 2 and p:
            hs[0, 2, :2] = 0.0
            hs[0, 2, 2] = 0.0
        if trial % 4 == 3 and p:
            hs[-1, 1, 1] = np.nan
        pts = rng.uniform(-1, 2, (int(rng.integers(1, 6)), 2))
        with np.errstate(all="ignore"):
            for card in (pts, DISC_CENTRES):
                got, expected = hg.jacobians(hs, card), _reference_jacobians(hs, card)
                assert got.shape == expected.shape
                np.testing.assert_array_equal(got, expected)
                got = hg.ellipse_centres(hs, card, DISC_RADIUS)
                expected = _reference_ellipse_centres(hs, card, DISC_RADIUS)
                assert got.shape == expected.shape
                np.testing.assert_array_equal(got, expected)


def test_warm_up_compiles_what_the_detector_calls() -> None:
    """After `warm_up` a detection compiles nothing more (its argument types, read-only
    and non-contiguous arrays included, were all seen)."""
    from app.core.detection.detector import Detector

    kernels.warm_up()
    dispatchers = {name: getattr(kernels, name) for name in dir(kernels)
                   if hasattr(getattr(kernels, name), "signatures") and not name.startswith("_")}
    dispatchers.pop("pairwise_sum")  # called from the kernels only (compiled into them)
    before = {name: set(d.signatures) for name, d in dispatchers.items()}
    rng = np.random.default_rng(15)
    Detector(cand.load_default_classifier()).detect(_texture(rng, 240, 320))
    assert {name: set(d.signatures) for name, d in dispatchers.items()} == before
