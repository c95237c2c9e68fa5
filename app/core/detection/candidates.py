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

numpy/OpenCV/SciPy, and numba kernels (`_candidates_kernels`: the rest of stage 1a after
the morphology, the window copies, the screen's correction, the disc's geometry in its
window, the suppression sweep) where fused loops beat chains of whole-array calls, with
identical results. The learned parameters are fitted by `app.learning.classifier`. No
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

from app.core.detection import _candidates_kernels as kernels
from app.core.detection._frame import as_gray

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
    """Trained parameters of both learned stages (`app.learning.classifier` fits them),
    stored read-only.

    Parameters
    ----------
    blob_thresholds : ndarray, shape (LEVELS,)
        Stage 1a: the smallest dark-blob score of a local maximum at each level (level 0,
        with ~2/3 of all windows and only small, sharp discs, can afford a stricter one);
        one number stands for every level.
    screen_w1 : ndarray, shape (144, H)
    screen_b1 : ndarray, shape (H,)
    screen_w2 : ndarray, shape (H,)
    screen_b2 : float
    screen_threshold : float
        Stage 1b, a one-hidden-layer perceptron on the normalised window x, passes
        ``w2 . relu(x W1 + b1) + b2 > screen_threshold``.
    prototypes : ndarray, shape (M, 144)
        Condensed training windows, normalised (zero mean, unit norm).
    labels : ndarray, shape (M,)
        1 for a disc prototype, 0 for a non-disc one (at least one of each).
    nn_threshold : float
        Stage 2 accepts a window when (distance to the nearest negative prototype) -
        (distance to the nearest positive) > nn_threshold; 0 is the plain 1-NN rule.
    stats : dict
        Training statistics (JSON-able).

    Raises
    ------
    ValueError
        Arrays of the wrong shape, non-finite values, or labels other than 0 and 1.
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
        # Column sums of W1 and W1 with a column of ones, for `_screen_gathered`; and the
        # prototypes split by class once (stage 2 needs the nearest of each class).
        object.__setattr__(self, "_w1_sum", w1.sum(axis=0))
        w1_ext = np.ascontiguousarray(np.concatenate([w1, np.ones((_DIM, 1), np.float32)], 1))
        object.__setattr__(self, "_w1_ext", w1_ext)
        object.__setattr__(self, "_pos", np.ascontiguousarray(protos[labels == 1].T))
        object.__setattr__(self, "_neg", np.ascontiguousarray(protos[labels == 0].T))

    def replace(self, **changes: Any) -> DiscClassifier:
        """A copy with some fields changed (thresholds, stats).

        Parameters
        ----------
        **changes
            Fields and their new values.

        Returns
        -------
        DiscClassifier
            The copy, checked like a new classifier.
        """
        return dataclasses.replace(self, **changes)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Every parameter as a named array (scalars as 0-d arrays), for .npy storage.

        Returns
        -------
        dict of str to ndarray
            The parameters, with the storage format version and the window size.
        """
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
        """The classifier stored by `to_arrays`.

        Parameters
        ----------
        arrays : dict of str to ndarray
            Arrays as `to_arrays` names them.
        stats : dict, optional
            Training statistics.

        Returns
        -------
        DiscClassifier
            The classifier; ValueError on a missing or malformed array, another format
            version or another window size.
        """
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
    """The classifier shipped with the package.

    Returns
    -------
    DiscClassifier
        The parameters in ``app/data/default_classifier.npz`` (made by
        ``scripts/train_default_classifier.py``), with their training statistics.
    """
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


def _scannable(image: np.ndarray) -> np.ndarray:
    """The image as the candidate stage scans it: `as_gray`, and at least `MIN_SIDE`
    pixels on each side (ValueError otherwise)."""
    gray = as_gray(image)
    if min(gray.shape) < MIN_SIDE:
        raise ValueError(f"image must be at least {MIN_SIDE}x{MIN_SIDE} pixels, got {gray.shape[1]}x{gray.shape[0]}")
    return gray


def pyramid(gray: np.ndarray, workspace: _Workspace | None = None) -> list[np.ndarray]:
    """The image pyramid the windows are scanned on.

    Parameters
    ----------
    gray : ndarray
        uint8 greyscale image (level 0).
    workspace : _Workspace, optional
        Buffers for the levels above 0 (valid until the workspace is next used for an
        image of this size).

    Returns
    -------
    list of ndarray
        Up to `LEVELS` uint8 levels, each halved by ``cv2.pyrDown``; levels with a side
        shorter than half a window are left out (nothing to find there).
    """
    levels = [gray]
    while len(levels) < LEVELS:
        h, w = levels[-1].shape
        if min((h + 1) // 2, (w + 1) // 2) < _HALF:
            break
        dst = None if workspace is None else workspace.get(f"pyr{len(levels)}", ((h + 1) // 2, (w + 1) // 2), np.uint8)
        levels.append(cv2.pyrDown(levels[-1], dst=dst))
    return levels


def pyramid_window_count(shape: tuple[int, int]) -> int:
    """How many windows a full scan examines: one per pixel position of every level.

    Parameters
    ----------
    shape : tuple of int
        The image's (height, width).

    Returns
    -------
    int
        The window count over the pyramid.
    """
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
    """A level with a replicated border of half a window, so that windows centred on any
    pixel of the level (including at its very edge) exist.

    Parameters
    ----------
    level : ndarray
        uint8 pyramid level (h, w).
    workspace : _Workspace, optional
        A buffer for the result.

    Returns
    -------
    ndarray
        uint8 (h + 12, w + 12).
    """
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
    """Stage-1a score of every 12x12 window lying wholly inside a padded level.

    Parameters
    ----------
    padded : ndarray
        uint8 level with a replicated border (`pad_level`), shape (h, w).
    workspace : _Workspace, optional
        Buffers for every intermediate and the result (valid until the workspace is
        next used for an image of this size); without, fresh arrays.

    Returns
    -------
    ndarray
        float32 (h - 11, w - 11): entry (y, x) scores the window
        ``padded[y : y + 12, x : x + 12]``. Unitless, about -1..1; a clean disc of the
        level's size range scores 0.4-0.8.
    """
    ws = workspace if workspace is not None else _Workspace()
    h, w = padded.shape
    integral, dil, ero = _tophat_integral(padded, ws)
    # (centre mean - window mean) / (range + eps) from the window sums, in one compiled
    # pass with the arithmetic of the OpenCV calls of its reference
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
    """The 3x3 local maxima of a score image above a threshold.

    Parameters
    ----------
    score : ndarray
        float32 scores (h, w).
    threshold : float
        Maxima must lie strictly above it.
    workspace : _Workspace, optional
        Scratch buffers.

    Returns
    -------
    ys, xs : ndarray of intp
        Rows and columns of the maxima, in row-major order.
    """
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
    """Dense stage-1a score of every window of one pyramid level.

    Parameters
    ----------
    level : ndarray
        uint8 level (H, W).

    Returns
    -------
    ndarray
        float32 (H + 1, W + 1), entry (y, x) for the window centred at level position
        (x - 0.5, y - 0.5).
    """
    return blob_scores(pad_level(np.ascontiguousarray(level, dtype=np.uint8)))


def stage1_mask(level: np.ndarray, threshold: float) -> np.ndarray:
    """The windows of one level that stage 1a passes.

    Parameters
    ----------
    level : ndarray
        uint8 level (H, W).
    threshold : float
        The level's blob threshold.

    Returns
    -------
    ndarray of bool
        (H + 1, W + 1), indexed as `stage1_scores`: the 3x3 local maxima of its scores
        above `threshold`.
    """
    score = stage1_scores(level)
    mask = np.zeros(score.shape, bool)
    ys, xs = local_maxima(score, threshold)
    mask[ys, xs] = True
    return mask


# --------------------------------------------------------------------------------------
# Windows
# --------------------------------------------------------------------------------------


def extract_windows(padded: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Copies of windows of a padded level.

    Parameters
    ----------
    padded : ndarray
        uint8 padded level (`pad_level`).
    ys, xs : ndarray of int
        Top-left corners of the windows in it.

    Returns
    -------
    ndarray
        uint8 (N, 12, 12).
    """
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
    """Windows normalised for the screen and stage 2: each minus its mean, divided by its
    norm (unit vectors, so squared distances are ``2 - 2 a.b``). Invariant to gain and
    offset; a flat window becomes ~0 rather than NaN.

    Parameters
    ----------
    windows : ndarray, shape (N, 12, 12) or (N, 144)
        Raw windows.

    Returns
    -------
    ndarray
        float32 (N, 144).
    """
    w = np.asarray(windows, dtype=np.float32).reshape(-1, _DIM)
    w = w - w.mean(axis=1, keepdims=True)
    norm = np.sqrt(np.einsum("ij,ij->i", w, w))
    w /= np.maximum(norm, np.float32(_NORM_EPS))[:, None]
    return w


def screen_scores(normalised: np.ndarray, classifier: DiscClassifier) -> np.ndarray:
    """Stage-1b score of normalised windows: ``w2 . relu(x W1 + b1) + b2``.

    Parameters
    ----------
    normalised : ndarray, shape (N, 144)
        Windows from `normalise_windows`.
    classifier : DiscClassifier
        Its screen's weights.

    Returns
    -------
    ndarray
        float32 (N,); the screen passes scores above ``classifier.screen_threshold``.
    """
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
    # (W1 extended by a column of ones, whose product column goes unused: BLAS's float32
    # sums depend on the shape of the product, and this shape gives the screen scores the
    # tests' reference computes)
    product = flat @ classifier._w1_ext  # type: ignore[attr-defined]
    hidden = product[:, :-1]
    kernels.screen_hidden(hidden, sums, sums_sq, classifier._w1_sum,  # type: ignore[attr-defined]
                          classifier.screen_b1, np.float32(_NORM_EPS))
    return hidden @ classifier.screen_w2 + np.float32(classifier.screen_b2)


def nn_scores(normalised: np.ndarray, classifier: DiscClassifier) -> np.ndarray:
    """Stage-2 score of normalised windows: the distance to the nearest negative prototype
    minus the distance to the nearest positive one.

    Parameters
    ----------
    normalised : ndarray, shape (N, 144)
        Windows from `normalise_windows`.
    classifier : DiscClassifier
        Its prototypes.

    Returns
    -------
    ndarray
        float32 (N,); > 0: the nearest prototype is a disc; stage 2 accepts scores above
        ``classifier.nn_threshold``.
    """
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
    """Stage 2 alone on raw windows: `nn_scores` of the normalised windows.

    Parameters
    ----------
    windows : ndarray, shape (N, 12, 12)
        Raw windows; ValueError for another shape.
    classifier : DiscClassifier
        Its prototypes.

    Returns
    -------
    ndarray
        float32 (N,) stage-2 scores.
    """
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
    """The disc's radius in each window, from its radial profile.

    The profile (mean grey level in 1-px rings about the window centre) is followed out
    from the darkest of the two inner rings until it crosses halfway to the brightest ring
    beyond; the crossing is interpolated and scaled by `_RADIUS_GAIN`.

    Parameters
    ----------
    windows : ndarray, shape (N, 12, 12) or (N, 144)
        Raw windows.

    Returns
    -------
    radius : ndarray
        float32 (N,) disc radii in pixels of the windows' level.
    half : ndarray
        float32 (N,) grey level halfway between the disc and its surround.
    """
    w = np.asarray(windows, dtype=np.float32).reshape(-1, _DIM)
    prof = w @ _RINGS  # (N, 6): a BLAS product (its float32 sums are part of the result)
    # the rest per window in one compiled loop (`kernels.ring_radius`: the same float32
    # steps as its numpy reference, without ~15 calls' overhead)
    radius, half = np.empty(w.shape[0], np.float32), np.empty(w.shape[0], np.float32)
    kernels.ring_radius(prof, _RING_MID, np.float32(_RADIUS_GAIN), radius, half)
    return radius, half


def window_centroid(windows: np.ndarray, radius: np.ndarray, half: np.ndarray, iterations: int = 2) -> np.ndarray:
    """Sub-pixel offset of the dark disc from each window's centre: the centroid of darkness
    (`half` minus grey level, clipped at 0) inside a circular aperture of the disc radius
    plus a pixel, re-centred on the previous estimate `iterations - 1` times, so
    neighbours in the window barely pull.

    Parameters
    ----------
    windows : ndarray, shape (N, 12, 12) or (N, 144)
        Raw windows.
    radius, half : ndarray, shape (N,)
        From `window_radius`.
    iterations : int
        Centroid passes.

    Returns
    -------
    ndarray
        float32 (N, 2) offsets (x, y) in pixels of the windows' level, each within 2 px.
    """
    w = np.ascontiguousarray(windows, dtype=np.float32).reshape(-1, _DIM)
    half = np.ascontiguousarray(half, np.float32)
    reach2 = (np.asarray(radius, np.float32) + np.float32(1.0)) ** 2
    offset = np.zeros((w.shape[0], 2), np.float32)
    weight, total = np.empty_like(w), np.empty(w.shape[0], np.float32)
    for it in range(iterations):
        # darkness in the aperture and its sum fused (`kernels.centroid_weights`); the
        # moments stay a BLAS product (its float32 sums are part of the result)
        kernels.centroid_weights(w, half, reach2, _DX, _DY, _DIST2, offset, it == 0, weight, total)
        kernels.centroid_offset(weight @ _DXY, total, offset)
    return offset


def window_geometry(windows: np.ndarray, iterations: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Where the disc is in each window, and how big.

    Parameters
    ----------
    windows : ndarray, shape (N, 12, 12) or (N, 144)
        Raw windows.
    iterations : int
        Centroid passes (`window_centroid`).

    Returns
    -------
    offset : ndarray
        float32 (N, 2) from the window centre, in pixels of the windows' level.
    radius : ndarray
        float32 (N,) in pixels of the windows' level.
    """
    w = np.asarray(windows, dtype=np.float32).reshape(-1, _DIM)
    if w.shape[0] == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
    radius, half = window_radius(w)
    return window_centroid(w, radius, half, iterations), radius


@dataclass(frozen=True, eq=False)
class Stage1Windows:
    """Windows that passed stage 1 (1a, and the screen unless skipped), and where they are.

    The levels above 0 and the padded levels may be buffers of the thread's workspace:
    valid until the next detection on the same thread.

    Parameters
    ----------
    windows : ndarray
        uint8 (N, 12, 12) raw windows.
    level : ndarray
        int8 (N,) pyramid level of each.
    centre : ndarray
        float32 (N, 2) window centres in pixels of their level.
    blob : ndarray
        float32 (N,) stage-1a scores.
    screen : ndarray
        float32 (N,) stage-1b scores.
    total_windows : int
        Windows a full scan examines.
    padded_levels : tuple of ndarray
        The padded pyramid.
    levels : tuple of ndarray
        The pyramid (`pyramid`).
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
        """The window centres in full-resolution pixels.

        Returns
        -------
        ndarray
            float32 (N, 2).
        """
        return self.centre * (np.float32(2.0) ** self.level.astype(np.float32))[:, None]


def scan_levels(gray: np.ndarray, blob_thresholds: float | Sequence[float], workspace: _Workspace | None = None
                ) -> list[tuple[int, np.ndarray, int, np.ndarray, np.ndarray, np.ndarray]]:
    """Stage 1a over the pyramid: the windows at 3x3 local maxima of the blob score above
    each level's threshold. Every window centred on a level (-0.5 .. size - 0.5) is
    examined.

    Parameters
    ----------
    gray : ndarray
        uint8 greyscale image.
    blob_thresholds : float or sequence of float
        Per level (one number for all).
    workspace : _Workspace, optional
        Buffers for the padded levels.

    Returns
    -------
    list of tuple
        Per level ``(level, padded, pad, ys, xs, blob)``: the level with a replicated
        border of `pad` pixels, the top-left corners (in it) of the windows, and their
        scores. A window at top-left (y, x) is centred at level position
        ``(x + 5.5 - pad, y + 5.5 - pad)``.
    """
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
    """Stage 1 over the pyramid of an image: the windows that reach stage 2.

    Parameters
    ----------
    image : ndarray
        uint8 greyscale, BGR or BGRA (`as_gray`), at least `MIN_SIDE` pixels a side.
    classifier : DiscClassifier
        Its blob thresholds and screen.
    apply_screen : bool
        False stops after 1a (to measure it, or to collect training windows); the screen
        scores are reported either way.
    blob_thresholds : float or sequence of float, optional
        Overrides the classifier's 1a thresholds.
    workspace : _Workspace, optional
        Buffers (default: the thread's own).

    Returns
    -------
    Stage1Windows
        The windows, their levels, centres and scores.
    """
    gray = _scannable(image)
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
    """Greedy non-maximum suppression of candidate rows.

    In order of `priority`, a candidate is kept unless its centre lies inside the disc of
    an already kept one (so the four discs of a card, 2.4 diameters apart, or 1 diameter
    when it is tilted by 65 degrees, stay apart).

    Parameters
    ----------
    candidates : ndarray, shape (N, 4)
        Rows ``[u, v, radius, score]``.
    priority : ndarray, shape (N,), optional
        Default: the score column.

    Returns
    -------
    ndarray of intp
        Indices of the kept rows, in priority order.
    """
    c = np.asarray(candidates, dtype=np.float32).reshape(-1, 4)
    key = c[:, 3] if priority is None else np.asarray(priority, np.float32).reshape(-1)
    order = np.argsort(-key, kind="stable")
    if order.size <= 1:
        return order
    return order[_greedy(order.size, *_clash_pairs(c[order]))]


#: A window at least this many pyramid levels coarser than the windows inside it may
#: hold a whole small card rather than one disc (`_claimed_discs`); and at least this
#: many of the finer windows must pass stage 2 for them to be kept beside it (three
#: discs of a card: completion finds the fourth).
CARD_CLAIM_LEVELS = 2
CARD_CLAIM_MIN_DISCS = 3


def _claimed_discs(s1: Stage1Windows, classifier: DiscClassifier, order: np.ndarray, first: np.ndarray,
                   second: np.ndarray, accepted: np.ndarray, score: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """The windows of a small card's discs that a coarse window claiming the whole card
    suppressed, kept beside it (bool over the priority order, like `accepted`); the
    stage-2 scores of the windows it judges are written into `score`.

    Two levels up, a card with 4 px discs is a 4 px blob, and in bright light, its white
    clipped into a white wall, nothing around it tells it from a disc: its window passes
    both stages and claims the card's four discs (bench_detect, bright: 3 cards in a
    one-off count). So the finer windows such a claimer suppressed are
    judged by stage 2 after all, and kept, beside it, when at least
    `CARD_CLAIM_MIN_DISCS` of them pass and clash with no other kept window. A large
    disc's rim seen at finer levels seldom gives three windows stage 2 accepts."""
    extra = np.zeros(order.size, bool)
    level = s1.level[order].astype(np.int16)
    coarse = accepted[first] & (level[first] - level[second] >= CARD_CLAIM_LEVELS)
    if not coarse.any():
        return extra
    claimers, fine = first[coarse], second[coarse]
    unscored = fine[~np.isfinite(score[order[fine]])]
    if unscored.size:
        idx = order[np.unique(unscored)]
        score[idx] = nn_scores(normalise_windows(s1.windows[idx]), classifier)
    passed = (score[order[fine]] > np.float32(classifier.nn_threshold)) & inside[fine] & ~accepted[fine]
    for claimer in np.unique(claimers[passed]):
        mine = np.zeros(order.size, bool)
        mine[fine[passed & (claimers == claimer)]] = True
        # among them, the usual suppression (a disc's windows at neighbouring positions
        # and levels are one disc); the claimer strikes none of them, every other window
        # kept so far does
        kept = _greedy(order.size, first, second, active=mine)
        kept &= ~(np.bincount(second, weights=(accepted & ~_one(order.size, claimer))[first],
                              minlength=order.size) > 0)
        if kept.sum() >= CARD_CLAIM_MIN_DISCS:
            extra |= kept
    return extra


def _one(n: int, i: int) -> np.ndarray:
    mask = np.zeros(n, bool)
    mask[i] = True
    return mask


def detect_windows(image: np.ndarray, classifier: DiscClassifier) -> tuple[np.ndarray, Stage1Windows, np.ndarray]:
    """`find_candidates` with its workings.

    Parameters
    ----------
    image : ndarray
        uint8 greyscale, BGR or BGRA (`as_gray`), at least `MIN_SIDE` pixels a side.
    classifier : DiscClassifier
        The classifier.

    Returns
    -------
    rows : ndarray
        float32 (N, 4) candidates ``[u, v, radius, score]``, best score first.
    windows : Stage1Windows
        The stage-1 windows.
    index : ndarray of intp
        (N,) each row's window in `windows`.
    """
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
    accepted |= _claimed_discs(s1, classifier, order, first, second, accepted, score, inside[order])
    kept = order[accepted]
    kept = kept[np.argsort(-score[kept], kind="stable")]
    rows = rows[kept]
    rows[:, 3] = score[kept]
    return rows, s1, kept


def find_candidates(image: np.ndarray, classifier: DiscClassifier) -> np.ndarray:
    """Disc candidates in an image.

    Stage 1 over the pyramid; the windows of one disc (neighbouring positions and levels)
    are grouped by non-maximum suppression in order of their screen score (it tells how
    well a window is centred on its disc better than the 1-NN distance does), and stage 2
    judges each group's leader; a rejected leader does not take its group down (the
    windows only it suppressed get their turn). Centre and radius come from each accepted
    window (`window_geometry`).

    Parameters
    ----------
    image : ndarray
        uint8 greyscale or BGR, at least `MIN_SIDE` x `MIN_SIDE`; ValueError otherwise.
    classifier : DiscClassifier
        The classifier.

    Returns
    -------
    ndarray
        float32 (N, 4) rows ``[u, v, radius, score]``, best score first: the disc centre
        in full-resolution pixels (centre of the top-left pixel = (0, 0)), its radius
        (coarse, ~15%), and the stage-2 score (> ``classifier.nn_threshold``; higher =
        more disc-like).
    """
    return detect_windows(image, classifier)[0]
