"""Adapting a disc classifier to a site from its own images, self-labelled.

A site with odd lighting, paper or lenses shows discs the simulator-trained classifier
has seen little of. The user hands in a few images of the site with targets in view;
no one labels anything:

* the current detector runs on each image; every disc of a target it finds *and*
  verifies (grouping, photometric checks, a readable code) is a disc, so the stage-1
  windows at that disc (every level whose range holds it, within `PEAK_REACH` level
  pixels of its centre) become positives, including those stage 2 rejected;
* windows stage 1 passes far from every verified disc (`NEGATIVE_RADII` radii) become
  negatives, the candidates stage 2 wrongly accepted among them (the hard negatives);
  candidates that took part in a grouped quadrilateral that failed verification are
  left unlabelled: they may be the discs of a target the detector missed;
* stage 2, the condensed nearest-neighbour classifier, is extended by Hart's rule
  starting from the current prototypes (they stand for the simulator training set):
  only the site windows the current prototypes misclassify are added. Stage 1 (the
  blob thresholds and the screen) and the thresholds stay: refitting the screen on a
  few images would forget the simulator's range of conditions.

Pure numpy/OpenCV; no I/O.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.core.detection import as_gray, assemble_targets, group_candidates
from app.core.detection import candidates as cand
from app.core.markers import DEFAULT_FAMILY, get_family
from app.learning.classifier import condense, dihedral
from app.learning.labels import NEGATIVE_RADII, PEAK_REACH, disc_levels

Progress = Callable[[str, float], None]


@dataclass(frozen=True)
class SiteWindows:
    """Self-labelled windows from one site image and what the detector found there."""

    positives: np.ndarray  # (P, 12, 12) uint8
    negatives: np.ndarray  # (N, 12, 12) uint8
    targets: int  # verified, identified targets
    unlabelled: int  # candidates left out (members of unverified quadrilaterals)
    false_candidates: int  # candidates stage 2 accepted far from every verified disc


def label_site_image(gray: np.ndarray, classifier: cand.DiscClassifier, family: str = DEFAULT_FAMILY,
                     max_negatives: int = 2000, rng: np.random.Generator | None = None) -> SiteWindows:
    """Positive and negative windows of one uint8 greyscale image, labelled by the
    detector itself (see the module docstring)."""
    gray = as_gray(gray)
    rows, s1, kept = cand.detect_windows(gray, classifier)
    targets = assemble_targets(gray, rows, family)
    empty = np.zeros((0, cand.WINDOW, cand.WINDOW), np.uint8)
    if len(s1) == 0:
        return SiteWindows(empty, empty, len(targets), 0, 0)
    discs = np.array([[u, v, 2.0 * r] for t in targets for (u, v), r in zip(t.discs, t.disc_radii, strict=True)],
                     np.float64).reshape(-1, 3)
    # A disc whose measured radius is missing gets the mean of its card's.
    if discs.size:
        discs[:, 2] = np.where(discs[:, 2] > 0, discs[:, 2], np.nanmean(np.where(discs[:, 2] > 0, discs[:, 2], np.nan)))
    centres = s1.full_resolution_centres().astype(np.float64)
    scale = 2.0 ** s1.level.astype(np.float64)
    positive = np.zeros(len(s1), bool)
    far = np.ones(len(s1), bool)
    for u, v, d in discs:
        dist = np.hypot(centres[:, 0] - u, centres[:, 1] - v)
        positive |= np.isin(s1.level, disc_levels(d)) & (dist <= PEAK_REACH * scale)
        far &= dist > NEGATIVE_RADII * 0.5 * d + 0.5 * scale
    # Members of grouped quadrilaterals that were not verified: possibly a missed target.
    unverified = np.zeros(len(s1), bool)
    quads = group_candidates(rows)
    if quads.size:
        members = np.unique(quads)
        suspect = rows[members]
        for u, v, r, _ in suspect:
            near = np.hypot(centres[:, 0] - u, centres[:, 1] - v) <= max(NEGATIVE_RADII * r, 1.5 * 2.0)
            unverified |= near
    negative = far & ~unverified
    accepted = np.zeros(len(s1), bool)
    accepted[kept] = True
    false_candidates = int((accepted & negative).sum())
    neg_idx = np.flatnonzero(negative)
    if neg_idx.size > max_negatives:
        # Keep every hard negative (stage 2 accepted it), sample the rest.
        hard = neg_idx[accepted[neg_idx]]
        easy = neg_idx[~accepted[neg_idx]]
        rng = rng if rng is not None else np.random.default_rng(0)
        take = max(max_negatives - hard.size, 0)
        easy = np.sort(rng.choice(easy, min(take, easy.size), replace=False))
        neg_idx = np.concatenate([hard, easy])
    return SiteWindows(
        positives=s1.windows[positive],
        negatives=s1.windows[neg_idx],
        targets=len(targets),
        unlabelled=int((far & unverified & accepted).sum()),
        false_candidates=false_candidates,
    )


def _stage2_rates(classifier: cand.DiscClassifier, positives: np.ndarray, negatives: np.ndarray
                  ) -> tuple[float | None, float | None]:
    """(fraction of positive windows stage 2 accepts, fraction of negatives it accepts)."""
    def accept(w: np.ndarray) -> float | None:
        if w.shape[0] == 0:
            return None
        return float(np.mean(cand.nn_scores(cand.normalise_windows(w), classifier) > classifier.nn_threshold))

    return accept(positives), accept(negatives)


def adapt_classifier(
    base: cand.DiscClassifier,
    images: Sequence[np.ndarray],
    family: str = DEFAULT_FAMILY,
    progress: Progress | None = None,
    seed: int = 0,
    max_negatives_per_image: int = 2000,
) -> cand.DiscClassifier:
    """A new classifier: `base` with stage 2 extended by the self-labelled windows of
    `images` (uint8 greyscale). Raises ValueError when the images hold no verified
    target (there would be nothing to learn discs from)."""
    get_family(family)
    if not images:
        raise ValueError("no images to adapt to")
    rng = np.random.default_rng(seed)
    labelled: list[SiteWindows] = []
    for index, image in enumerate(images):
        labelled.append(label_site_image(image, base, family, max_negatives_per_image, rng))
        if progress:
            progress("labelling site images", 0.6 * (index + 1) / len(images))
    pos = np.concatenate([s.positives for s in labelled])
    neg = np.concatenate([s.negatives for s in labelled])
    targets_before = [s.targets for s in labelled]
    if sum(targets_before) == 0:
        raise ValueError("the current classifier verified no target in any image: "
                         "give images where at least one target is clearly in view")
    if progress:
        progress("condensing", 0.65)
    # Site disc windows in all 8 rotations/reflections, like the simulator positives.
    site_pos = cand.normalise_windows(dihedral(pos)) if pos.size else np.zeros((0, cand.WINDOW**2), np.float32)
    site_neg = cand.normalise_windows(neg) if neg.size else np.zeros((0, cand.WINDOW**2), np.float32)
    protos = np.asarray(base.prototypes, np.float32)
    x = np.concatenate([protos, site_pos, site_neg])
    y = np.concatenate([np.asarray(base.labels, np.int8), np.ones(site_pos.shape[0], np.int8),
                        np.zeros(site_neg.shape[0], np.int8)])
    store, passes = condense(x, y, rng, initial=np.arange(protos.shape[0]))
    adapted = base.replace(prototypes=x[store], labels=y[store])
    recall_before, fp_before = _stage2_rates(base, pos, neg)
    recall_after, fp_after = _stage2_rates(adapted, pos, neg)
    if progress:
        progress("checking on the site images", 0.8)
    targets_after = []
    for index, image in enumerate(images):
        rows = cand.find_candidates(image, adapted)
        targets_after.append(len(assemble_targets(as_gray(image), rows, family)))
        if progress:
            progress("checking on the site images", 0.8 + 0.2 * (index + 1) / len(images))
    stats: dict[str, Any] = {
        **{k: v for k, v in base.stats.items() if k in ("seed", "blob_thresholds")},
        "adapted_from_prototypes": int(protos.shape[0]),
        "site_images": len(images),
        "site_targets_verified": int(sum(targets_before)),
        "site_positive_windows": int(pos.shape[0]),
        "site_negative_windows": int(neg.shape[0]),
        "site_hard_negatives": int(sum(s.false_candidates for s in labelled)),
        "site_unlabelled_candidates": int(sum(s.unlabelled for s in labelled)),
        "condensation_prototypes": int(store.size),
        "condensation_added": int(store.size - protos.shape[0]),
        "condensation_passes": int(passes),
        "site_stage2_disc_window_accept_before": recall_before,
        "site_stage2_disc_window_accept_after": recall_after,
        "site_stage2_false_window_accept_before": fp_before,
        "site_stage2_false_window_accept_after": fp_after,
        "site_targets_before": int(sum(targets_before)),
        "site_targets_after": int(sum(targets_after)),
    }
    if progress:
        progress("done", 1.0)
    return adapted.replace(stats=stats)
