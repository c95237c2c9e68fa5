"""Disc candidates: the learned first stage of the fiducial detector (Claus & Fitzgibbon,
WACV 2005, section 4).

The paper's "ideal but impractical" detector compares every 12x12 window of a 4-level
image pyramid with every training example (1-nearest neighbour) and made it run at video
rate with two changes, both here:

* a fast classifier at the line marked [*] that rejects almost every window while
  keeping ~99% of the disc windows (stage 1; the paper: ~3000x fewer windows), and
* Hart's condensed nearest neighbour, which shrinks the training set to the examples
  near the class boundary (stage 2: the 1-NN decision with far fewer distances).

Stage 1 is a cascade of two cheap tests:

1a. A dense dark-blob operator over every window of every level, a handful of whole-image
    OpenCV calls: the black top-hat ``closing(I) - I`` (12x12 structuring element: a dark
    spot narrower than the window is filled, an edge or a large dark area is not), its
    4x4 centre mean minus its 12x12 window mean (the dark mass must sit in the middle of
    the window), divided by the window's grey-level range (invariant to gain and offset).
    Only 3x3 local maxima above a per-level threshold survive: ~1000 windows of a
    textured 640x480 frame (~400x fewer than all windows).
1b. The "screen": a one-hidden-layer perceptron (16 ReLU units) on the normalised window,
    2.3k multiply-adds per window, trained on discs against the windows 1a lets through.
    Together ~2000x fewer windows than a full scan, ~200-300 per textured frame.

Each survivor's disc centre and radius are measured in its window (`window_geometry`).
Non-maximum suppression groups the windows of one disc (neighbouring positions and
levels) in order of the screen score, and stage 2 judges each group's leader: the
condensed 1-NN on windows normalised to zero mean and unit norm, where a squared
distance is ``2 - 2 a.b``, so the stage is one float32 matrix product with ~360
prototypes. A leader stage 2 rejects does not take its group down (the windows only it
suppressed get their turn). The stage-2 score (distance to the nearest non-disc
prototype minus distance to the nearest disc prototype) is the candidate's score.

Why the screen: every window 1a proposes is a dark blob, and in the space of normalised
12x12 windows many of them (eyes, coins, punctuation, gaps in gravel) lie among the
discs. Hart's rule then keeps a large fraction of whatever it is given (~30% here, vs
1.4% in the paper, whose negatives were random windows), and a 1-NN over thousands of
prototypes for every 1a window would take milliseconds. The screen removes ~85% of those
windows at a tenth of the cost, so stage 2 sees ~200 windows per frame and its condensed
set can stay small. The thresholds of the screen and stage 2 are tuned together, after
training, for disc recall on fresh frames of each condition (`app.learning.training`).

Scale: the window is fixed at 12x12 and the image is halved per level (``cv2.pyrDown``).
Each level is trained for discs of 3.5..10 of its pixels across (`DIAMETER_RANGE`), so
consecutive levels overlap and the four levels together cover discs of ~3.5 to ~80
full-resolution pixels: below ~3.5 px a disc no longer differs from a speck of texture;
at 10 px the window still shows a ring of card around the disc.

Coordinates: full resolution, centre of the top-left pixel at (0, 0). ``cv2.pyrDown``
centres level-L pixel i on full-resolution pixel ``i * 2**L``, so a level position maps
to full resolution by a plain ``* 2**L``.

numpy/OpenCV/SciPy, and a few numba kernels (`app.core.detection.kernels`: the rest of stage 1a
after the morphology, the window copies, the screen's correction, the suppression
sweep) where fused loops beat chains of whole-array calls, with identical results. No
I/O apart from `load_default_classifier` reading the file that ships inside the package.
"""

from __future__ import annotations

import dataclasses
import json
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from app.core.detection import kernels

WINDOW: int = 12
LEVELS: int = 4
#: Disc diameter, in pixels of the pyramid level it is found at, that a level is trained
#: for. The ranges of neighbouring levels overlap (10 / 2 > 3.5), so every disc from ~3.5
#: to ~80 px has at least one level where it fits the window well.
DIAMETER_RANGE: tuple[float, float] = (3.5, 10.0)
#: Smallest image side accepted by `find_candidates`.
MIN_SIDE: int = 2 * WINDOW

_HALF = WINDOW // 2  # border added around each level so windows may overhang the edge
_DIM = WINDOW * WINDOW
_SE = np.ones((WINDOW, WINDOW), np.uint8)
_RANGE_EPS = 2.0  # grey levels added to the range in 1a: flat regions score ~0
_NORM_EPS = 1e-3  # norm floor when normalising (a flat window stays ~0, never NaN)

_FORMAT_VERSION = 1


# --------------------------------------------------------------------------------------
# Classifier
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)  # eq=False: ndarray fields make a generated __eq__ useless
class DiscClassifier:
    """Trained parameters of both stages.

    blob_thresholds: (LEVELS,) stage 1a, minimum dark-blob score of a local maximum at
        each level (level 0, with ~2/3 of all windows and only small, sharp discs, can
        afford a stricter one).
    screen_w1 (144, H), screen_b1 (H,), screen_w2 (H,), screen_b2, screen_threshold:
        stage 1b, a one-hidden-layer perceptron on the normalised window x,
        ``w2 . relu(x W1 + b1) + b2 > screen_threshold``.
    prototypes: (M, 144) float32 condensed training windows, normalised (zero mean,
        unit norm); labels: (M,) int8, 1 disc, 0 not.
    nn_threshold: stage 2 accepts a window when (distance to the nearest negative
        prototype) - (distance to the nearest positive) > nn_threshold; 0 is the plain
        1-NN rule.
    stats: training statistics (JSON-able).
    """

    blob_thresholds: np.ndarray
    screen_w1: np.ndarray
    screen_b1: np.ndarray
    screen_w2: np.ndarray
    screen_b2: float
    screen_threshold: float
    prototypes: np.ndarray
    labels: np.ndarray
    nn_threshold: float = 0.0
    stats: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        w1 = np.ascontiguousarray(self.screen_w1, dtype=np.float32)
        b1 = np.ascontiguousarray(self.screen_b1, dtype=np.float32).reshape(-1)
        w2 = np.ascontiguousarray(self.screen_w2, dtype=np.float32).reshape(-1)
        protos = np.ascontiguousarray(self.prototypes, dtype=np.float32)
        labels = np.asarray(self.labels).astype(np.int8).reshape(-1)
        if w1.ndim != 2 or w1.shape[0] != _DIM or w1.shape[1] < 1:
            raise ValueError(f"screen_w1 must have shape ({_DIM}, H), got {w1.shape}")
        if b1.shape != (w1.shape[1],) or w2.shape != (w1.shape[1],):
            raise ValueError("screen_b1 and screen_w2 must have one entry per hidden unit")
        if protos.ndim != 2 or protos.shape[1] != _DIM:
            raise ValueError(f"prototypes must have shape (M, {_DIM}), got {protos.shape}")
        if labels.shape != (protos.shape[0],):
            raise ValueError("labels must have one entry per prototype")
        if not np.isin(labels, (0, 1)).all():
            raise ValueError("labels must be 0 or 1")
        if not (labels == 1).any() or not (labels == 0).any():
            raise ValueError("stage 2 needs at least one positive and one negative prototype")
        blob = np.array(self.blob_thresholds, dtype=np.float32).reshape(-1)
        if blob.size == 1:
            blob = np.repeat(blob, LEVELS)
        if blob.shape != (LEVELS,) or not np.isfinite(blob).all():
            raise ValueError(f"blob_thresholds must hold {LEVELS} finite numbers")
        blob.setflags(write=False)
        object.__setattr__(self, "blob_thresholds", blob)
        for name in ("screen_b2", "screen_threshold", "nn_threshold"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite")
            object.__setattr__(self, name, value)
        if not all(np.isfinite(a).all() for a in (w1, b1, w2, protos)):
            raise ValueError("classifier arrays must be finite")
        for name, a in (("screen_w1", w1), ("screen_b1", b1), ("screen_w2", w2), ("prototypes", protos),
                        ("labels", labels)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        object.__setattr__(self, "stats", dict(self.stats))
        # Column sums of W1, for `_screen_raw`; and prototypes split by class once
        # (stage 2 needs the nearest of each class).
        object.__setattr__(self, "_w1_sum", w1.sum(axis=0))
        object.__setattr__(self, "_w1_ext", np.ascontiguousarray(np.concatenate([w1, np.ones((_DIM, 1), np.float32)], 1)))
        object.__setattr__(self, "_pos", np.ascontiguousarray(protos[labels == 1].T))
        object.__setattr__(self, "_neg", np.ascontiguousarray(protos[labels == 0].T))

    def replace(self, **changes: Any) -> DiscClassifier:
        """A copy with some fields changed (thresholds, stats)."""
        return dataclasses.replace(self, **changes)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Every parameter as a named array (scalars as 0-d arrays), for .npy storage."""
        return {
            "format_version": np.array(_FORMAT_VERSION, dtype=np.int32),
            "window": np.array(WINDOW, dtype=np.int32),
            "blob_thresholds": np.array(self.blob_thresholds, dtype=np.float32),
            "screen_w1": np.array(self.screen_w1, dtype=np.float32),
            "screen_b1": np.array(self.screen_b1, dtype=np.float32),
            "screen_w2": np.array(self.screen_w2, dtype=np.float32),
            "screen_b2": np.array(self.screen_b2, dtype=np.float64),
            "screen_threshold": np.array(self.screen_threshold, dtype=np.float64),
            "prototypes": np.array(self.prototypes, dtype=np.float32),
            "labels": np.array(self.labels, dtype=np.int8),
            "nn_threshold": np.array(self.nn_threshold, dtype=np.float64),
        }

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], stats: dict[str, Any] | None = None) -> DiscClassifier:
        """Inverse of `to_arrays`; ValueError on a missing or malformed array."""
        required = ("blob_thresholds", "screen_w1", "screen_b1", "screen_w2", "screen_b2", "screen_threshold",
                    "prototypes", "labels")
        missing = [k for k in required if k not in arrays]
        if missing:
            raise ValueError(f"classifier arrays missing: {', '.join(missing)}")
        version = int(np.asarray(arrays.get("format_version", _FORMAT_VERSION)))
        if version != _FORMAT_VERSION:
            raise ValueError(f"unsupported classifier format version {version}")
        window = int(np.asarray(arrays.get("window", WINDOW)))
        if window != WINDOW:
            raise ValueError(f"classifier was trained for {window}x{window} windows, not {WINDOW}x{WINDOW}")

        def scalar(name: str, default: float | None = None) -> float:
            a = np.asarray(arrays[name]) if name in arrays else np.asarray(default)
            if a.size != 1:
                raise ValueError(f"{name} must be a scalar")
            return float(a.reshape(()))

        return cls(
            blob_thresholds=np.asarray(arrays["blob_thresholds"]),
            screen_w1=np.asarray(arrays["screen_w1"]),
            screen_b1=np.asarray(arrays["screen_b1"]),
            screen_w2=np.asarray(arrays["screen_w2"]),
            screen_b2=scalar("screen_b2"),
            screen_threshold=scalar("screen_threshold"),
            prototypes=np.asarray(arrays["prototypes"]),
            labels=np.asarray(arrays["labels"]),
            nn_threshold=scalar("nn_threshold", 0.0),
            stats=dict(stats or {}),
        )


def load_default_classifier() -> DiscClassifier:
    """The classifier shipped with the package (``app/data/default_classifier.npz``,
    made by ``scripts/train_default_classifier.py``)."""
    from importlib import resources

    with resources.files("app.data").joinpath("default_classifier.npz").open("rb") as fh:
        with np.load(fh, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    stats = json.loads(str(arrays.pop("stats_json"))) if "stats_json" in arrays else {}
    return DiscClassifier.from_arrays(arrays, stats)


# --------------------------------------------------------------------------------------
# Workspace
# --------------------------------------------------------------------------------------


class _Workspace:
    """Reusable image-sized buffers, by (name, shape, dtype).

    Stage 1a touches ~15 arrays the size of a pyramid level per frame. Allocated afresh
    each time they come from mmap and every page faults on first touch, which costs more
    than the OpenCV calls filling them (measured: 5 ms vs 0.7 ms per 640x480 frame), so
    the detector keeps one workspace per thread (`_thread_workspace`) and writes into
    it. A buffer is valid until its name is next used for an image of the same size."""

    def __init__(self) -> None:
        self._buffers: dict[tuple[str, tuple[int, ...], str], np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        key = (name, shape, dtype)  # callers pass tuples of ints and numpy scalar types
        buf = self._buffers.get(key)
        if buf is None:
            if len(self._buffers) > 256:  # many image sizes: start again rather than grow
                self._buffers.clear()
            buf = self._buffers[key] = np.empty(tuple(int(s) for s in shape), dtype)
        return buf

    def rows(self, name: str, n: int, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        """The first `n` rows of a buffer of ``(capacity, *shape)`` (capacity a power of
        two >= n, so a varying count reuses one buffer)."""
        cap = 1 << max(int(n) - 1, 0).bit_length()
        return self.get(name, (max(cap, 64), *shape), dtype)[:n]


_LOCAL = threading.local()


def _thread_workspace() -> _Workspace:
    ws = getattr(_LOCAL, "workspace", None)
    if ws is None:
        ws = _LOCAL.workspace = _Workspace()
    return ws


# --------------------------------------------------------------------------------------
# Input and pyramid
# --------------------------------------------------------------------------------------


def as_gray(image: np.ndarray) -> np.ndarray:
    """uint8 greyscale from uint8 greyscale, BGR or BGRA; ValueError otherwise."""
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    elif a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    elif a.ndim != 2:
        raise ValueError(f"expected a greyscale or BGR image, got shape {a.shape}")
    if min(a.shape) < MIN_SIDE:
        raise ValueError(f"image must be at least {MIN_SIDE}x{MIN_SIDE} pixels, got {a.shape[1]}x{a.shape[0]}")
    return np.ascontiguousarray(a)


def pyramid(gray: np.ndarray, workspace: _Workspace | None = None) -> list[np.ndarray]:
    """Up to `LEVELS` uint8 levels, each halved by ``cv2.pyrDown``; levels with a side
    shorter than half a window are left out (nothing to find there)."""
    levels = [gray]
    while len(levels) < LEVELS:
        h, w = levels[-1].shape
        if min((h + 1) // 2, (w + 1) // 2) < _HALF:
            break
        dst = None if workspace is None else workspace.get(f"pyr{len(levels)}", ((h + 1) // 2, (w + 1) // 2), np.uint8)
        levels.append(cv2.pyrDown(levels[-1], dst=dst))
    return levels


def pyramid_window_count(shape: tuple[int, int]) -> int:
    """Windows a full scan examines: one per pixel position of every level."""
    h, w = shape[:2]
    total = 0
    for level in range(LEVELS):
        if level and min(h, w) < _HALF:
            break
        total += (h + 1) * (w + 1)
        h, w = (h + 1) // 2, (w + 1) // 2
    return total


# --------------------------------------------------------------------------------------
# Stage 1a: dense dark-blob score
# --------------------------------------------------------------------------------------


def pad_level(level: np.ndarray, workspace: _Workspace | None = None) -> np.ndarray:
    """The level with a replicated border of half a window, so that windows centred on
    any pixel of the level (including at its very edge) exist."""
    h, w = level.shape
    dst = None if workspace is None else workspace.get("pad", (h + WINDOW, w + WINDOW), np.uint8)
    return cv2.copyMakeBorder(level, _HALF, _HALF, _HALF, _HALF, cv2.BORDER_REPLICATE, dst=dst)


def _tophat_integral(padded: np.ndarray, ws: _Workspace) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The morphology of stage 1a on a padded level: (integral image (h + 1, w + 1) int32
    of the black top-hat, 12x12 max, 12x12 min), in `ws`'s buffers."""
    h, w = padded.shape
    key = (h, w)
    # 12x12 max/min over the window (anchor 6: rows y-6..y+5 -> centre y-0.5) and the
    # closing (erosion anchored at 5 so the composite element is centred).
    dil = cv2.dilate(padded, _SE, dst=ws.get("dil", key, np.uint8), anchor=(_HALF, _HALF))
    ero = cv2.erode(padded, _SE, dst=ws.get("ero", key, np.uint8), anchor=(_HALF, _HALF))
    tophat = cv2.erode(dil, _SE, dst=ws.get("top", key, np.uint8), anchor=(_HALF - 1, _HALF - 1))
    cv2.subtract(tophat, padded, dst=tophat)
    # window sums from the integral image (exact int32): `kernels.blob_ratio`
    integral = cv2.integral(tophat, sum=ws.get("int", (h + 1, w + 1), np.int32), sdepth=cv2.CV_32S)
    return integral, dil, ero


def blob_scores(padded: np.ndarray, workspace: _Workspace | None = None) -> np.ndarray:
    """Stage-1a score of every 12x12 window lying wholly inside `padded` (a level with
    a replicated border, see `pad_level`).

    Returns float32 of shape (h - 11, w - 11): entry (y, x) scores the window
    ``padded[y : y + 12, x : x + 12]``. Unitless, about -1..1; a clean disc of the
    level's size range scores 0.4-0.8.

    With a `workspace` every intermediate and the result live in its buffers (valid
    until the workspace is next used for an image of this size); without, fresh arrays.
    """
    ws = workspace if workspace is not None else _Workspace()
    h, w = padded.shape
    integral, dil, ero = _tophat_integral(padded, ws)
    # (centre mean - window mean) / (range + eps) from the window sums, in one compiled
    # pass with the arithmetic of the OpenCV calls it replaced
    score = ws.get("blob", (h - WINDOW + 1, w - WINDOW + 1), np.float32)
    kernels.blob_ratio(integral, dil, ero, np.float32(_RANGE_EPS), score)
    return score


def _maxima_buffers(shape: tuple[int, int], ws: _Workspace) -> tuple[np.ndarray, ...]:
    """Scratch and output buffers of `kernels.local_maxima` for scores of `shape`."""
    h, w = shape
    return (ws.get("max3", (3, w), np.float32), ws.get("maxima_row", (-(-w // 8) * 8,), np.uint8),
            ws.get("maxima_y", (h * w,), np.intp), ws.get("maxima_x", (h * w,), np.intp))


def _threshold32(threshold: float) -> np.float32:
    """A local maximum's threshold, + tiny (strictly above), rounded to float32 as
    cv2.max rounds a scalar for a float32 image."""
    return np.float32(float(threshold) + 1e-6)


def local_maxima(score: np.ndarray, threshold: float, workspace: _Workspace | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(ys, xs) int arrays of 3x3 local maxima of `score` strictly above `threshold`,
    in row-major order."""
    ws = workspace if workspace is not None else _Workspace()
    max3, row_mask, ys, xs = _maxima_buffers(score.shape, ws)
    n = kernels.local_maxima(np.ascontiguousarray(score, np.float32), _threshold32(threshold), max3, row_mask, ys, xs)
    return ys[:n].copy(), xs[:n].copy()


def _blob_maxima(padded: np.ndarray, threshold: float, ws: _Workspace) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``local_maxima(blob_scores(padded), threshold)`` and the scores there, in one
    pass that never writes the score image (`kernels.blob_maxima`): (ys, xs, scores)."""
    h, w = padded.shape
    integral, dil, ero = _tophat_integral(padded, ws)
    shape = (h - WINDOW + 1, w - WINDOW + 1)
    max3, row_mask, ys, xs = _maxima_buffers(shape, ws)
    rows = ws.get("blob_rows", (3, shape[1]), np.float32)  # the scores: three rows at a time
    vals = ws.get("maxima_score", (shape[0] * shape[1],), np.float32)
    n = kernels.blob_maxima(integral, dil, ero, np.float32(_RANGE_EPS), _threshold32(threshold), rows, max3, row_mask,
                            ys, xs, vals)
    return ys[:n].copy(), xs[:n].copy(), vals[:n].copy()


def stage1_scores(level: np.ndarray) -> np.ndarray:
    """Dense stage-1a score of every window of one pyramid level (uint8, H x W):
    float32 (H + 1, W + 1), entry (y, x) for the window centred at level position
    (x - 0.5, y - 0.5)."""
    return blob_scores(pad_level(np.ascontiguousarray(level, dtype=np.uint8)))


def stage1_mask(level: np.ndarray, threshold: float) -> np.ndarray:
    """bool (H + 1, W + 1): the windows of one level stage 1a passes (3x3 local maxima of
    `stage1_scores` above `threshold`), indexed as `stage1_scores`."""
    score = stage1_scores(level)
    mask = np.zeros(score.shape, bool)
    ys, xs = local_maxima(score, threshold)
    mask[ys, xs] = True
    return mask


# --------------------------------------------------------------------------------------
# Windows
# --------------------------------------------------------------------------------------


def extract_windows(padded: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """(N, 12, 12) uint8 copies of the windows with top-left ``(ys, xs)`` of a padded level."""
    h, w = padded.shape
    sy, sx = padded.strides
    # A read-only strided view of every window (np.ndarray directly: as_strided costs
    # ~30 us of Python per call).
    shape = (h - WINDOW + 1, w - WINDOW + 1, WINDOW, WINDOW)
    if padded.dtype == np.uint8 and padded.flags.c_contiguous:
        view = np.ndarray(shape, np.uint8, padded, 0, (sy, sx, sy, sx))
    else:
        view = np.lib.stride_tricks.as_strided(padded, shape, (sy, sx, sy, sx), writeable=False)
    return view[ys, xs]


def normalise_windows(windows: np.ndarray) -> np.ndarray:
    """(N, 144) float32: each window minus its mean, divided by its norm (unit vectors,
    so squared distances are ``2 - 2 a.b``). Invariant to gain and offset; a flat window
    becomes ~0 rather than NaN."""
    w = np.asarray(windows, dtype=np.float32).reshape(-1, _DIM)
    w = w - w.mean(axis=1, keepdims=True)
    norm = np.sqrt(np.einsum("ij,ij->i", w, w))
    w /= np.maximum(norm, np.float32(_NORM_EPS))[:, None]
    return w


def screen_scores(normalised: np.ndarray, classifier: DiscClassifier) -> np.ndarray:
    """Stage-1b score of normalised windows (N, 144): ``w2 . relu(x W1 + b1) + b2``."""
    hidden = np.asarray(normalised, np.float32) @ classifier.screen_w1
    hidden += classifier.screen_b1
    np.maximum(hidden, 0.0, out=hidden)
    return hidden @ classifier.screen_w2 + np.float32(classifier.screen_b2)


def _screen_gathered(flat: np.ndarray, sums: np.ndarray, sums_sq: np.ndarray, classifier: DiscClassifier
                     ) -> np.ndarray:
    """`screen_scores` of raw windows (N, 144) float32 (with their pixel sums and sums of
    squares, `kernels.gather_windows`) without normalising them first:
    ``x W1 = (w W1 - mean(w) 1 W1) / |w - mean(w)|``, one product and a cheap
    correction (`kernels.screen_hidden`) instead of a pass over every pixel of every
    window."""
    # (W1 extended by a column of ones, whose product column is not used any more: the
    # product of the same shape keeps BLAS's float32 sums, and so the scores, as they were)
    product = flat @ classifier._w1_ext  # type: ignore[attr-defined]
    hidden = product[:, :-1]
    kernels.screen_hidden(hidden, sums, sums_sq, classifier._w1_sum,  # type: ignore[attr-defined]
                          classifier.screen_b1, np.float32(_NORM_EPS))
    return hidden @ classifier.screen_w2 + np.float32(classifier.screen_b2)


def nn_scores(normalised: np.ndarray, classifier: DiscClassifier) -> np.ndarray:
    """Stage-2 score of normalised windows: distance to the nearest negative prototype
    minus distance to the nearest positive one (> 0: the nearest example is a disc)."""
    x = np.ascontiguousarray(normalised, dtype=np.float32)
    if x.shape[0] == 0:
        return np.zeros(0, np.float32)
    # Unit vectors: |a - b|^2 = 2 - 2 a.b, so the nearest prototype has the largest dot.
    pos = (x @ classifier._pos).max(axis=1)  # type: ignore[attr-defined]
    neg = (x @ classifier._neg).max(axis=1)  # type: ignore[attr-defined]
    # Norm of a flat window is ~0, not 1; its distances are still well defined below.
    sq = np.einsum("ij,ij->i", x, x)
    d_pos = np.sqrt(np.maximum(sq + 1.0 - 2.0 * pos, 0.0))
    d_neg = np.sqrt(np.maximum(sq + 1.0 - 2.0 * neg, 0.0))
    return (d_neg - d_pos).astype(np.float32)


def classify_windows(windows: np.ndarray, classifier: DiscClassifier) -> np.ndarray:
    """Stage 2 alone on raw (N, 12, 12) windows: `nn_scores` of the normalised windows."""
    w = np.asarray(windows)
    if w.ndim != 3 or w.shape[1:] != (WINDOW, WINDOW):
        raise ValueError(f"windows must have shape (N, {WINDOW}, {WINDOW}), got {w.shape}")
    return nn_scores(normalise_windows(w), classifier)


# --------------------------------------------------------------------------------------
# Position and radius from the window
# --------------------------------------------------------------------------------------

_GRID = np.arange(WINDOW, dtype=np.float32) - np.float32((WINDOW - 1) / 2)  # offsets from the centre
_DX = np.tile(_GRID, WINDOW)
_DY = np.repeat(_GRID, WINDOW)
_DIST = np.hypot(_DX, _DY)
_DIST2 = _DX * _DX + _DY * _DY
_DXY = np.stack([_DX, _DY], axis=1)  # (144, 2): first moments by one product
_RING_EDGES = np.arange(0.0, 7.0, 1.0, dtype=np.float32)  # rings 0-1, 1-2, ..., 5-6 px
_RINGS = np.stack([(_DIST >= a) & (_DIST < a + 1) for a in _RING_EDGES[:-1]], axis=1).astype(np.float32)
_RINGS /= _RINGS.sum(axis=0, keepdims=True)  # (144, 6): ring means by one product
_RING_MID = _RING_EDGES[:-1] + 0.5
#: The half-level crossing of the ring profile sits ~16% inside the true edge (rings
#: average the blurred edge with the dark centre); measured on simulated discs.
_RADIUS_GAIN = 1.19


def window_radius(windows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Disc radius (N,) in pixels of the window's level, and the grey level (N,) halfway
    between the disc and its surround.

    The radial profile (mean grey level in 1-px rings about the window centre) is
    followed out from the darkest of the two inner rings until it crosses halfway to the
    brightest ring beyond; the crossing is interpolated and scaled by `_RADIUS_GAIN`.
    """
    w = np.asarray(windows, dtype=np.float32).reshape(-1, _DIM)
    prof = w @ _RINGS  # (N, 6): BLAS's float32 sums, as they were
    # the rest per window in one compiled loop (`kernels.ring_radius`: the same float32
    # steps as the numpy chain it replaced, without ~15 calls' overhead)
    radius, half = np.empty(w.shape[0], np.float32), np.empty(w.shape[0], np.float32)
    kernels.ring_radius(prof, _RING_MID, np.float32(_RADIUS_GAIN), radius, half)
    return radius, half


def window_centroid(windows: np.ndarray, radius: np.ndarray, half: np.ndarray, iterations: int = 2) -> np.ndarray:
    """Sub-pixel offset (N, 2) of the dark disc from the window centre, in pixels of the
    window's level: the centroid of darkness (`half` minus grey level, clipped at 0)
    inside a circular aperture of the disc radius plus a pixel, re-centred on the
    previous estimate `iterations - 1` times, so neighbours in the window barely pull."""
    w = np.ascontiguousarray(windows, dtype=np.float32).reshape(-1, _DIM)
    half = np.ascontiguousarray(half, np.float32)
    reach2 = (np.asarray(radius, np.float32) + np.float32(1.0)) ** 2
    offset = np.zeros((w.shape[0], 2), np.float32)
    weight, total = np.empty_like(w), np.empty(w.shape[0], np.float32)
    for it in range(iterations):
        # darkness in the aperture and its sum fused (`kernels.centroid_weights`); the
        # moments stay a BLAS product, so its float32 sums are as they were
        kernels.centroid_weights(w, half, reach2, _DX, _DY, _DIST2, offset, it == 0, weight, total)
        kernels.centroid_offset(weight @ _DXY, total, offset)
    return offset


def window_geometry(windows: np.ndarray, iterations: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """(offset (N, 2), radius (N,)) of the disc in each window, in its level's pixels."""
    w = np.asarray(windows, dtype=np.float32).reshape(-1, _DIM)
    if w.shape[0] == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
    radius, half = window_radius(w)
    return window_centroid(w, radius, half, iterations), radius


@dataclass(frozen=True, eq=False)
class Stage1Windows:
    """Windows that passed stage 1 (1a, and the screen unless skipped), and where they are.

    windows: (N, 12, 12) uint8 raw; level: (N,) int8; centre: (N, 2) window centres in
    pixels of their level; blob: (N,) stage-1a score; screen: (N,) stage-1b score;
    total_windows: windows a full scan examines; padded_levels: the padded pyramid; levels: the pyramid
    (`pyramid`). The levels above 0 and the padded levels may be buffers of the
    thread's workspace: valid until the next detection on the same thread.
    """

    windows: np.ndarray
    level: np.ndarray
    centre: np.ndarray
    blob: np.ndarray
    screen: np.ndarray
    total_windows: int
    padded_levels: tuple[np.ndarray, ...] = ()
    levels: tuple[np.ndarray, ...] = ()

    def __len__(self) -> int:
        return int(self.level.shape[0])

    def full_resolution_centres(self) -> np.ndarray:
        """(N, 2) window centres in full-resolution pixels."""
        return self.centre * (np.float32(2.0) ** self.level.astype(np.float32))[:, None]


def scan_levels(gray: np.ndarray, blob_thresholds: float | Sequence[float], workspace: _Workspace | None = None
                ) -> list[tuple[int, np.ndarray, int, np.ndarray, np.ndarray, np.ndarray]]:
    """Stage 1a over the pyramid: per level ``(level, padded, pad, ys, xs, blob)``: the
    level with a replicated border of `pad` pixels, the top-left corners (in it) of the
    windows at 3x3 local maxima of the blob score above the level's threshold, and
    their scores. A window at top-left (y, x) is centred at level position
    ``(x + 5.5 - pad, y + 5.5 - pad)``; every window centred on the level (-0.5 .. size
    - 0.5) is examined. With a `workspace` the padded levels are its buffers."""
    return _scan(gray, blob_thresholds, workspace)[1]


def _scan(gray: np.ndarray, blob_thresholds: float | Sequence[float], workspace: _Workspace | None
          ) -> tuple[list[np.ndarray], list[tuple[int, np.ndarray, int, np.ndarray, np.ndarray, np.ndarray]]]:
    """`scan_levels` and the (unpadded) pyramid levels."""
    thresholds = np.broadcast_to(np.asarray(blob_thresholds, np.float64), (LEVELS,))
    ws = workspace if workspace is not None else _Workspace()
    out = []
    levels = pyramid(gray, workspace)
    for level_index, level in enumerate(levels):
        padded = pad_level(level, workspace)
        ys, xs, blob = _blob_maxima(padded, float(thresholds[level_index]), ws)
        out.append((level_index, padded, _HALF, ys, xs, blob))
    return levels, out


def stage1_windows(image: np.ndarray, classifier: DiscClassifier, apply_screen: bool = True,
                   blob_thresholds: float | Sequence[float] | None = None,
                   workspace: _Workspace | None = None) -> Stage1Windows:
    """Run stage 1 over the pyramid of `image`: the windows that reach stage 2.

    ``apply_screen=False`` stops after 1a (to measure it, or to collect training
    windows); ``blob_thresholds`` overrides the classifier's 1a thresholds.
    """
    gray = as_gray(image)
    thr = classifier.blob_thresholds if blob_thresholds is None else blob_thresholds
    ws = _thread_workspace() if workspace is None else workspace
    levels, scanned = _scan(gray, thr, ws)
    padded_levels = tuple(p for _, p, _, _, _, _ in scanned)
    total = pyramid_window_count(gray.shape)
    half = np.float32((WINDOW - 1) / 2)
    found = [(lv, padded, pad, ys, xs, blob) for lv, padded, pad, ys, xs, blob in scanned if ys.size]
    if not found:
        return Stage1Windows(
            windows=np.zeros((0, WINDOW, WINDOW), np.uint8), level=np.zeros(0, np.int8),
            centre=np.zeros((0, 2), np.float32), blob=np.zeros(0, np.float32), screen=np.zeros(0, np.float32),
            total_windows=total, padded_levels=padded_levels, levels=tuple(levels),
        )
    # the windows of every level copied once, as uint8 and as the screen's float32 rows
    n = sum(ys.size for _, _, _, ys, _, _ in found)
    raw = np.empty((n, WINDOW, WINDOW), np.uint8)
    flat = ws.rows("screen_in", n, (_DIM,), np.float32)
    sums, sums_sq = ws.rows("screen_sums", n, (), np.int64), ws.rows("screen_sums_sq", n, (), np.int64)
    start = 0
    for _, padded, _, ys, xs, _ in found:
        stop = start + ys.size
        kernels.gather_windows(padded, ys, xs, raw[start:stop], flat[start:stop], sums[start:stop],
                               sums_sq[start:stop])
        start = stop
    level, xs, ys, blob = (np.concatenate(c) for c in zip(*[
        (np.full(ys.shape, lv, np.int8), xs.astype(np.float32) + (half - pad), ys.astype(np.float32) + (half - pad),
         blob) for lv, _, pad, ys, xs, blob in found]))
    screen = _screen_gathered(flat, sums, sums_sq, classifier)
    if apply_screen:
        keep = np.flatnonzero(screen > np.float32(classifier.screen_threshold))
        raw, level, xs, ys, blob, screen = raw[keep], level[keep], xs[keep], ys[keep], blob[keep], screen[keep]
    centre = np.stack([xs, ys], axis=1).astype(np.float32)
    return Stage1Windows(windows=raw, level=level, centre=centre, blob=blob.astype(np.float32), screen=screen,
                         total_windows=total, padded_levels=padded_levels, levels=tuple(levels))


# --------------------------------------------------------------------------------------
# Non-maximum suppression and the whole candidate stage
# --------------------------------------------------------------------------------------


#: Stage-1b score (a logit: 0 is even odds) above which a window claims its whole disc
#: in non-maximum suppression: the windows centred inside it (its rim, seen as small
#: blobs at finer levels) are suppressed. Below it only mutual duplicates merge, so a
#: doubtful big blob (a whole card seen at a coarse level) cannot swallow a disc.
_CLAIM_SCORE = 0.0


def _clash_pairs(rows: np.ndarray, claims: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, j), i < j (rows in priority order), where i suppresses j: j's centre
    lies inside i's disc and, unless i claims its disc (`claims`, default all), i's
    centre inside j's too. A sweep along x finds the few close pairs (every row looks
    within its own radius); comparing all pairs of a few hundred windows would cost
    more than stage 2, and a k-d tree's fixed search radius is set by the largest disc."""
    if rows.shape[0] < 2:
        empty = np.zeros(0, np.intp)
        return empty, empty
    claim = np.ones(rows.shape[0], bool) if claims is None else np.asarray(claims, bool)
    return kernels.clash_pairs(np.ascontiguousarray(rows, np.float32), claim)  # the sweep, compiled


def _greedy(n: int, first: np.ndarray, second: np.ndarray, active: np.ndarray | None = None) -> np.ndarray:
    """Greedy suppression of rows 0..n-1 (priority order) given clash pairs
    ``first[k] < second[k]``: bool mask of the kept rows among the `active` ones
    (`kernels.greedy`: in priority order, each kept row strikes out those it clashes with)."""
    return kernels.greedy(first, second, np.ones(n, bool) if active is None else active)


def suppress(candidates: np.ndarray, priority: np.ndarray | None = None) -> np.ndarray:
    """Greedy non-maximum suppression of (N, 4) ``[u, v, radius, score]`` rows.

    In order of `priority` (default: the score column), a candidate is kept unless its
    centre lies inside the disc of an already kept one (so the four discs of a card,
    2.4 diameters apart, or 1 diameter when it is tilted by 65 degrees, stay apart).
    Returns the indices of the kept rows, in priority order.
    """
    c = np.asarray(candidates, dtype=np.float32).reshape(-1, 4)
    key = c[:, 3] if priority is None else np.asarray(priority, np.float32).reshape(-1)
    order = np.argsort(-key, kind="stable")
    if order.size <= 1:
        return order
    return order[_greedy(order.size, *_clash_pairs(c[order]))]


def detect_windows(image: np.ndarray, classifier: DiscClassifier) -> tuple[np.ndarray, Stage1Windows, np.ndarray]:
    """`find_candidates` with its workings: (rows (N, 4) best score first, the stage-1
    windows, index (N,) of each row's window in them)."""
    s1 = stage1_windows(image, classifier)
    n = len(s1)
    if n == 0:
        return np.zeros((0, 4), np.float32), s1, np.zeros(0, np.intp)
    offset, radius = window_geometry(s1.windows, iterations=1)
    scale = np.float32(2.0) ** s1.level.astype(np.float32)
    rows = np.empty((n, 4), np.float32)
    rows[:, :2] = (s1.centre + offset) * scale[:, None]
    rows[:, 2] = radius * scale
    # A centre off the image (a window at a coarse level's edge) cannot be a disc the
    # later stages could use; treat it as rejected.
    height, width = s1.padded_levels[0].shape[0] - 2 * _HALF, s1.padded_levels[0].shape[1] - 2 * _HALF
    inside = (rows[:, 0] >= -0.5) & (rows[:, 0] <= width - 0.5) & (rows[:, 1] >= -0.5) & (rows[:, 1] <= height - 0.5)
    # Group the windows of each disc (neighbouring positions and levels) in order of
    # their screen score and let stage 2 judge each group's leader. A rejected leader
    # does not take its group down: the windows only it suppressed get their turn.
    order = np.argsort(-s1.screen, kind="stable")
    first, second = _clash_pairs(rows[order], s1.screen[order] > np.float32(_CLAIM_SCORE))
    keep = _greedy(n, first, second)
    score = np.full(n, -np.inf, np.float32)
    thr = np.float32(classifier.nn_threshold)
    leaders = order[keep]
    score[leaders] = nn_scores(normalise_windows(s1.windows[leaders]), classifier)
    accepted = keep & (score[order] > thr) & inside[order]
    blocked = np.bincount(second, weights=accepted[first], minlength=n) > 0
    retry = ~keep & ~blocked
    if retry.any():
        idx = order[retry]
        score[idx] = nn_scores(normalise_windows(s1.windows[idx]), classifier)
        ok = retry & (score[order] > thr) & inside[order]
        if ok.any():
            accepted |= _greedy(n, first, second, active=ok)
    kept = order[accepted]
    kept = kept[np.argsort(-score[kept], kind="stable")]
    rows = rows[kept]
    rows[:, 3] = score[kept]
    return rows, s1, kept


def find_candidates(image: np.ndarray, classifier: DiscClassifier) -> np.ndarray:
    """Disc candidates in a uint8 greyscale or BGR image (any size >= 24x24).

    Returns float32 (N, 4) rows ``[u, v, radius, score]``, best score first: the disc
    centre in full-resolution pixels (centre of the top-left pixel = (0, 0)), its radius
    (coarse, ~15%), and the stage-2 score (> nn_threshold; higher = more disc-like).

    Stage 1 over the pyramid; stage 2 scores every survivor; centre and radius come from
    each accepted window (`window_geometry`); of the accepted windows of one disc
    (neighbouring positions and levels) non-maximum suppression keeps the one with the
    best stage-1b score (it tells how well a window is centred on its disc better than
    the 1-NN distance does).
    """
    return detect_windows(image, classifier)[0]


# --------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------




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
    extra = np.zeros((0, _DIM), np.float32)
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
