"""The simulator: rooms of cards rendered through a real lens model, degraded as cameras
degrade images, with ground truth for every disc. Tests, benchmarks and training
measure against it; the service never imports it.

Modules:

* `app.sim.render`: textured planar quads seen through a `Camera` (`render`).
* `app.sim.scenes`: cards placed in 3D, rooms with photo-textured or painted walls and
  boards standing in them, named single-frame scenarios and the ground truth of every
  frame.
* `app.sim.walks`: camera walks through a room (survey loops, tracking, a loop near the
  middle, a pan), hand-held shake and the motion blur of each exposure.
* `app.sim.degrade`: camera degradations (blur, noise, exposure, glare, JPEG, a thin
  lens's depth of field) and their named presets.
* `app.sim.surfaces`: what each pixel sees (point, normal, depth, card or not).
* `app.sim.lighting`: lamps whose light falls off with distance, glossy card paper.
* `app.sim.video`: a walk recorded as a phone records it (H.264 through libx264).
* `app.sim.camera_feed`: a walk as a browser's fake camera plays it (y4m), each frame stamped with its index.
* `app.sim.examples`: the named example rooms and walks the benchmarks and tests measure on.

The photographs on walls and backgrounds need scikit-image and the video PyAV: ``pip
install 'fidotrack[sim]'``. The package's name `render` is the function; import the render
module's other names from it directly (``from app.sim.render import visible_points``).
"""

from app.sim.degrade import PRESETS, Degradation, DegradationRanges, ThinLens
from app.sim.examples import (
    BENCH_CAMERA,
    BENCH_ROOM,
    CINE_LENS,
    EXAMPLES,
    FURNISHED_ROOM,
    GLOSSY_PAPER,
    PLAIN_ROOM,
    SMALL_ROOM,
    SPARSE_ROOM,
    WALKS,
    ExampleRoom,
    ExampleWalk,
    RoomWalk,
)
from app.sim.lighting import Lamp, Lighting, ceiling_lamps
from app.sim.render import TexturedQuad, render
from app.sim.scenes import (
    SCENARIOS,
    FrameScenario,
    FrameTruth,
    PlacedTarget,
    Scene,
    TargetTruth,
    frame_truth,
    render_frame,
    render_walk,
    room_scene,
    scenario_frame,
)
from app.sim.video import PHONE, PhoneVideo, record
from app.sim.walks import ExposureBlur, Shake, Walk, WalkKind, camera_walk, draw_walk, walk_speeds

__all__ = [
    "BENCH_CAMERA",
    "BENCH_ROOM",
    "CINE_LENS",
    "EXAMPLES",
    "FURNISHED_ROOM",
    "GLOSSY_PAPER",
    "PHONE",
    "PLAIN_ROOM",
    "PRESETS",
    "SCENARIOS",
    "SMALL_ROOM",
    "SPARSE_ROOM",
    "WALKS",
    "Degradation",
    "DegradationRanges",
    "ExampleRoom",
    "ExampleWalk",
    "ExposureBlur",
    "FrameScenario",
    "FrameTruth",
    "Lamp",
    "Lighting",
    "PhoneVideo",
    "PlacedTarget",
    "RoomWalk",
    "Scene",
    "Shake",
    "TargetTruth",
    "TexturedQuad",
    "ThinLens",
    "Walk",
    "WalkKind",
    "camera_walk",
    "ceiling_lamps",
    "draw_walk",
    "frame_truth",
    "record",
    "render",
    "render_frame",
    "render_walk",
    "room_scene",
    "scenario_frame",
    "walk_speeds",
]
