"""Grouping (app.core.detection.grouping): the true disc quadrilateral among clutter, in the
layout's orientation; and its compiled kernels against the vectorised grouping, bit for
bit."""

from __future__ import annotations

import cv2
import numpy as np

from app.core.detection import grouping as gr
from app.sim.candidates import simulate_candidates


def test_grouping_finds_the_true_quadrilateral_among_clutter(default_frames: list) -> None:
    rng = np.random.default_rng(0)
    n_cards = 0
    for image, truth in default_frames:
        cand = simulate_candidates(image, truth.targets, rng, n_random=60, n_texture=40)
        quads = gr.group_candidates(cand)
        assert quads.ndim == 2 and quads.shape[1] == 4
        for t in truth.targets:
            if not t.visible:
                continue
            n_cards += 1
            # some proposal has a candidate on each disc, in the layout's cyclic order
            d = np.hypot(*(cand[quads, None, :2] - t.discs_px[None, None]).transpose(3, 0, 1, 2))  # (P, 4, 4)
            on = d <= 1.5  # jitter is 1 px
            hit = any(
                all(on[p, k, (k + s) % 4] for k in range(4)) for p in range(len(quads)) for s in range(4)
            )
            assert hit, f"card {t.id} not proposed"
        # proposals stay few: clutter must not explode the 4-cycles
        assert quads.shape[0] <= 20 * len(cand)
    assert n_cards >= 6


def test_grouping_orientation_is_the_layouts(clean_frames: list) -> None:
    rng = np.random.default_rng(1)
    image, truth = clean_frames[0]
    cand = simulate_candidates(image, truth.targets, rng, n_random=0, n_texture=0, jitter_px=0.0)
    for q in gr.group_candidates(cand):
        p = cand[q, :2].astype(np.float64)
        a, b = p[1] - p[0], p[3] - p[0]
        cross = a[0] * b[1] - a[1] * b[0]
        assert cross > 0  # clockwise on screen (y down), as discs 0-1-2-3 printed


# --------------------------------------------------------------------------------------
# The compiled kernels (`_grouping_kernels`: edge_sweep, edge_ranks_keep, group_graph)
# against the vectorised grouping
# --------------------------------------------------------------------------------------


def _reference_quad_geometry_ok(x: np.ndarray, y: np.ndarray, r: np.ndarray) -> np.ndarray:
    if x.shape[1] == 0:
        return np.zeros(0, bool)
    xn, yn = x[gr._NEXT], y[gr._NEXT]
    t = x * yn - xn * y
    area = 0.5 * (t[0] + t[1] + t[2] + t[3])
    rm = 0.25 * (r[0] + r[1] + r[2] + r[3])
    # sqrt(area) / radius is the same for every affine view of a card
    lo, hi = gr.SQRT_AREA_OVER_RADIUS[0] ** 2, gr.SQRT_AREA_OVER_RADIUS[1] ** 2
    ok = (area >= lo * rm * rm) & (area <= hi * rm * rm)
    ok &= r.max(axis=0) <= gr.RADIUS_RATIO_MAX * r.min(axis=0)
    ex, ey = xn - x, yn - y  # e[k] = p[k+1] - p[k]
    s2 = ex * ex + ey * ey
    ok &= s2.min(axis=0) >= gr.SIDE_RATIO_MIN**2 * s2.max(axis=0)
    exn, eyn, s2n = ex[gr._NEXT], ey[gr._NEXT], s2[gr._NEXT]
    cross = ex * eyn - ey * exn
    dot = ex * exn + ey * eyn
    # convex and turning like the layout; interior angle at every vertex in range
    ok &= ((cross > 0) & (dot * dot < gr._COS2_ANGLE * s2 * s2n)).all(axis=0)
    return ok


def _reference_edges(pts: np.ndarray, rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = pts.shape[0]
    order = np.argsort(pts[:, 0], kind="stable")
    # (ndarray.take: cheaper than fancy indexing, the more so on rows of 2-d arrays)
    xs, ys, rs = pts[:, 0].take(order), pts[:, 1].take(order), rad.take(order)
    reach = (1.5 * gr.EDGE_OVER_RADIUS[1]) * rs
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
    ok = (rb <= gr.RADIUS_RATIO_MAX * ra) & (ra <= gr.RADIUS_RATIO_MAX * rb)
    ok &= (d2 >= gr.EDGE_OVER_RADIUS[0] ** 2 * rs2) & (d2 <= gr.EDGE_OVER_RADIUS[1] ** 2 * rs2)
    sel = np.flatnonzero(ok)
    a, b = order[a[sel]], order[b[sel]]
    if a.size == 0:
        return a, b
    deg = np.bincount(a, minlength=n) + np.bincount(b, minlength=n)
    crowded = deg > gr.EDGE_KEEP
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
            drop[inc] = (rank[:m] >= gr.EDGE_KEEP) & (rank[m:] >= gr.EDGE_KEEP) & ca[inc] & cb[inc]
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
    ok = (dot * dot < gr._COS2_ANGLE * l1 * l2) & (short2 >= gr.SIDE_RATIO_MIN**2 * np.maximum(l1, l2))
    ok &= (cross >= gr.APEX_AREA_OVER_RADIUS[0] ** 2 * r2) & (cross <= gr.APEX_AREA_OVER_RADIUS[1] ** 2 * r2)
    return j, l_, short2, ok


def _reference_group(candidates: np.ndarray, img: np.ndarray | None = None, scale: float = 1.0
                     ) -> tuple[np.ndarray, gr._Graph | None]:
    empty = np.zeros((0, 4), np.intp)
    idx = gr._clean(candidates)
    n = idx.size
    if n < 3:
        return empty, None
    c = np.asarray(candidates, np.float64).take(idx, axis=0)
    pts, rad = c[:, :2].copy(), c[:, 2].copy()  # contiguous: for ndarray.take
    ea, eb = _reference_edges(pts, rad)
    dark = white = None
    if img is not None and ea.size:
        keep, dark, white = gr._side_test(pts, ea, eb, img, scale)
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
        return empty, gr._Graph(idx=idx, pts=pts, rad=rad, src=src, dst=dst, dark=dark)
    first = np.repeat(pos, more)
    second = np.arange(tot) - np.repeat(np.cumsum(more) - more - pos - 1, more)
    i = src[first]
    j0 = dst[first]
    j, l_, short2, ok = _reference_card_corners(pts, rad, i, j0, dst[second])
    corners = corner_white = None
    if dark is not None:
        # completion's corners (any apex): similar radii at j and l too
        rj, rl = rad[j], rad[l_]
        sel = np.flatnonzero(ok & (rj <= gr.RADIUS_RATIO_MAX * rl) & (rl <= gr.RADIUS_RATIO_MAX * rj))
        corners = np.array([i[sel], j[sel], l_[sel]])
        white = np.concatenate([white, white])[key]
        corner_white = np.minimum(white[first[sel]], white[second[sel]])
    graph = gr._Graph(idx=idx, pts=pts, rad=rad, src=src, dst=dst, dark=dark, corners=corners,
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
    good = (ex * ex + ey * ey <= gr.FOURTH_TOLERANCE**2 * short2[t]) & (k > i[t]) & (k != l_[t])
    t, k = t[good], k[good]
    if t.size == 0:
        return empty, graph
    quads = np.array([i[t], j[t], k, l_[t]])  # (4, P)
    quads = quads[:, _reference_quad_geometry_ok(px.take(quads), py.take(quads), rad.take(quads))]
    return idx.take(quads.T), graph


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
    """`grouping._group` (edge_sweep, edge_ranks_keep, group_graph) against the
    vectorised grouping: the proposals and every field of the graph, bit for bit."""
    rng = np.random.default_rng(16)
    n_quads = n_corners = 0
    for trial in range(600):
        cands, img = _random_candidates(rng, trial, 120, 160)
        for level in (img, None):
            got, got_graph = gr._group(cands, level, 0.5)
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
