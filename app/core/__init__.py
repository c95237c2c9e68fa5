"""The fidotrack vision library: numpy/OpenCV/SciPy only, no web, database or simulator code.

Sub-packages:

* `app.core.geometry`: the camera model, poses and pose estimation, similarity
  alignment, card homographies and the tracking regions a pose predicts.
* `app.core.detection`: the disc detector: candidate discs, targets, disc fit, `Detector`.
* `app.core.features`: the scene's own points, tracked from frame to frame (the
  survey's feature tracks).
* `app.core.survey`: the automatic survey: a map and the camera's intrinsics from a video.

Core modules:

* `app.core.markers`: the target cards: layout, code families, raster and SVG output.
* `app.core.imagecodec`: safe decoding of client JPEG and PNG images to greyscale.
* `app.core.freed`: FreeD D1 camera-tracking packets: a pose as pan, tilt, roll and
  position, and their bytes.

Conventions (disc order, frames, units) are in docs/map-format.md. The sub-packages are
not imported here: import the one you need (``from app.core.geometry import Camera``).
"""

__all__ = ["detection", "features", "freed", "geometry", "imagecodec", "markers", "survey"]
