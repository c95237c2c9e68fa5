"""A rolling shutter: a frame's rows read out one after another while the camera moves.

A phone's sensor does not expose its frame at one instant: it reads the rows from top to
bottom over the readout time (about 10-30 ms at 30 frames a second), so each row sees
the room from where the camera was when that row was read. A camera turning sideways
shears the picture; one moving up or down stretches or squeezes it.

`RollingReadout` holds a frame's poses through its readout (`Walk.readouts` draws them
from a walk). `rolling_warp` turns a frame rendered from the mid-readout pose into the
rolling shutter's: each pixel is cast into the room from its own row's pose and looked
up in the render where that point appears. `rolling_projection` is the truth: where a
point of the room appears under the rolling shutter, its row and its row's pose agreeing.
The frame's pose (its truth, and what tracking should return) is the mid-readout one.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from app.core.geometry import Camera, Pose

#: Poses sampled through a readout (rows between them are interpolated).
READOUT_SAMPLES = 9
#: Fixed-point steps that find the row a point appears in (each one's error is the last
#: one's times the image's vertical motion over the readout in rows per row: well under 0.1).
ROW_ITERATIONS = 4


@dataclass(frozen=True)
class RollingReadout:
    """A frame's poses (map to camera) while its rows are read out.

    Attributes
    ----------
    poses : tuple of Pose
        Evenly in time from the first row's read (row 0) to the last's (row height - 1);
        the middle one is the frame's pose.
    """

    poses: tuple[Pose, ...]

    def at_rows(self, rows: np.ndarray, height: int) -> tuple[np.ndarray, np.ndarray]:
        """The camera's pose when the given rows were read: between the sampled poses
        the centre moves linearly and the rotation along the shortest arc.

        Parameters
        ----------
        rows : (N,) ndarray
            Image rows (fractional, clipped to the image).
        height : int
            The image's height in rows.

        Returns
        -------
        R : (N, 3, 3) ndarray
            Map-to-camera rotations.
        t : (N, 3) ndarray
            Map-to-camera translations.
        """
        n = len(self.poses)
        s = np.clip(np.asarray(rows, np.float64), 0.0, height - 1.0) / max(height - 1.0, 1.0) * (n - 1)
        j = np.minimum(np.floor(s).astype(int), n - 2)
        frac = (s - j)[:, None]
        Rs = np.array([p.R for p in self.poses])
        centres = np.array([p.position for p in self.poses])
        steps = Rotation.from_matrix(Rs[1:] @ Rs[:-1].transpose(0, 2, 1)).as_rotvec()  # (n - 1, 3)
        R = Rotation.from_rotvec(frac * steps[j]).as_matrix() @ Rs[j]
        centre = centres[j] + frac * (centres[j + 1] - centres[j])
        return R, -(R @ centre[:, :, None])[:, :, 0]


def rolling_projection(camera: Camera, readout: RollingReadout, points: np.ndarray) -> np.ndarray:
    """Where points of the room appear in a rolling-shutter frame: each in the row read
    while the camera saw it there.

    Parameters
    ----------
    camera : Camera
    readout : RollingReadout
    points : (N, 3) ndarray
        Map coordinates, in front of the camera.

    Returns
    -------
    (N, 2) ndarray
        Pixels.
    """
    X = np.asarray(points, np.float64).reshape(-1, 3)
    middle = readout.poses[len(readout.poses) // 2]
    uv = camera.project(middle.transform(X))
    for _ in range(ROW_ITERATIONS):
        R, t = readout.at_rows(uv[:, 1], camera.height)
        uv = camera.project((R @ X[:, :, None])[:, :, 0] + t)
    return uv


def rolling_warp(image: np.ndarray, camera: Camera, pose: Pose, readout: RollingReadout,
                 depth: np.ndarray) -> np.ndarray:
    """A frame rendered from `pose` as a rolling shutter reads it.

    Each pixel is cast into the room from the pose its row was read at, to the depth the
    render sees at that pixel (the depth changes little over a readout: only at a
    surface's outline is the cast point off), and the render is sampled where that
    point appears from `pose` (bilinear).

    Parameters
    ----------
    image : (height, width) ndarray of float
        The frame rendered from `pose` (the mid-readout pose).
    camera : Camera
    pose : Pose
        The pose `image` was rendered from.
    readout : RollingReadout
    depth : (height, width) ndarray
        Each pixel's depth along the optical axis from `pose`, metres (inf: nothing).

    Returns
    -------
    (height, width) ndarray of float32
    """
    h, w = image.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    ideal = camera.undistort_pixels(np.stack([xs.ravel(), ys.ravel()], axis=1))
    far = ~np.isfinite(depth.ravel())
    z = np.where(far, 1.0, depth.ravel())
    cam_points = np.column_stack([(ideal[:, 0] - camera.cx) / camera.fx * z, (ideal[:, 1] - camera.cy) / camera.fy * z,
                                  z])
    R, t = readout.at_rows(np.arange(h, dtype=np.float64), h)
    rows = ys.ravel().astype(int)
    # camera (row's pose) -> map -> camera (`pose`)
    world = ((cam_points - t[rows])[:, None, :] @ R[rows])[:, 0, :]
    uv = camera.project(pose.transform(world))
    uv[far] = np.column_stack([xs.ravel(), ys.ravel()])[far]
    maps = uv.reshape(h, w, 2).astype(np.float32)
    return cv2.remap(np.asarray(image, np.float32), maps[..., 0], maps[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
