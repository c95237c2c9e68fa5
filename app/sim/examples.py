"""Named example rooms and walks: the scenes that the benchmarks and the tests measure on.

Each example room fixes a room (its size, cards, card size, how the cards are placed and
how the walls look) and a camera. `ExampleRoom.walk` draws the room and a walk from one
seed (the room first, then the walk, from the same random stream) and hands back the
stream so that rendering the walk goes on from it: the same seed gives the same room,
the same walk and the same frames wherever it is used. Each example walk fixes a room,
a kind of walk and whether it is hand-held (shake, motion blur of the exposure).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from app.core.geometry import Camera, Pose
from app.sim.degrade import DegradationRanges, ThinLens
from app.sim.lighting import Lighting, ceiling_lamps
from app.sim.render import TexturedQuad
from app.sim.scenes import (
    CardPlacement,
    FrameTruth,
    Scene,
    WallFinish,
    plain_paint,
    render_walk,
    room_scene,
    room_walls,
)
from app.sim.video import PhoneVideo
from app.sim.walks import ExposureBlur, Shake, Walk, WalkKind, draw_walk

__all__ = [
    "BARE_WALL_ROOM",
    "BARE_WALL_WALK",
    "BENCH_CAMERA",
    "BENCH_ROOM",
    "BENCH_WALK",
    "CENTRE_LOOP_WALK",
    "CINE_LENS",
    "EXAMPLES",
    "EXPOSURE_S",
    "FURNISHED_ROOM",
    "FURNISHED_WALK",
    "GLOSSY_PAPER",
    "GLOSS_SHININESS",
    "HAND_HELD",
    "LAMP_AMBIENT",
    "LAMP_GRID",
    "PAN_WALK",
    "PLAIN_ROOM",
    "PLAIN_WALK",
    "SMALL_ROOM",
    "SPARSE_ROOM",
    "SPARSE_WALK",
    "WALKS",
    "BareWallRoom",
    "ExampleRoom",
    "ExampleWalk",
    "RoomWalk",
    "example",
    "example_walk",
]

#: The benchmarks' camera: 640x480, f 820 px, principal point at the image centre,
#: barrel distortion k1 -0.12 (a typical webcam or phone lens).
BENCH_CAMERA = Camera(np.array([[820.0, 0.0, 319.5], [0.0, 820.0, 239.5], [0.0, 0.0, 1.0]]),
                      np.array([-0.12, 0.0, 0.0, 0.0, 0.0]), 640, 480)


@dataclass(frozen=True)
class RoomWalk:
    """A room and a camera walk through it, with the random stream that drew them.

    Attributes
    ----------
    scene : Scene
        The room.
    poses : list of Pose
        The walk, map-to-camera transforms.
    rng : numpy.random.Generator
        The stream after drawing both: rendering the walk goes on from it.
    blur : list of ExposureBlur or None
        Each frame's motion blur from the camera's motion during its exposure; None:
        the degradation preset's random blur.
    walk : Walk or None
        The drawn walk the poses are of (its poses between frames: a rolling shutter's
        readout); None: only the frames' poses are known.
    """

    scene: Scene
    poses: list[Pose]
    rng: np.random.Generator
    blur: list[ExposureBlur] | None = None
    walk: Walk | None = None

    def frames(self, camera: Camera, degradation: str | DegradationRanges = "default", supersample: int = 2,
               video: PhoneVideo | None = None, follow_path: bool = False, lens: ThinLens | None = None,
               lighting: Lighting | None = None, readout_s: float | None = None
               ) -> Iterator[tuple[np.ndarray, FrameTruth]]:
        """The walk's rendered frames and their truth (`render_walk`, with the walk's blur),
        drawn on from `rng`.

        Parameters
        ----------
        camera : Camera
            The camera that films the walk.
        degradation : str or DegradationRanges, optional
            Name of a degradation preset, or the ranges themselves.
        supersample : int, optional
            Samples per pixel along each axis.
        video : PhoneVideo, optional
            Record the walk as a phone's video (H.264) instead of frame by frame.
        follow_path : bool, optional
            Render each frame along its exposure's path rather than smearing it
            straight (walks with an exposure only; several renders a frame).
        lens : ThinLens, optional
            The lens's depth of field: each pixel blurred as its depth says.
        lighting : Lighting, optional
            Lamps that light the room (`app.sim.lighting`); None: lit alike everywhere.
        readout_s : float, optional
            A rolling shutter's readout time, seconds (`Walk.readouts`; walks drawn by
            `ExampleRoom.walk` only); None: a global shutter.

        Yields
        ------
        image : (height, width) ndarray of uint8
        truth : FrameTruth

        Raises
        ------
        ValueError
            With `readout_s`, when the walk between its frames is not known.
        """
        readouts = None
        if readout_s is not None:
            if self.walk is None:
                raise ValueError("a rolling shutter needs the drawn walk (ExampleRoom.walk)")
            readouts = self.walk.readouts(readout_s)
        yield from render_walk(self.scene, camera, self.poses, self.rng, degradation, supersample, blur=self.blur,
                               video=video, follow_path=follow_path, lens=lens, lighting=lighting,
                               readouts=readouts)


@dataclass(frozen=True)
class ExampleRoom:
    """A box room with cards on its walls and the camera that films it.

    Attributes
    ----------
    name : str
        The key in `EXAMPLES`.
    size : tuple of float
        (W, D, H) of the room, metres.
    n_targets : int
        Cards on the walls.
    marker_size_m : float
        Side of a card, metres.
    camera : Camera
        The camera that films the room.
    cards : CardPlacement
        How the cards are placed on the walls ("random" or "spread").
    walls : WallFinish
        How the walls look ("photo" mosaics or "plain" paint).
    furniture : int
        Boards standing along the walls, a card on each (ids after the wall cards').
    """

    name: str
    size: tuple[float, float, float]
    n_targets: int
    marker_size_m: float
    camera: Camera
    cards: CardPlacement = "random"
    walls: WallFinish = "photo"
    furniture: int = 0

    def lamps(self, gloss: float = 0.0) -> Lighting:
        """The room lit by `LAMP_GRID` lamps under its ceiling (`ceiling_lamps`), its
        cards' paper as glossy as `gloss` says (`GLOSSY_PAPER`: photo paper).

        Parameters
        ----------
        gloss : float
            The cards' specular reflectance (0: matte).

        Returns
        -------
        Lighting
        """
        return ceiling_lamps(self.size, *LAMP_GRID, ambient=LAMP_AMBIENT, gloss=gloss, shininess=GLOSS_SHININESS)

    def scene(self, seed: int) -> Scene:
        """The room drawn from `seed` (its cards' places and the wall photographs).

        Parameters
        ----------
        seed : int
            Seed of the random stream that draws the room.

        Returns
        -------
        Scene
            The same room as ``walk(seed, n).scene`` for any n.
        """
        return self.walk(seed, 0).scene

    def walk(self, seed: int, n_frames: int, kind: WalkKind = "calibration", shake: Shake | None = None,
             exposure_s: float | None = None) -> RoomWalk:
        """The room drawn from `seed` and then a walk of `n_frames` poses of `kind`
        through it, from the same random stream.

        Parameters
        ----------
        seed : int
            Seed of the random stream that draws the room, then the walk.
        n_frames : int
            Poses in the walk.
        kind : WalkKind
            A calibration walk (two loops round the room, filming the walls), a tracking
            walk (a slower wander), a centre loop or a pan (`app.sim.walks`).
        shake : Shake, optional
            Hand-held jitter on the walk, drawn after it.
        exposure_s : float, optional
            Exposure time, seconds: each frame gets the motion blur of the camera's
            motion during it (its pose is the one at mid-exposure). None: the
            degradation preset's random blur.

        Returns
        -------
        RoomWalk
            The scene, the poses, the random stream and the frames' blur, ready to render
            the walk.
        """
        rng = np.random.default_rng(seed)
        scene = room_scene(rng, self.size, n_targets=self.n_targets, marker_size_m=self.marker_size_m,
                           walls=self.walls, cards=self.cards, furniture=self.furniture)
        walk = draw_walk(rng, self.size, n_frames, kind, shake)
        blur = walk.exposure_blur(self.camera, exposure_s, self.size) if exposure_s is not None else None
        return RoomWalk(scene, walk.poses, rng, blur, walk)


@dataclass(frozen=True)
class BareWallRoom(ExampleRoom):
    """An example room with one side wall left bare: its cards taken off and the wall
    painted plain, so that a camera facing it sees neither a card nor texture.

    The room, the cards on the other walls and the walk are drawn as `ExampleRoom`'s
    from the same seed: the same seed gives the same room with one wall stripped.

    Attributes
    ----------
    bare_wall : int
        The bare wall's index among the side walls of `room_walls` (0: the wall at y = 0).
    """

    bare_wall: int = 0

    def walk(self, seed: int, n_frames: int, kind: WalkKind = "calibration", shake: Shake | None = None,
             exposure_s: float | None = None) -> RoomWalk:
        """`ExampleRoom.walk`, with the bare wall stripped of its cards and its photographs.

        Parameters
        ----------
        seed, n_frames, kind, shake, exposure_s
            As `ExampleRoom.walk`.

        Returns
        -------
        RoomWalk
        """
        drawn = super().walk(seed, n_frames, kind, shake, exposure_s)
        wall = room_walls(self.size)[self.bare_wall]
        background = list(drawn.scene.background)
        background[self.bare_wall] = TexturedQuad(background[self.bare_wall].corners,
                                                  plain_paint(BARE_WALL_GREY, side_wall=True))
        # Cards hang 2 mm off their wall (more where bent): those within 5 cm of it are its.
        targets = [t for t in drawn.scene.targets
                   if abs(float((t.point(np.array([[0.5, 0.5]]))[0] - wall.centre) @ wall.inward)) > 0.05]
        scene = Scene(background=background, targets=targets, room_size=drawn.scene.room_size,
                      furniture=drawn.scene.furniture)
        return replace(drawn, scene=scene)


#: The bare wall's paint (a fraction of white).
BARE_WALL_GREY = 0.78


#: The benchmarks' room: 8 x 6 x 3 m, 30 cards of 0.2 m (bench_survey, bench_track,
#: bench_disc_fit and the tests that measure against them).
BENCH_ROOM = ExampleRoom("bench", (8.0, 6.0, 3.0), 30, 0.2, BENCH_CAMERA)

#: A small room for quick end-to-end tests: 5 x 4 x 2.6 m, 24 cards of 0.25 m, filmed
#: at 640x480 with f 700 px and k1 -0.1.
SMALL_ROOM = ExampleRoom("small", (5.0, 4.0, 2.6), 24, 0.25,
                         Camera.pinhole(700.0, 640, 480, dist=[-0.1, 0.0, 0.0, 0.0, 0.0]))

#: A room as people have one: the bench room's size and camera with 10 cards of 0.2 m
#: spread round the walls (about 2.8 m apart, long stretches of bare wall between them),
#: on photo walls.
SPARSE_ROOM = ExampleRoom("sparse", (8.0, 6.0, 3.0), 10, 0.2, BENCH_CAMERA, cards="spread")

#: The sparse room with plain painted walls: the same cards as `SPARSE_ROOM` for the
#: same seed, nothing on the walls for natural features to hold on to.
PLAIN_ROOM = ExampleRoom("plain", (8.0, 6.0, 3.0), 10, 0.2, BENCH_CAMERA, cards="spread", walls="plain")

#: A furnished room: the bench room's size and camera, 24 cards on the walls and 6 more on
#: boards standing on desks and lecterns along them, turned and leant back (up to nearly
#: flat): cards seen from above, at angles the wall cards are not.
FURNISHED_ROOM = ExampleRoom("furnished", (8.0, 6.0, 3.0), 24, 0.2, BENCH_CAMERA, furniture=6)

#: The bench room with its long wall at y = 0 bare (`BareWallRoom`): the same room as
#: `BENCH_ROOM` for the same seed, less that wall's cards (about 9 of the 30) and photographs.
BARE_WALL_ROOM = BareWallRoom("bare_wall", (8.0, 6.0, 3.0), 30, 0.2, BENCH_CAMERA, bare_wall=0)

#: The example rooms by name.
EXAMPLES: dict[str, ExampleRoom] = {room.name: room for room in (BENCH_ROOM, SMALL_ROOM, SPARSE_ROOM, PLAIN_ROOM,
                                                                  FURNISHED_ROOM, BARE_WALL_ROOM)}

#: The example rooms' lamps (`ExampleRoom.lamps`): a grid of rows x columns lamps 10 cm
#: under the ceiling, and the bounce light, as a fraction of a lamp's light 1 m away. In
#: the bench room, the long wall is lit up to 2.9 times as brightly under a lamp as
#: between lamps and corners, at card heights.
LAMP_GRID = (2, 3)
LAMP_AMBIENT = 0.08
#: Glossy photo paper: its highlight's peak, as a fraction of the lamp's light on the
#: card, and how sharp it is (a Blinn-Phong exponent). Matte paper: 0.
GLOSSY_PAPER = 0.6
GLOSS_SHININESS = 60.0


#: A phone held in the hand: 0.2 degrees RMS of rotation and 1.5 mm of translation
#: jitter about each axis, at 1.5-6 Hz.
HAND_HELD = Shake()

#: A cinema camera's depth of field at the bench camera's field of view: a 32 mm lens at
#: f/2.8 on a Super 35 sensor (24.9 mm across, 640 px: f 820 px), focused at 2.5 m.
#: Walls 4-5 m off blur by 0.7-0.9 px (radius); a card at 1 m by 2.8 px. (A phone's
#: 4-7 mm lens at f/1.8 keeps nearly all of a room sharp.)
CINE_LENS = ThinLens(focal_length_mm=32.0, f_number=2.8, focus_m=2.5)

#: The example walks' exposure, seconds: a phone's video in a well-lit room (at 36
#: degrees a second, a 5 px smear at f = 820 px).
EXPOSURE_S = 1.0 / 100.0


@dataclass(frozen=True)
class ExampleWalk:
    """A named way of filming an example room.

    Attributes
    ----------
    name : str
        The key in `WALKS`.
    room : ExampleRoom
        The room filmed.
    kind : WalkKind
        How the camera moves.
    shake : Shake or None
        Hand-held jitter; None: a steady camera.
    exposure_s : float or None
        Exposure time for the motion blur of the camera's own motion; None: the
        degradation preset's random blur.
    """

    name: str
    room: ExampleRoom
    kind: WalkKind
    shake: Shake | None = None
    exposure_s: float | None = None

    def walk(self, seed: int, n_frames: int) -> RoomWalk:
        """The room drawn from `seed`, then this walk of `n_frames` frames through it
        (`ExampleRoom.walk`).

        Parameters
        ----------
        seed : int
            Seed of the random stream that draws the room, then the walk.
        n_frames : int
            Frames of the walk.

        Returns
        -------
        RoomWalk
        """
        return self.room.walk(seed, n_frames, self.kind, self.shake, self.exposure_s)


#: The benchmarks' survey walk: two loops round the bench room, steady, random blur.
BENCH_WALK = ExampleWalk("bench", BENCH_ROOM, "calibration")
#: A small loop near the middle of the bench room looking out at its walls, hand-held.
CENTRE_LOOP_WALK = ExampleWalk("centre_loop", BENCH_ROOM, "centre_loop", HAND_HELD, EXPOSURE_S)
#: Turning round on one spot in the bench room, hand-held but with no translation: a
#: pure pan, no baseline.
PAN_WALK = ExampleWalk("pan", BENCH_ROOM, "pan", Shake(translation_m=0.0), EXPOSURE_S)
#: The centre loop in the sparse room: one or two cards in most frames, or none.
SPARSE_WALK = ExampleWalk("sparse", SPARSE_ROOM, "centre_loop", HAND_HELD, EXPOSURE_S)
#: The centre loop in the sparse room with plain walls.
PLAIN_WALK = ExampleWalk("plain", PLAIN_ROOM, "centre_loop", HAND_HELD, EXPOSURE_S)
#: The centre loop in the furnished room: the cards on its boards seen from above.
FURNISHED_WALK = ExampleWalk("furnished", FURNISHED_ROOM, "centre_loop", HAND_HELD, EXPOSURE_S)

#: The centre loop in the bench room with one long wall bare: the same walk as
#: `CENTRE_LOOP_WALK` for the same seed; for about a third of each turn the camera faces
#: the bare wall, with no card and nothing for feature tracks to hold on to.
BARE_WALL_WALK = ExampleWalk("bare_wall", BARE_WALL_ROOM, "centre_loop", HAND_HELD, EXPOSURE_S)

#: The example walks by name.
WALKS: dict[str, ExampleWalk] = {
    walk.name: walk for walk in (BENCH_WALK, CENTRE_LOOP_WALK, PAN_WALK, SPARSE_WALK, PLAIN_WALK, FURNISHED_WALK,
                                 BARE_WALL_WALK)
}


def example(name: str) -> ExampleRoom:
    """The example room called `name`.

    Parameters
    ----------
    name : str
        A key of `EXAMPLES`.

    Returns
    -------
    ExampleRoom

    Raises
    ------
    KeyError
        If there is no such example.
    """
    return EXAMPLES[name]


def example_walk(name: str) -> ExampleWalk:
    """The example walk called `name`.

    Parameters
    ----------
    name : str
        A key of `WALKS`.

    Returns
    -------
    ExampleWalk

    Raises
    ------
    KeyError
        If there is no such walk.
    """
    return WALKS[name]
