"""Training the disc classifier (`app.core.detection.candidates.DiscClassifier`) from
labelled windows.

`train_classifier` fits both learned stages of the candidate detector from raw 12x12
windows: the screen (stage 1b, a one-hidden-layer perceptron: `fit_screen`) and the
condensed nearest-neighbour stage 2 (Hart's condensed nearest neighbour, `condense`,
then Gates' reduction, `reduce_store`), with thresholds calibrated on held-out
positives, and reports held-out statistics. `rejection_stats` measures on marker-free
images how many windows each stage lets through. Where the windows come from is the
caller's business: the simulator (`training`) or a site's own images (`adapt`, which
extends stage 2 with `condense` alone). Pure numpy/SciPy; no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from app.core.detection.candidates import (
    LEVELS,
    WINDOW,
    DiscClassifier,
    find_candidates,
    nn_scores,
    normalise_windows,
    stage1_windows,
)

__all__ = ["condense", "dihedral", "fit_screen", "nn_predict", "reduce_store", "rejection_stats", "train_classifier"]


def dihedral(windows: np.ndarray) -> np.ndarray:
    """The 8 rotations and reflections of each window (N, 12, 12) -> (8N, 12, 12): a
    disc has no preferred orientation, and neither do its neighbours."""
    w = np.asarray(windows)
    flipped = w[:, :, ::-1]
    return np.concatenate([np.rot90(w, k, axes=(1, 2)) for k in range(4)]
                          + [np.rot90(flipped, k, axes=(1, 2)) for k in range(4)])


def fit_screen(pos: np.ndarray, neg: np.ndarray, rng: np.random.Generator, hidden: int = 16,
               l2: float = 1e-4, max_iter: int = 250) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Stage 1b: a one-hidden-layer perceptron (ReLU) on normalised windows, fitted by
    L-BFGS to the class-balanced logistic loss with a small weight decay.

    Returns (w1 (144, H), b1 (H,), w2 (H,), b2). Deterministic for a given `rng`.
    """
    from scipy.optimize import minimize

    x = np.ascontiguousarray(np.concatenate([pos, neg]), dtype=np.float32)
    y = np.concatenate([np.ones(len(pos), np.float32), np.zeros(len(neg), np.float32)])
    n, d = x.shape
    weight = np.where(y == 1, n / (2.0 * len(pos)), n / (2.0 * len(neg))).astype(np.float32) / n
    sizes = (d * hidden, hidden, hidden, 1)
    cuts = np.cumsum(sizes)[:-1]

    def unpack(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        a, b, c, e = np.split(theta.astype(np.float32), cuts)
        return a.reshape(d, hidden), b, c, float(e[0])

    def loss(theta: np.ndarray) -> tuple[float, np.ndarray]:
        w1, b1, w2, b2 = unpack(theta)
        pre = x @ w1 + b1
        act = np.maximum(pre, 0.0)
        z = act @ w2 + b2
        # log(1 + exp(-z)) for positives, log(1 + exp(z)) for negatives, stably.
        s = np.where(y == 1, -z, z)
        value = float(np.sum(weight * (np.logaddexp(0.0, s)))) + l2 * float(np.sum(w1 * w1) + np.sum(w2 * w2))
        p = 1.0 / (1.0 + np.exp(-np.clip(z, -30, 30)))
        dz = weight * (p - y)
        g_w2 = act.T @ dz + 2 * l2 * w2
        g_b2 = np.array([dz.sum()], np.float32)
        d_act = np.outer(dz, w2) * (pre > 0)
        g_w1 = x.T @ d_act + 2 * l2 * w1
        g_b1 = d_act.sum(axis=0)
        return value, np.concatenate([g_w1.ravel(), g_b1, g_w2, g_b2]).astype(np.float64)

    theta0 = np.concatenate([
        rng.normal(0.0, 1.0 / np.sqrt(d), d * hidden), np.zeros(hidden),
        rng.normal(0.0, 1.0 / np.sqrt(hidden), hidden), np.zeros(1),
    ])
    result = minimize(loss, theta0, jac=True, method="L-BFGS-B", options={"maxiter": max_iter})
    w1, b1, w2, b2 = unpack(result.x)
    return w1, b1, w2, b2


def condense(x: np.ndarray, y: np.ndarray, rng: np.random.Generator, chunk: int = 2048,
             max_passes: int = 50, initial: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Hart's condensed nearest neighbour (1968): indices of a subset ("store") that
    classifies every training example correctly by 1-NN. Examples are visited in a
    random order; one misclassified by the current store joins it; passes repeat until
    one adds nothing. Returns (store indices, passes).

    Exact sequential semantics, but fast: each chunk's similarities to the store are one
    matrix product, and a prototype added inside the chunk updates the rest of the chunk
    with one vector product. Rows of x are unit vectors, so nearest = largest dot.

    ``initial``: indices that start the store (e.g. an existing classifier's prototypes
    when it is adapted to new examples: Hart's rule then adds only what they get wrong).
    """
    x = np.ascontiguousarray(x, dtype=np.float32)
    y = np.asarray(y).astype(np.int8)
    order = rng.permutation(x.shape[0])
    start_with = [int(order[0])] if initial is None or len(initial) == 0 else [int(i) for i in initial]
    store: list[int] = list(dict.fromkeys(start_with))
    in_store = np.zeros(x.shape[0], bool)
    in_store[store] = True
    passes = 0
    while passes < max_passes:
        passes += 1
        added = 0
        for start in range(0, order.size, chunk):
            idx = order[start : start + chunk]
            idx = idx[~in_store[idx]]
            if idx.size == 0:
                continue
            sims = x[idx] @ x[store].T  # (c, S)
            is_pos = y[store] == 1
            best_p = sims[:, is_pos].max(axis=1) if is_pos.any() else np.full(idx.size, -np.inf, np.float32)
            best_n = sims[:, ~is_pos].max(axis=1) if (~is_pos).any() else np.full(idx.size, -np.inf, np.float32)
            for j in range(idx.size):
                label = y[idx[j]]
                if (best_p[j] > best_n[j]) == (label == 1):
                    continue
                k = int(idx[j])
                store.append(k)
                in_store[k] = True
                added += 1
                if j + 1 < idx.size:
                    s = x[idx[j + 1 :]] @ x[k]
                    target = best_p if label == 1 else best_n
                    np.maximum(target[j + 1 :], s, out=target[j + 1 :])
        if added == 0:
            break
    return np.asarray(store, dtype=np.intp), passes


def reduce_store(x: np.ndarray, y: np.ndarray, store: np.ndarray) -> np.ndarray:
    """Gates' reduced nearest neighbour (1972), run after Hart's rule: visit the store
    in order and drop a prototype when every training example is still classified
    correctly without it. Returns the remaining store indices."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    y = np.asarray(y).astype(np.int8)
    store = np.asarray(store, dtype=np.intp)
    sims = x @ x[store].T  # (N, S)
    same = y[:, None] == y[store][None, :]
    keep = np.ones(store.size, bool)
    neg_inf = np.float32(-np.inf)

    def best(mask_cols: np.ndarray, rows: np.ndarray, same_class: bool) -> np.ndarray:
        sub = sims[np.ix_(rows, mask_cols)]
        ok = same[np.ix_(rows, mask_cols)] == same_class
        return np.where(ok, sub, neg_inf).max(axis=1) if mask_cols.size else np.full(rows.size, neg_inf)

    cols = np.flatnonzero(keep)
    rows_all = np.arange(x.shape[0])
    other = best(cols, rows_all, False)  # nearest prototype of the other class, per example
    for j in range(store.size):
        keep[j] = False
        cols = np.flatnonzero(keep)
        # Only examples whose nearest same-class prototype was j can change.
        affected = np.flatnonzero(same[:, j] & (sims[:, j] >= other))
        if affected.size:
            still = best(cols, affected, True)
            if not np.all(still > other[affected]):
                keep[j] = True
    return store[keep]


def nn_predict(x: np.ndarray, ref: np.ndarray, ref_labels: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """1-NN labels of unit rows `x` against reference unit rows (chunked)."""
    out = np.empty(x.shape[0], np.int8)
    ref = np.ascontiguousarray(ref, dtype=np.float32)
    for s in range(0, x.shape[0], chunk):
        out[s : s + chunk] = ref_labels[np.argmax(x[s : s + chunk] @ ref.T, axis=1)]
    return out


def train_classifier(
    positives: np.ndarray,
    negatives: np.ndarray,
    rng: np.random.Generator,
    *,
    blob_thresholds: float | Sequence[float] = (0.25, 0.16, 0.16, 0.16),
    screen_fn_rate: float = 0.01,
    nn_fn_rate: float = 0.003,
    hidden: int = 16,
    augment: bool = True,
    holdout: float = 0.15,
    max_screen_examples: int = 60000,
    max_condense_positives: int = 600,
    max_condense_negatives: int = 600,
    reduce: bool = True,
    nn_negatives: np.ndarray | None = None,
    background_images: Sequence[np.ndarray] = (),
    stats: dict[str, Any] | None = None,
) -> DiscClassifier:
    """Fit the screen (stage 1b) and condense stage 2 from raw (N, 12, 12) windows.

    positives: disc windows as stage 1a presents them (centred within ~1.5 level px);
    negatives: non-disc windows, best the ones stage 1a lets through (those are the ones
    the classifier has to tell apart).

    Splits: a ``holdout`` fraction of each class is kept out for the statistics; a
    further 10% of the positives calibrates the thresholds. ``augment`` adds the 8
    rotations/reflections of each training positive.

    * Screen: perceptron on a class-balanced subsample; threshold at ``screen_fn_rate``
      false negatives on the calibration positives.
    * Stage 2: Hart's rule on the training windows the screen passes (at most
      ``max_condense_*`` of each class: the condensed set, and so the time per window,
      grows with the examples near the boundary), then Gates' reduction (``reduce``) drops
      prototypes the training set does not need; threshold: the 1-NN rule (0) or lower,
      so that at most ``nn_fn_rate`` of the calibration positives the screen passes fail.

    ``nn_negatives`` are extra negatives for stage 2 only (e.g. the detector's own false
    candidates, mined on frames): those the screen passes fill up to half of the
    stage-2 negatives.
    ``blob_thresholds`` are the stage-1a thresholds per level (chosen by the caller on
    whole frames: they decide which windows exist, before any of this);
    ``background_images`` (marker-free photographs, uint8) measure the rejection factor.
    """
    pos_raw = _check_windows(positives, "positives")
    neg_raw = _check_windows(negatives, "negatives")
    if pos_raw.shape[0] < 20 or neg_raw.shape[0] < 20:
        raise ValueError("need at least 20 positive and 20 negative windows")
    info: dict[str, Any] = dict(stats or {})

    perm_p = rng.permutation(pos_raw.shape[0])
    n_test_p = int(round(holdout * perm_p.size))
    n_cal_p = max(1, int(round(0.1 * perm_p.size)))
    p_te, p_cal, p_tr = perm_p[:n_test_p], perm_p[n_test_p : n_test_p + n_cal_p], perm_p[n_test_p + n_cal_p :]
    perm_n = rng.permutation(neg_raw.shape[0])
    n_test_n = int(round(holdout * perm_n.size))
    n_te, n_tr = perm_n[:n_test_n], perm_n[n_test_n:]

    pos = normalise_windows(dihedral(pos_raw[p_tr]) if augment else pos_raw[p_tr])
    neg = normalise_windows(neg_raw[n_tr])
    cal = normalise_windows(pos_raw[p_cal])

    # Stage 1b on a class-balanced subsample (the cost of L-BFGS is linear in it).
    sp = np.sort(rng.choice(pos.shape[0], min(pos.shape[0], max_screen_examples // 2), replace=False))
    sn = np.sort(rng.choice(neg.shape[0], min(neg.shape[0], max_screen_examples // 2), replace=False))
    w1, b1, w2, b2 = fit_screen(pos[sp], neg[sn], rng, hidden=hidden)

    def screen(x: np.ndarray) -> np.ndarray:
        return np.maximum(x @ w1 + b1, 0.0) @ w2 + np.float32(b2)

    s_cal = screen(cal)
    screen_thr = float(np.quantile(s_cal, screen_fn_rate))

    # Stage 2: Hart's rule on what the screen lets through (the rest never reaches it).
    keep_p = np.flatnonzero(screen(pos) > screen_thr)
    keep_n = np.flatnonzero(screen(neg) > screen_thr)
    if keep_p.size == 0 or keep_n.size == 0:
        raise ValueError("the screen leaves no positives or no negatives to condense")
    if keep_p.size > max_condense_positives:
        keep_p = np.sort(rng.choice(keep_p, max_condense_positives, replace=False))
    extra = np.zeros((0, WINDOW * WINDOW), np.float32)
    if nn_negatives is not None and len(nn_negatives):
        extra = normalise_windows(_check_windows(nn_negatives, "nn_negatives"))
        extra = extra[screen(extra) > screen_thr]
        if extra.shape[0] > max_condense_negatives // 2:
            extra = extra[np.sort(rng.choice(extra.shape[0], max_condense_negatives // 2, replace=False))]
    n_plain = max_condense_negatives - extra.shape[0]
    if keep_n.size > n_plain:
        keep_n = np.sort(rng.choice(keep_n, n_plain, replace=False))
    x = np.concatenate([pos[keep_p], neg[keep_n], extra])
    y = np.concatenate([np.ones(keep_p.size, np.int8), np.zeros(keep_n.size + extra.shape[0], np.int8)])
    store, passes = condense(x, y, rng)
    hart_size = int(store.size)
    if reduce:
        store = reduce_store(x, y, store)
    protos, labels = x[store], y[store]
    clf = DiscClassifier(blob_thresholds=np.broadcast_to(np.asarray(blob_thresholds, np.float32), (LEVELS,)),
                         screen_w1=w1, screen_b1=b1, screen_w2=w2, screen_b2=b2,
                         screen_threshold=screen_thr, prototypes=protos, labels=labels, nn_threshold=0.0)
    cal_seen = s_cal > screen_thr
    cal_nn = nn_scores(cal[cal_seen], clf)
    nn_thr = min(0.0, float(np.quantile(cal_nn, nn_fn_rate))) if cal_nn.size else 0.0
    clf = clf.replace(nn_threshold=nn_thr)

    # Held-out statistics; stage 2 is judged on the windows the screen passes.
    te_x = normalise_windows(np.concatenate([pos_raw[p_te], neg_raw[n_te]]))
    te_y = np.concatenate([np.ones(p_te.size, np.int8), np.zeros(n_te.size, np.int8)])
    te_s1 = screen(te_x)
    seen = te_s1 > screen_thr
    full_pred = nn_predict(te_x[seen], x, y)
    cond_pred = nn_predict(te_x[seen], protos, labels)
    te_scores = nn_scores(te_x[seen], clf)
    ys = te_y[seen]

    def rate(a: np.ndarray) -> float | None:
        return float(np.mean(a)) if a.size else None

    info.update({
        "train_positives": int(p_tr.size),
        "train_positives_augmented": int(pos.shape[0]),
        "train_negatives": int(n_tr.size),
        "heldout_positives": int(p_te.size),
        "heldout_negatives": int(n_te.size),
        "screen_hidden_units": int(hidden),
        "screen_fn_rate_target": float(screen_fn_rate),
        "screen_fn_rate_heldout": rate(te_s1[te_y == 1] <= screen_thr),
        "screen_pass_rate_negatives_heldout": rate(te_s1[te_y == 0] > screen_thr),
        "condensation_examples": int(x.shape[0]),
        "condensation_mined_negatives": int(extra.shape[0]),
        "condensation_hart_prototypes": hart_size,
        "condensation_prototypes": int(protos.shape[0]),
        "condensation_positive_prototypes": int((labels == 1).sum()),
        "condensation_passes": int(passes),
        "nn_threshold": nn_thr,
        "heldout_agreement_condensed_vs_full": rate(full_pred == cond_pred),
        "heldout_full_1nn_accuracy": rate(full_pred == ys),
        "heldout_condensed_accuracy": rate(cond_pred == ys),
        "heldout_stage2_fn_rate": rate(te_scores[ys == 1] <= nn_thr),
        "heldout_stage2_fp_rate": rate(te_scores[ys == 0] > nn_thr),
        "heldout_stage2_score_positive_median": float(np.median(te_scores[ys == 1])) if (ys == 1).any() else None,
        "heldout_stage2_score_negative_median": float(np.median(te_scores[ys == 0])) if (ys == 0).any() else None,
        "heldout_fn_rate_stage1_and_2": rate(~(seen[te_y == 1]) | (nn_scores(te_x[te_y == 1], clf) <= nn_thr)),
    })
    if background_images:
        info.update(rejection_stats(clf, background_images))
    return clf.replace(stats=info)


def rejection_stats(classifier: DiscClassifier, images: Sequence[np.ndarray]) -> dict[str, Any]:
    """How many of all pyramid windows of `images` (marker-free) each stage lets
    through: the rejection factors (all windows / windows passed) of stage 1a, of
    stage 1 (1a + screen) and of the whole stage (candidates reported)."""
    total = passed_1a = passed = reported = 0
    for image in images:
        s1 = stage1_windows(image, classifier, apply_screen=False)
        total += s1.total_windows
        passed_1a += len(s1)
        passed += int(np.sum(s1.screen > np.float32(classifier.screen_threshold)))
        reported += int(find_candidates(image, classifier).shape[0])
    return {
        "background_windows": int(total),
        "stage1a_rejection_factor": float(total / max(passed_1a, 1)),
        "stage1_rejection_factor": float(total / max(passed, 1)),
        "candidate_rejection_factor": float(total / max(reported, 1)),
    }


def _check_windows(windows: np.ndarray, name: str) -> np.ndarray:
    w = np.asarray(windows)
    if w.ndim != 3 or w.shape[1:] != (WINDOW, WINDOW):
        raise ValueError(f"{name} must have shape (N, {WINDOW}, {WINDOW}), got {w.shape}")
    if w.dtype != np.uint8 and not np.isfinite(w).all():
        raise ValueError(f"{name} must be finite")
    return w
