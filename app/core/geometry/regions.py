"""Regions of interest for tracking: where the map's targets will appear in the next frame.

A tracking client streams a video, so the previous frame's pose (and the one before it:
a velocity) predicts every mapped target's image position in the next frame. Detecting
only in boxes around those predictions is much cheaper than scanning the whole frame
(the detector's cost grows with the pixels it examines).

Boxes are snapped outward to multiples of `RegionParams.align` pixels (8): the
detector's 4-level pyramid halves the image three times, and a crop whose corner is a
multiple of 8 full-resolution pixels is a whole number of pixels at every level, so its
pyramid samples are the full frame's (away from the crop's own border, as
tests/core/geometry/test_regions.py checks), and a target well inside a crop is found with the same disc
centres as in the full frame.

numpy, cv2.Rodrigues and the Camera's own projection: no web or storage imports.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from app.core.geometry.camera import Camera, Pose

__all__ = [
    "MapTargets",
    "PredictedTarget",
    "Region",
    "RegionParams",
    "decode_reduction",
    "disc_diameters",
    "extrapolate",
    "merge_regions",
    "plan_regions",
    "predict_in_view",
    "predict_regions",
    "predict_targets",
    "reduce_regions",
]

#: Card corners from the disc centres: discs sit at 0.2 / 0.8 of the card side, so the
#: card's corners are 0.5 / 0.3 = 5/3 as far from the card centre as its discs.
_CORNER_SCALE = 5.0 / 3.0
#: A disc's diameter over the distance between neighbouring disc centres: radius 0.125
#: of the card side, centres 0.6 of it apart.
_DISC_PER_SIDE = 0.25 / 0.6


@dataclass(frozen=True)
class RegionParams:
    """How generous the boxes are, and when a region scan is not worth it.

    Margins are pixels per frame of prediction (the gap in ``seq`` since the last pose):
    ``motion_px`` covers pose noise and rotation jitter (it moves every card alike);
    ``motion_card`` (times the card's apparent size) covers an unpredicted translation,
    which moves near cards, the big ones, more than far ones; ``motion_speed`` (times how
    far the velocity moves the target) covers a changing velocity: the faster the
    camera moves, the worse a constant-velocity guess. Without a velocity (one pose
    only) the ``still_*`` margins hold, which must cover a whole frame's motion.

    Attributes
    ----------
    motion_px : float
        Margin per frame ahead with a velocity, pixels.
    motion_card : float
        Margin per frame ahead with a velocity, times the card's apparent size.
    motion_speed : float
        Margin times how far the velocity moves the target (pixels per pixel).
    still_px, still_card : float
        As `motion_px` and `motion_card`, without a velocity.
    border_px : float
        Extra pixels beyond the card outline.
    align : int
        Box edges snap outward to multiples of this many pixels (a multiple of 8).
    min_side : int
        Smallest crop side, pixels.
    max_fraction : float
        Crops covering more of the frame than this: scan the whole frame.
    crop_cost_px : int
        Two boxes merge when together they cost at most this many more pixels.
    near_m : float
        Cards with a disc or corner nearer than this (metres, along the optical axis)
        are not predicted.
    max_steps : int
        Predictions further ahead than this many frames are not trusted.

    Raises
    ------
    ValueError
        If `align` is not a positive multiple of 8.
    """

    motion_px: float = 8.0
    motion_card: float = 0.2
    motion_speed: float = 0.2
    still_px: float = 32.0
    still_card: float = 1.0
    #: Extra pixels beyond the card outline (the detector drops a disc that is not
    #: wholly inside its crop; the card reaches 1.6 disc radii past its disc centres).
    border_px: float = 4.0
    #: Box edges snap outward to multiples of this (a multiple of 8, see the module doc;
    #: 16 would cost ~12% more pixels on the bench walk for nothing).
    align: int = 8
    #: Smallest crop side (the detector refuses crops under 24 px).
    min_side: int = 32
    #: A union of boxes above this fraction of the frame: scan the whole frame instead
    #: (the crops' scan would cost about as much, and a full scan finds everything).
    max_fraction: float = 0.6
    #: Two boxes merge when their common bounding box costs less than this many pixels
    #: more than the two apart: fewer crop edges (a disc cut by one is dropped) and
    #: less packing waste in the detector's mosaic.
    crop_cost_px: int = 48 * 48
    #: Cameras closer than this to a disc (metres) do not predict it.
    near_m: float = 0.05
    #: Predictions further ahead than this many frames are not trusted.
    max_steps: int = 8

    def __post_init__(self) -> None:
        if self.align <= 0 or self.align % 8:
            raise ValueError(f"align must be a positive multiple of 8, got {self.align}")


@dataclass(frozen=True, eq=False)
class MapTargets:
    """A map's targets stacked for fast projection (built once per map).

    Attributes
    ----------
    ids : (T,) ndarray of int
        Target ids, ascending.
    discs : (T, 4, 3) ndarray
        Disc centres in map coordinates, metres, in disc order (0 top-left, 1 top-right,
        2 bottom-right, 3 bottom-left as printed).
    corners : (T, 4, 3) ndarray
        Card corners extrapolated from the discs.
    normals : (T, 3) ndarray
        Unit normals out of the printed faces.
    centres : (T, 3) ndarray
        Card centres (mean of the discs).
    points : (T * 8, 3) ndarray
        Each target's discs, then its corners.
    """

    ids: np.ndarray  # (T,) int
    discs: np.ndarray  # (T, 4, 3) metres
    corners: np.ndarray  # (T, 4, 3) card corners extrapolated from the discs
    normals: np.ndarray  # (T, 3) unit, out of the printed face
    centres: np.ndarray  # (T, 3)
    points: np.ndarray  # (T * 8, 3): each target's discs, then its corners

    @classmethod
    def from_discs(cls, discs: Mapping[int, np.ndarray]) -> MapTargets:
        """Stack a map's targets.

        Parameters
        ----------
        discs : mapping of int to (4, 3) array_like
            Target id to its disc centres in map coordinates (metres), in disc order.

        Returns
        -------
        MapTargets
        """
        ids = np.array(sorted(discs), dtype=np.int64)
        d = np.array([np.asarray(discs[int(i)], np.float64).reshape(4, 3) for i in ids]).reshape(-1, 4, 3)
        centre = d.mean(axis=1, keepdims=True)
        corners = centre + _CORNER_SCALE * (d - centre)
        # Discs in layout order (top-left, top-right, bottom-right, bottom-left): the
        # printed face's normal is (bottom-left - top-left) x (top-right - top-left).
        n = np.cross(d[:, 3] - d[:, 0], d[:, 1] - d[:, 0]) if len(ids) else np.zeros((0, 3))
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        points = np.concatenate([d, corners], axis=1).reshape(-1, 3)
        return cls(ids=ids, discs=d, corners=corners, normals=n, centres=centre.reshape(-1, 3), points=points)

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass(frozen=True, eq=False)
class PredictedTarget:
    """Where a map target is expected in the next frame.

    Attributes
    ----------
    id : int
        The target's id.
    discs_px : (4, 2) ndarray
        Predicted disc centres, pixels.
    box : tuple of float
        (x0, y0, x1, y1), the padded box around the card in pixels, not yet snapped or
        clipped to the image.
    """

    id: int
    discs_px: np.ndarray
    box: tuple[float, float, float, float]  # x0, y0, x1, y1 (not yet snapped or clipped)


@dataclass(frozen=True)
class Region:
    """A crop of the frame and the map targets predicted in it.

    Attributes
    ----------
    x0, y0 : int
        First column and row of the crop, full-frame pixels.
    x1, y1 : int
        One past the last column and row.
    ids : tuple of int
        The map targets predicted in the crop.
    """

    x0: int
    y0: int
    x1: int
    y1: int
    ids: tuple[int, ...] = ()

    @property
    def width(self) -> int:
        """Columns in the crop."""
        return self.x1 - self.x0

    @property
    def height(self) -> int:
        """Rows in the crop."""
        return self.y1 - self.y0

    @property
    def area(self) -> int:
        """Pixels in the crop."""
        return self.width * self.height

    def contains(self, uv: np.ndarray) -> bool:
        """Whether all points lie inside the crop.

        Parameters
        ----------
        uv : (N, 2) array_like
            Full-frame pixel coordinates (pixel centres at integers, so the crop's edges
            are at x0 - 0.5 and x1 - 0.5).

        Returns
        -------
        bool
        """
        p = np.asarray(uv, np.float64).reshape(-1, 2)
        return bool(((p[:, 0] >= self.x0 - 0.5) & (p[:, 0] <= self.x1 - 0.5)
                     & (p[:, 1] >= self.y0 - 0.5) & (p[:, 1] <= self.y1 - 0.5)).all())


# --------------------------------------------------------------------------------------
# Motion
# --------------------------------------------------------------------------------------


def extrapolate(before: Pose, last: Pose, steps: float) -> Pose:
    """Constant-velocity guess of a later pose.

    Parameters
    ----------
    before, last : Pose
        Two poses (map to camera), `before` the earlier.
    steps : float
        How many times the motion from `before` to `last` is applied again after `last`
        (fractions allowed: the rotation is scaled on its axis).

    Returns
    -------
    Pose
        The extrapolated pose.
    """
    # delta = last o before^-1 (camera(before) -> camera(last)), in plain arrays.
    dR = last.R @ before.R.T
    dt = last.t - dR @ before.t
    rvec, _ = cv2.Rodrigues(dR)
    # t of delta^s for a screw motion is close to s * t when the rotation per frame is
    # small (a hand-held camera turns a few degrees a frame at most); exact for s = 1.
    sR = dR if steps == 1.0 else cv2.Rodrigues(rvec * steps)[0]
    st = dt if steps == 1.0 else dt * steps
    return Pose(sR @ last.R, sR @ last.t + st)


# --------------------------------------------------------------------------------------
# Prediction
# --------------------------------------------------------------------------------------


#: Normalised field (Camera.field_radius) in which projections are trusted, as a
#: multiple of the image corners' radius: beyond 1.25x (and short of the fold) a point
#: is simply off the image; its box is built at the field's edge instead.
_FIELD_MARGIN = 1.25


def _project(camera: Camera, cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3), z > 0 -> (pixels (N, 2), beyond the lens's valid
    field (N,)). Points beyond are moved in, along their direction, to the edge of the
    valid field, which lies outside the image: a box reaching them reaches the image's
    edge there, not some place the distortion polynomial folds them back to."""
    limit = camera.field_radius(_FIELD_MARGIN)
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    r = np.sqrt(x * x + y * y)
    far = r > limit
    if far.any():
        cam = cam.copy()
        cam[far, :2] *= (limit / r[far])[:, None]
    return camera.project(cam), far


def predict_targets(targets: MapTargets, camera: Camera, pose: Pose, previous: Pose | None = None,
                    steps: float = 1.0, params: RegionParams | None = None) -> list[PredictedTarget]:
    """Every map target in front of the camera, facing it, whose padded box meets the image.

    Parameters
    ----------
    targets : MapTargets
    camera : Camera
    pose : Pose
        The predicted pose (map to camera) of the frame to scan.
    previous : Pose or None, optional
        The pose `pose` was extrapolated from; None: no velocity, `pose` is simply the
        last one, and the ``still_*`` margins apply.
    steps : float, optional
        Frames since the last pose.
    params : RegionParams, optional

    Returns
    -------
    list of PredictedTarget
        In ascending id order.
    """
    p = params or RegionParams()
    n = len(targets)
    if n == 0:
        return []
    cam = (targets.points @ pose.R.T + pose.t).reshape(n, 8, 3)  # discs, then card corners
    ahead = (cam[:, :, 2] > p.near_m).all(axis=1)
    facing = np.einsum("ij,ij->i", targets.normals, pose.position - targets.centres) > 0
    if previous is not None:
        # Where the discs were (in the same camera): how far the velocity moves them.
        cam0 = (targets.discs @ previous.R.T + previous.t).reshape(n, 4, 3)
        ahead &= (cam0[:, :, 2] > p.near_m).all(axis=1)
    keep = np.flatnonzero(ahead & facing)
    if keep.size == 0:
        return []
    both = cam[keep] if previous is None else np.concatenate([cam[keep], cam0[keep]], axis=1)
    uv, far = _project(camera, both.reshape(-1, 3))
    uv, far = uv.reshape(keep.size, -1, 2), far.reshape(keep.size, -1)
    # A card whose discs are all beyond the lens's field is off the image.
    near = ~far[:, :4].all(axis=1)
    keep, uv = keep[near], uv[near]
    if keep.size == 0:
        return []
    discs_px, corners_px = uv[:, :4], uv[:, 4:8]
    size = np.ptp(discs_px, axis=1).max(axis=1)  # the disc square's apparent size
    steps = max(float(steps), 1.0)
    if previous is not None:
        shift = np.minimum(np.abs(uv[:, 8:] - discs_px).max(axis=(1, 2)), camera.width + camera.height)
        margin = (p.motion_px + p.motion_card * size) * steps + p.motion_speed * shift
    else:
        margin = (p.still_px + p.still_card * size) * steps
    pad = margin + p.border_px
    lo = corners_px.min(axis=1) - pad[:, None]
    hi = corners_px.max(axis=1) + pad[:, None]
    w, h = camera.width, camera.height
    meets = (hi[:, 0] >= 0) & (lo[:, 0] <= w - 1) & (hi[:, 1] >= 0) & (lo[:, 1] <= h - 1)
    meets &= np.isfinite(lo).all(axis=1) & np.isfinite(hi).all(axis=1)
    return [PredictedTarget(int(targets.ids[keep[k]]), discs_px[k], (float(lo[k, 0]), float(lo[k, 1]),
                                                                      float(hi[k, 0]), float(hi[k, 1])))
            for k in np.flatnonzero(meets)]


# --------------------------------------------------------------------------------------
# Boxes to crops
# --------------------------------------------------------------------------------------


def _snap(box: tuple[float, float, float, float], width: int, height: int, p: RegionParams
          ) -> tuple[int, int, int, int]:
    """Outward to multiples of `align` (the last pixel's right edge is x1 - 0.5 + 0.5),
    clipped to the image, grown to `min_side` where the image allows."""
    a = p.align
    x0 = max(0, math.floor((box[0] + 0.5) / a) * a)
    y0 = max(0, math.floor((box[1] + 0.5) / a) * a)
    x1 = min(width, math.ceil((box[2] + 0.5) / a) * a)
    y1 = min(height, math.ceil((box[3] + 0.5) / a) * a)
    if x1 - x0 < p.min_side:
        x1 = min(width, x0 + p.min_side)
        x0 = max(0, min(x0, (x1 - p.min_side) // 8 * 8))
    if y1 - y0 < p.min_side:
        y1 = min(height, y0 + p.min_side)
        y0 = max(0, min(y0, (y1 - p.min_side) // 8 * 8))
    return x0, y0, x1, y1


def merge_regions(regions: list[Region], crop_cost_px: int = 0) -> list[Region]:
    """Merge crops until no two overlap, touch, or are cheaper together.

    A target then lies in one crop only (no duplicate detections, no target cut by
    another crop's edge).

    Parameters
    ----------
    regions : list of Region
    crop_cost_px : int, optional
        Two crops also merge when their common bounding box has at most this many pixels
        more than the two apart.

    Returns
    -------
    list of Region
        Sorted by (y0, x0); each carries the ids of the crops merged into it.
    """
    # Plain lists: this runs every frame, on a handful of boxes.
    boxes = [[r.x0, r.y0, r.x1, r.y1, set(r.ids)] for r in regions]
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for i in range(len(boxes)):
            a = boxes[i]
            area_a = (a[2] - a[0]) * (a[3] - a[1])
            for j in range(i + 1, len(boxes)):
                b = boxes[j]
                touch = a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]
                x0, y0, x1, y1 = min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])
                if touch or (x1 - x0) * (y1 - y0) <= area_a + (b[2] - b[0]) * (b[3] - b[1]) + crop_cost_px:
                    boxes[i] = [x0, y0, x1, y1, a[4] | b[4]]
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return sorted((Region(b[0], b[1], b[2], b[3], tuple(sorted(b[4]))) for b in boxes), key=lambda r: (r.y0, r.x0))


def plan_regions(predicted: list[PredictedTarget], width: int, height: int, params: RegionParams | None = None
                 ) -> list[Region] | None:
    """Crops covering the predicted boxes: snapped outward to `align`, clipped, merged.

    Parameters
    ----------
    predicted : list of PredictedTarget
    width, height : int
        Frame size, pixels.
    params : RegionParams, optional

    Returns
    -------
    list of Region or None
        None when the crops cover more than ``max_fraction`` of the frame: scan the
        whole frame instead.
    """
    p = params or RegionParams()
    boxes = [Region(*_snap(t.box, width, height, p), ids=(t.id,)) for t in predicted]
    boxes = [b for b in boxes if b.width > 0 and b.height > 0]
    regions = merge_regions(boxes, p.crop_cost_px)
    if sum(r.area for r in regions) > p.max_fraction * width * height:
        return None
    return regions


def predict_in_view(targets: MapTargets, camera: Camera, last: Pose, steps: float = 1.0,
                    before: Pose | None = None, before_steps: float = 1.0,
                    params: RegionParams | None = None) -> list[PredictedTarget]:
    """The map targets the next frame of a tracking stream should see, and where.

    Parameters
    ----------
    targets, camera, last, steps, before, before_steps, params
        As `predict_regions`.

    Returns
    -------
    list of PredictedTarget
        As `predict_targets`: the pose extrapolated from `before` and `last` when there
        is a `before`, else `last` with the margins of a camera whose motion is unknown.
    """
    p = params or RegionParams()
    if before is not None:
        pose = extrapolate(before, last, steps / max(before_steps, 1e-9))
        return predict_targets(targets, camera, pose, previous=last, steps=steps, params=p)
    return predict_targets(targets, camera, last, previous=None, steps=steps, params=p)


def predict_regions(targets: MapTargets, camera: Camera, last: Pose, steps: float = 1.0,
                    before: Pose | None = None, before_steps: float = 1.0,
                    params: RegionParams | None = None) -> list[Region] | None:
    """The regions to scan in the next frame of a tracking stream.

    Parameters
    ----------
    targets : MapTargets
        The map's targets.
    camera : Camera
    last : Pose
        The last known pose (map to camera).
    steps : float, optional
        Frames from the one seen from `last` to the one to scan.
    before : Pose or None, optional
        The pose `before_steps` frames before `last`, for a velocity.
    before_steps : float, optional
        Frames from `before` to `last`.
    params : RegionParams, optional

    Returns
    -------
    list of Region or None
        The crops to scan; None: scan the whole frame; an empty list: no mapped target
        can be in view.
    """
    p = params or RegionParams()
    predicted = predict_in_view(targets, camera, last, steps, before, before_steps, p)
    return plan_regions(predicted, camera.width, camera.height, p)


# --------------------------------------------------------------------------------------
# Decoding a frame smaller
# --------------------------------------------------------------------------------------


def disc_diameters(predicted: list[PredictedTarget]) -> np.ndarray:
    """Each predicted target's smallest disc diameter, pixels: the disc square's shortest
    side times the disc's share of it (a card seen at an angle is narrowest across its
    shortest side, and so are its discs).

    Parameters
    ----------
    predicted : list of PredictedTarget

    Returns
    -------
    (N,) ndarray
    """
    if not predicted:
        return np.zeros(0)
    discs = np.array([t.discs_px for t in predicted])  # (N, 4, 2)
    sides = np.linalg.norm(discs - np.roll(discs, -1, axis=1), axis=2)
    return _DISC_PER_SIDE * sides.min(axis=1)


def decode_reduction(predicted: list[PredictedTarget], width: int, height: int, min_disc_px: float,
                     factors: tuple[int, ...] = (1, 2, 4), min_side: int = 0) -> int:
    """The largest factor a frame can be decoded smaller by and still show every predicted
    disc at least `min_disc_px` across, in a frame at least `min_side` pixels high and wide.

    `min_disc_px` keeps every predicted card within the detector's reach (its smallest
    discs are 3.5 px across). The detector measures disc centres to a fraction of its own
    pixels, so a frame decoded at 1 / f measures them f times coarser in the frame's
    pixels: `min_side` keeps enough pixels for the pose's precision. Only the targets
    predicted on the image count (a card beyond its edge is not scanned).

    Parameters
    ----------
    predicted : list of PredictedTarget
        The targets the next frame should see (`predict_in_view`).
    width, height : int
        Frame size, pixels.
    min_disc_px : float
        Smallest disc diameter, pixels of the reduced frame.
    factors : tuple of int, optional
        The factors to choose from, ascending (the decoder's: 1, 2, 4, 8).
    min_side : int, optional
        Smallest side of the reduced frame, pixels.

    Returns
    -------
    int
        One of `factors`; the first when no target is predicted (nothing tells how
        small the discs to find are).
    """
    # Factors the frame's size allows first: none, and nothing needs predicting.
    sized = [f for f in factors if -(-min(width, height) // f) >= min_side]
    if len(sized) < 2 or not predicted:
        return factors[0]
    discs = np.array([t.discs_px for t in predicted])  # (N, 4, 2)
    on = ((discs[..., 0] >= -0.5) & (discs[..., 0] <= width - 0.5)
          & (discs[..., 1] >= -0.5) & (discs[..., 1] <= height - 0.5)).any(axis=1)
    if not on.any():
        return factors[0]
    sides = np.linalg.norm(discs[on] - np.roll(discs[on], -1, axis=1), axis=2)
    smallest = _DISC_PER_SIDE * float(sides.min())
    fitting = [f for f in sized if smallest / f >= min_disc_px]
    return max(fitting) if fitting else factors[0]


def reduce_regions(regions: list[Region], factor: int, width: int, height: int, align: int = 8) -> list[Region]:
    """Crops of a frame in the pixels of the frame decoded at 1 / `factor`.

    Each crop covers at least the frame's crop (pixel ``i`` of the reduced frame covers
    the frame's pixels ``i * factor`` to ``(i + 1) * factor - 1``), snapped outward to
    multiples of `align` in the reduced frame, where the detector's pyramid reads it.

    Parameters
    ----------
    regions : list of Region
        Crops in the frame's pixels.
    factor : int
        The reduction.
    width, height : int
        Size of the reduced frame, pixels.
    align : int, optional
        A multiple of 8.

    Returns
    -------
    list of Region
        The crops, merged where the snapping makes them meet.
    """
    if factor == 1:
        return list(regions)
    def up(value: int) -> int:  # the reduced pixel that covers `value - 1`, then the grid, rounded up
        reduced = -(-value // factor)
        return -(-reduced // align) * align

    out = []
    for r in regions:
        x0, y0 = r.x0 // factor // align * align, r.y0 // factor // align * align
        x1, y1 = min(width, up(r.x1)), min(height, up(r.y1))
        if x1 > x0 and y1 > y0:
            out.append(Region(x0, y0, x1, y1, r.ids))
    return merge_regions(out)
