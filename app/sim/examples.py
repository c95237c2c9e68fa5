"""Named example rooms: the scenes that the benchmarks and the tests measure on.

Each example fixes a room (its size, cards and card size), a camera and how a walk
through the room is drawn. `ExampleRoom.walk` draws the room and a walk from one seed
(the room first, then the walk, from the same random stream) and hands back the stream
so that rendering the walk goes on from it: the same seed gives the same room, the same
walk and the same frames wherever it is used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.geometry import Camera, Pose
from app.sim.scenes import Scene, camera_walk, room_scene

__all__ = ["BENCH_CAMERA", "BENCH_ROOM", "EXAMPLES", "SMALL_ROOM", "ExampleRoom", "RoomWalk", "example"]

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
    """

    scene: Scene
    poses: list[Pose]
    rng: np.random.Generator


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
    """

    name: str
    size: tuple[float, float, float]
    n_targets: int
    marker_size_m: float
    camera: Camera

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

    def walk(self, seed: int, n_frames: int, kind: str = "calibration") -> RoomWalk:
        """The room drawn from `seed` and then a walk of `n_frames` poses of `kind`
        through it, from the same random stream.

        Parameters
        ----------
        seed : int
            Seed of the random stream that draws the room, then the walk.
        n_frames : int
            Poses in the walk.
        kind : {"calibration", "tracking"}
            A calibration walk (two loops round the room, filming the walls) or a
            tracking walk (a slower wander).

        Returns
        -------
        RoomWalk
            The scene, the poses and the random stream, ready to render the walk.
        """
        rng = np.random.default_rng(seed)
        scene = room_scene(rng, self.size, n_targets=self.n_targets, marker_size_m=self.marker_size_m)
        return RoomWalk(scene, camera_walk(rng, scene.room_size, n_frames, kind=kind), rng)


#: The benchmarks' room: 8 x 6 x 3 m, 30 cards of 0.2 m (bench_survey, bench_track,
#: bench_disc_fit and the tests that measure against them).
BENCH_ROOM = ExampleRoom("bench", (8.0, 6.0, 3.0), 30, 0.2, BENCH_CAMERA)

#: A small room for quick end-to-end tests: 5 x 4 x 2.6 m, 24 cards of 0.25 m, filmed
#: at 640x480 with f 700 px and k1 -0.1.
SMALL_ROOM = ExampleRoom("small", (5.0, 4.0, 2.6), 24, 0.25,
                         Camera.pinhole(700.0, 640, 480, dist=[-0.1, 0.0, 0.0, 0.0, 0.0]))

#: The example rooms by name.
EXAMPLES: dict[str, ExampleRoom] = {room.name: room for room in (BENCH_ROOM, SMALL_ROOM)}


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
