"""Scenes for the simulator: marker cards placed in 3D, rooms with photo-textured or
plainly painted walls, and the ground truth of every rendered frame. The camera walks
through a room are `app.sim.walks`'s (`camera_walk` is also importable from here).

Ground truth is the projection of each disc's 3D centre (not the centroid of its imaged
ellipse), taken from the scene geometry, never from the code under test. Map
coordinates are metres; a room is the box [0, W] x [0, D] x [0, H] with z up; poses map
map points to the camera, ``x_cam = R @ X_map + t``.

The wall and background photographs come from scikit-image's bundled data
(``skimage.data``), an optional dependency: ``pip install 'fidotrack[sim]'``.
"""

from __future__ import annotations

import dataclasses
import functools
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import cv2
import numpy as np

from app.core.geometry import Camera, Pose
from app.core.markers import CODE_ORIGIN, CODE_SIZE, DEFAULT_FAMILY, get_family, marker_layout, render_card
from app.sim import degrade
from app.sim.lighting import Lighting, shade
from app.sim.render import TexturedQuad, render
from app.sim.shutter import RollingReadout, rolling_projection, rolling_warp
from app.sim.surfaces import Surfaces, cast_surfaces, quad_hits
from app.sim.video import PhoneVideo, record
from app.sim.walks import FPS, ExposureBlur, camera_walk, exposure_average

__all__ = [
    "CARD_PLACEMENTS",
    "CARD_TEXTURE_PX",
    "PHOTO_NAMES",
    "SCENARIOS",
    "WALL_FINISHES",
    "CardArtwork",
    "CardPlacement",
    "FrameScenario",
    "FrameTruth",
    "PlacedTarget",
    "Scene",
    "TargetTruth",
    "Wall",
    "WallFinish",
    "builtin_photos",
    "camera_walk",
    "card_texture",
    "frame_truth",
    "photo_mosaic",
    "plain_paint",
    "render_frame",
    "render_walk",
    "room_scene",
    "room_walls",
    "scenario_frame",
    "single_frame_scene",
    "target_truth",
]

#: Real photographs that scikit-image ships in its wheel (no download at run time).
PHOTO_NAMES: tuple[str, ...] = (
    "astronaut", "brick", "camera", "cat", "chelsea", "clock", "coffee", "coins", "grass",
    "gravel", "hubble_deep_field", "immunohistochemistry", "moon", "page", "rocket", "text",
)

# A card is drawn as three flat panels split at the edges of the code area, so a bent
# card stays a mesh of planes (each disc lies whole on one panel, its centre exact) and
# the fold lines fall between discs and code.
_PANEL_EDGES = (0.0, CODE_ORIGIN, CODE_ORIGIN + CODE_SIZE, 1.0)
#: Texture side of a card, texels: a multiple of 20 so that the panel edges fall on texel edges.
CARD_TEXTURE_PX = 480
# Texels by which panels overlap at a fold, so that anti-aliased edges leave no seam.
_PANEL_OVERLAP_PX = 2


@functools.cache
def builtin_photos() -> tuple[np.ndarray, ...]:
    """The photographs of `PHOTO_NAMES`, loaded once from scikit-image's bundled data.

    Returns
    -------
    tuple of ndarray
        Float32 greyscale images in [0, 1].

    Raises
    ------
    ImportError
        If scikit-image is not installed.
    """
    try:
        import skimage.data
    except ImportError as e:
        raise ImportError("the simulator needs scikit-image: pip install 'fidotrack[sim]'") from e

    photos = []
    for name in PHOTO_NAMES:
        image = np.asarray(getattr(skimage.data, name)())
        if image.ndim == 3:
            image = cv2.cvtColor(image[..., :3], cv2.COLOR_RGB2GRAY)
        photos.append((image.astype(np.float32) / 255.0))
    return tuple(photos)


@functools.cache
def card_texture(family: str, marker_id: int) -> np.ndarray:
    """A target's card as a texture (cached: a room reuses each card every frame).

    Parameters
    ----------
    family : str
        Code family name.
    marker_id : int
        Target id.

    Returns
    -------
    (CARD_TEXTURE_PX, CARD_TEXTURE_PX) ndarray of float32
        Grey levels in [0, 1], read-only; card units u -> texture units u.
    """
    card = render_card(marker_layout(family, marker_id), CARD_TEXTURE_PX)
    texture = card.astype(np.float32) / 255.0
    texture.setflags(write=False)
    return texture


def photo_mosaic(
    photos: Sequence[np.ndarray], rows: int, cols: int, tile_px: int, rng: np.random.Generator
) -> np.ndarray:
    """A wall texture: random crops of random photos, tiled (clutter at many scales).

    Parameters
    ----------
    photos : sequence of ndarray
        Greyscale float32 photographs.
    rows, cols : int
        Tiles down and across.
    tile_px : int
        Side of a tile, texels.
    rng : numpy.random.Generator
        Draws the photo, crop and mirroring of each tile.

    Returns
    -------
    (rows * tile_px, cols * tile_px) ndarray of float32
    """
    mosaic = np.empty((rows * tile_px, cols * tile_px), np.float32)
    for r in range(rows):
        for c in range(cols):
            photo = photos[int(rng.integers(len(photos)))]
            h, w = photo.shape
            side = int(rng.integers(min(h, w) // 3, min(h, w) + 1))
            y, x = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
            tile = cv2.resize(photo[y : y + side, x : x + side], (tile_px, tile_px), interpolation=cv2.INTER_AREA)
            if rng.random() < 0.5:
                tile = tile[:, ::-1]
            mosaic[r * tile_px : (r + 1) * tile_px, c * tile_px : (c + 1) * tile_px] = tile
    return mosaic


@dataclass(frozen=True, eq=False)
class CardArtwork:
    """Other printed artwork on a card of the same size (e.g. an AprilTag or ArUco
    marker for side-by-side benchmarks).

    Attributes
    ----------
    texture : (h, w) ndarray
        The card's texture, float32 in [0, 1].
    points_uv : (4, 2) ndarray
        The reference points whose projections are its ground truth, card units
        (0..1, origin top-left, x right, y down).
    """

    texture: np.ndarray
    points_uv: np.ndarray


@dataclass(frozen=True, eq=False)
class PlacedTarget:
    """A printed card in the scene.

    Attributes
    ----------
    id : int
        Target id.
    family : str
        Code family name.
    size_m : float
        Side of the card, metres.
    origin : (3,) ndarray
        The card's top-left corner (as printed), map coordinates.
    x_axis, y_axis : (3,) ndarray
        Unit vectors along its top edge and down its left edge (as printed);
        ``normal = y_axis x x_axis`` points out of the printed face.
    bend_m : float
        How far the middle panel is lifted off the card's plane, metres (paper is not
        flat).
    artwork : CardArtwork or None
        Other artwork printed instead of the target.
    """

    id: int
    family: str
    size_m: float
    origin: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    bend_m: float = 0.0
    artwork: CardArtwork | None = None

    @property
    def normal(self) -> np.ndarray:
        """Unit normal out of the printed face, map coordinates."""
        return np.cross(self.y_axis, self.x_axis)

    def _offset(self, u: np.ndarray) -> np.ndarray:
        # Panel-edge offsets along the normal: outer edges on the wall, the middle
        # panel lifted by bend_m; piecewise linear in between (flat panels).
        edges = np.array(_PANEL_EDGES)
        lift = np.array([0.0, self.bend_m, self.bend_m, 0.0])
        return np.interp(u, edges, lift)

    def point(self, uv: np.ndarray) -> np.ndarray:
        """Map coordinates of points on the (bent) card.

        Parameters
        ----------
        uv : (N, 2) array_like
            Card units: 0..1, origin top-left, x right, y down.

        Returns
        -------
        (N, 3) ndarray
            Map coordinates, metres.
        """
        uv = np.atleast_2d(np.asarray(uv, np.float64))
        u, v = uv[:, 0], uv[:, 1]
        return (
            self.origin
            + self.size_m * (u[:, None] * self.x_axis + v[:, None] * self.y_axis)
            + self._offset(u)[:, None] * self.normal
        )

    @property
    def discs(self) -> np.ndarray:
        """(4, 3) map coordinates of disc centres 0..3 (0 top-left, 1 top-right,
        2 bottom-right, 3 bottom-left as printed): the map's ground truth. For other
        artwork, its reference points."""
        if self.artwork is not None:
            return self.point(self.artwork.points_uv)
        return self.point(marker_layout(self.family, self.id).discs)

    @property
    def corners(self) -> np.ndarray:
        """(4, 3) map coordinates of the card's corners, top-left first, clockwise as printed."""
        return self.point(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64))

    def quads(self) -> list[TexturedQuad]:
        """The card as textured quads to render: three flat panels split at the code area.

        Returns
        -------
        list of TexturedQuad
        """
        texture = card_texture(self.family, self.id) if self.artwork is None else self.artwork.texture
        px = texture.shape[1]
        quads = []
        for k in range(len(_PANEL_EDGES) - 1):
            j0 = round(_PANEL_EDGES[k] * px) - (_PANEL_OVERLAP_PX if k > 0 else 0)
            j1 = round(_PANEL_EDGES[k + 1] * px) + (_PANEL_OVERLAP_PX if k < len(_PANEL_EDGES) - 2 else 0)
            u0, u1 = j0 / px, j1 / px
            # The overlap texels lie on this panel's own plane, extended past the fold.
            lo, hi = _PANEL_EDGES[k], _PANEL_EDGES[k + 1]
            corners_uv = np.array([[u0, 0], [u1, 0], [u1, 1], [u0, 1]], np.float64)
            corners = self._panel_point(corners_uv, lo, hi)
            quads.append(TexturedQuad(corners=corners, texture=texture[:, j0:j1]))
        return quads

    def _panel_point(self, uv: np.ndarray, lo: float, hi: float) -> np.ndarray:
        u, v = uv[:, 0], uv[:, 1]
        o_lo, o_hi = self._offset(np.array([lo, hi]))
        offset = o_lo + (u - lo) * (o_hi - o_lo) / (hi - lo)
        return (
            self.origin
            + self.size_m * (u[:, None] * self.x_axis + v[:, None] * self.y_axis)
            + offset[:, None] * self.normal
        )

    def to_map_target(self) -> dict[str, Any]:
        """The card's entry in a map document.

        Returns
        -------
        dict
            ``id`` and ``discs`` (4 x 3, metres, rounded to micrometres).
        """
        return {"id": self.id, "discs": self.discs.round(6).tolist()}


@dataclass(eq=False)
class Scene:
    """Background planes and placed targets, in map coordinates (metres).

    Attributes
    ----------
    background : list of TexturedQuad
        Walls, floor, ceiling or a backdrop.
    targets : list of PlacedTarget
    room_size : tuple of float or None
        (W, D, H) of a box room in metres; None for other scenes.
    furniture : list of TexturedQuad
        Boards standing in the room (some with cards on them): drawn like the
        background, and they hide what lies behind them from the truth as well.
    """

    background: list[TexturedQuad]
    targets: list[PlacedTarget]
    room_size: tuple[float, float, float] | None = None
    furniture: list[TexturedQuad] = field(default_factory=list)
    _quads: list[TexturedQuad] | None = field(default=None, repr=False)

    def quads(self) -> list[TexturedQuad]:
        """Everything to render: the background, the furniture, then every card's panels
        (built once).

        Returns
        -------
        list of TexturedQuad
        """
        if self._quads is None:
            self._quads = [*self.background, *self.furniture, *(q for t in self.targets for q in t.quads())]
        return self._quads

    def surfaces(self, camera: Camera, pose: Pose) -> Surfaces:
        """What each pixel sees from `pose` (`cast_surfaces`): the background and
        furniture as planes, each card as its square.

        Parameters
        ----------
        camera : Camera
        pose : Pose
            Map-to-camera transform.

        Returns
        -------
        Surfaces
        """
        return cast_surfaces(camera, pose, [q.corners for q in (*self.background, *self.furniture)],
                             [t.corners for t in self.targets])

    def map_document(self, camera: Camera) -> dict[str, Any]:
        """The true map as a map document (docs/map-format.md).

        Parameters
        ----------
        camera : Camera
            The camera written to the document.

        Returns
        -------
        dict
            In the frame "world", units metres, targets by id.
        """
        return {
            "frame": "world",
            "units": "m",
            "camera": camera.to_dict(),
            "targets": [t.to_map_target() for t in sorted(self.targets, key=lambda t: t.id)],
            "rms_px": 0.0,
            "survey_job_id": None,
        }


def _frame_of(point: np.ndarray, inward: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Right and down unit vectors of a surface seen from the side ``inward`` points to."""
    right = np.cross(up, inward)
    right /= np.linalg.norm(right)
    down = -np.cross(inward, right)
    return right, down


def _plane_quad(centre: np.ndarray, inward: np.ndarray, up: np.ndarray, width: float, height: float,
                texture: np.ndarray) -> TexturedQuad:
    right, down = _frame_of(centre, inward, up)
    top_left = centre - right * width / 2 - down * height / 2
    corners = np.array([
        top_left,
        top_left + right * width,
        top_left + right * width + down * height,
        top_left + down * height,
    ])
    return TexturedQuad(corners=corners, texture=texture)


# --- rooms --------------------------------------------------------------------------


@dataclass(frozen=True)
class Wall:
    """One face of a box room.

    Attributes
    ----------
    centre : (3,) ndarray
        Centre of the face, map coordinates.
    inward : (3,) ndarray
        Unit normal into the room.
    up : (3,) ndarray
        Unit vector that is up on the face as seen from inside.
    width, height : float
        Size of the face, metres.
    """

    centre: np.ndarray
    inward: np.ndarray
    up: np.ndarray
    width: float
    height: float


def room_walls(size: tuple[float, float, float]) -> list[Wall]:
    """The six faces of a box room [0, W] x [0, D] x [0, H] (z up), seen from inside.

    Parameters
    ----------
    size : tuple of float
        (W, D, H), metres.

    Returns
    -------
    list of Wall
        The four side walls (y = 0, y = D, x = 0, x = W), then floor and ceiling.
    """
    w, d, h = size
    z = np.array([0.0, 0.0, 1.0])
    y = np.array([0.0, 1.0, 0.0])
    return [
        Wall(np.array([w / 2, 0, h / 2]), np.array([0.0, 1, 0]), z, w, h),
        Wall(np.array([w / 2, d, h / 2]), np.array([0.0, -1, 0]), z, w, h),
        Wall(np.array([0, d / 2, h / 2]), np.array([1.0, 0, 0]), z, d, h),
        Wall(np.array([w, d / 2, h / 2]), np.array([-1.0, 0, 0]), z, d, h),
        Wall(np.array([w / 2, d / 2, 0]), np.array([0.0, 0, 1]), y, w, d),  # floor
        Wall(np.array([w / 2, d / 2, h]), np.array([0.0, 0, -1]), y, w, d),  # ceiling
    ]


#: How a room's walls, floor and ceiling look: "photo", mosaics of photographs (clutter
#: at every scale, for natural features to hold on to); "plain", uniform paint lit a
#: little unevenly, with no texture at all.
WallFinish = Literal["photo", "plain"]
#: Every wall finish.
WALL_FINISHES: tuple[WallFinish, ...] = get_args(WallFinish)
#: How the cards are placed on the side walls: "random", anywhere (at least 1.6 card
#: sides apart), so that cards cluster and most views hold several; "spread", evenly
#: round the room with some jitter, long stretches of bare wall between them.
CardPlacement = Literal["random", "spread"]
#: Every card placement.
CARD_PLACEMENTS: tuple[CardPlacement, ...] = get_args(CardPlacement)

# Plain paint: the grey of each face (the four side walls, floor, ceiling): the light
# falls on each wall differently.
_PAINT_GREY = (0.80, 0.74, 0.77, 0.71, 0.45, 0.86)
# Its shading: lighter towards the ceiling lights, darker towards the corners (fractions).
_PAINT_TOP_LIGHT, _PAINT_CORNER_SHADE = 0.04, 0.04
# Texels a side of a painted face: the shading is smooth, so a few texels carry it.
_PAINT_PX = 16
# Spread cards keep this far from the ends of a wall, metres (two cards either side of a
# corner stay apart).
_SPREAD_CORNER_M = 0.5


def plain_paint(grey: float, side_wall: bool) -> np.ndarray:
    """A painted face's texture: one grey, slightly shaded, no texture.

    Parameters
    ----------
    grey : float
        The paint's grey level in [0, 1].
    side_wall : bool
        Whether the face is a side wall (lighter towards its top, the ceiling) rather than
        the floor or the ceiling.

    Returns
    -------
    (16, 16) ndarray of float32
        Rows top to bottom as seen from inside the room; the shading is a smooth
        function of the position, darker by up to 4 % towards the face's ends.
    """
    across = np.linspace(-1.0, 1.0, _PAINT_PX)
    shade = 1.0 - _PAINT_CORNER_SHADE * across[None, :] ** 2
    if side_wall:
        shade = shade * (1.0 + _PAINT_TOP_LIGHT * -across[:, None])
    else:
        shade = shade * (1.0 - _PAINT_CORNER_SHADE * across[:, None] ** 2)
    return np.clip(grey * shade, 0.0, 1.0).astype(np.float32)


def room_scene(
    rng: np.random.Generator,
    size: tuple[float, float, float] = (8.0, 6.0, 3.0),
    n_targets: int = 30,
    marker_size_m: float = 0.2,
    family: str = DEFAULT_FAMILY,
    max_bend_m: float = 0.004,
    photos: Sequence[np.ndarray] | None = None,
    walls: WallFinish = "photo",
    cards: CardPlacement = "random",
    furniture: int = 0,
) -> Scene:
    """A box room with textured or painted walls, floor and ceiling, and cards on its walls.

    The cards get places, rotations and heights (centres 0.7 m up to min(H - 0.3, 2.3) m)
    on the four side walls, 2 mm off the wall, ids 0 .. n_targets - 1.

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws the wall textures, then the cards. Painted walls draw the same numbers as
        photo walls, so one seed gives the same cards and the same walk after them
        whatever the finish.
    size : tuple of float, optional
        (W, D, H) of the room, metres.
    n_targets : int, optional
        Cards to place.
    marker_size_m : float, optional
        Side of a card, metres.
    family : str, optional
        Code family of the cards.
    max_bend_m : float, optional
        Each card's bend is drawn uniformly from [0, max_bend_m], metres.
    photos : sequence of ndarray, optional
        Wall photographs; by default `builtin_photos`.
    walls : WallFinish, optional
        "photo" (photo mosaics) or "plain" (painted, `plain_paint`).
    cards : CardPlacement, optional
        "random" or "spread".
    furniture : int, optional
        Boards standing on furniture along the walls, each with a card on it (ids after
        the wall cards'), drawn after the wall cards (`_place_boards`).

    Returns
    -------
    Scene

    Raises
    ------
    ValueError
        If the cards or boards do not fit, or `walls` or `cards` is unknown.
    """
    if walls not in WALL_FINISHES:
        raise ValueError(f"unknown wall finish {walls!r}: one of {', '.join(WALL_FINISHES)}")
    if cards not in CARD_PLACEMENTS:
        raise ValueError(f"unknown card placement {cards!r}: one of {', '.join(CARD_PLACEMENTS)}")
    photos = photos if photos is not None else builtin_photos()
    faces = room_walls(size)
    background = []
    for index, wall in enumerate(faces):
        tile_m = 0.75
        rows = max(1, round(wall.height / tile_m))
        cols = max(1, round(wall.width / tile_m))
        # Painted walls draw the mosaic too (and drop it): the cards come next from the stream.
        texture = photo_mosaic(photos, rows, cols, 192, rng)
        if walls == "plain":
            texture = plain_paint(_PAINT_GREY[index], side_wall=index < 4)
        background.append(_plane_quad(wall.centre, wall.inward, wall.up, wall.width, wall.height, texture))
    side_walls = faces[:4]
    if cards == "spread":
        targets = _spread_cards(rng, side_walls, n_targets, marker_size_m, family, max_bend_m)
        return _furnish(Scene(background=background, targets=targets, room_size=size), rng, furniture,
                        marker_size_m, family, max_bend_m)

    targets: list[PlacedTarget] = []
    perimeter = np.array([wall.width for wall in side_walls])
    attempts = 0
    while len(targets) < n_targets:
        attempts += 1
        if attempts > 10000:
            raise ValueError(f"cannot place {n_targets} targets of {marker_size_m} m in a {size} room")
        wall = side_walls[int(rng.choice(4, p=perimeter / perimeter.sum()))]
        right, down = _frame_of(wall.centre, wall.inward, wall.up)
        margin = marker_size_m
        a = rng.uniform(-wall.width / 2 + margin, wall.width / 2 - margin)
        height = rng.uniform(0.7, min(wall.height - 0.3, 2.3))
        # 2 mm off the wall; the bend lifts the middle further out (a card stuck on a wall
        # cannot bend into it, and a panel behind the wall would vanish).
        centre = wall.centre + right * a + wall.up * (height - wall.height / 2) + wall.inward * 0.002
        if any(np.linalg.norm(centre - (t.point(np.array([[0.5, 0.5]]))[0])) < 1.6 * marker_size_m for t in targets):
            continue
        roll = rng.uniform(-np.pi, np.pi)
        x_axis = np.cos(roll) * right + np.sin(roll) * down
        y_axis = -np.sin(roll) * right + np.cos(roll) * down
        origin = centre - marker_size_m / 2 * (x_axis + y_axis)
        targets.append(
            PlacedTarget(
                id=len(targets), family=family, size_m=marker_size_m, origin=origin,
                x_axis=x_axis, y_axis=y_axis, bend_m=float(rng.uniform(0.0, max_bend_m)),
            )
        )
    return _furnish(Scene(background=background, targets=targets, room_size=size), rng, furniture, marker_size_m,
                    family, max_bend_m)


#: A board standing on furniture in a room (`_place_boards`), as a lectern, an easel on a
#: desk or a drafting table would hold it (the furniture under it is not drawn): its size
#: (width, height, metres), the height of its lower edge and how far that stands from the
#: wall (metres), how far it is turned from facing the room's middle about the vertical
#: and leant back from upright (degrees). Leant back by 70 degrees a board is nearly a
#: table top: a standing camera sees its card at a grazing angle.
BOARD_SIZE_M = (0.5, 0.6)
BOARD_FOOT_M = (0.5, 0.9)
BOARD_FROM_WALL_M = (0.6, 1.0)
BOARD_TURN_DEG = 50.0
BOARD_LEAN_DEG = (10.0, 70.0)
#: Boards keep this far from the walls and from each other (centres), metres.
_BOARD_CLEARANCE_M, _BOARD_SPACING_M = 0.05, 0.9
#: The boards' paint: a mid grey, so the white card stands out as it would on wood.
_BOARD_GREY = 0.42


def _furnish(scene: Scene, rng: np.random.Generator, n_boards: int, marker_size_m: float, family: str,
             max_bend_m: float) -> Scene:
    """The scene with `n_boards` boards standing in it, a card on each."""
    if n_boards <= 0:
        return scene
    assert scene.room_size is not None
    boards, cards = _place_boards(rng, scene.room_size, n_boards, len(scene.targets), marker_size_m, family,
                                  max_bend_m)
    return Scene(background=scene.background, targets=[*scene.targets, *cards], room_size=scene.room_size,
                 furniture=boards)


def _place_boards(rng: np.random.Generator, size: tuple[float, float, float], n_boards: int, first_id: int,
                  marker_size_m: float, family: str, max_bend_m: float
                  ) -> tuple[list[TexturedQuad], list[PlacedTarget]]:
    """Boards standing on furniture in front of the side walls, each turned and leant
    back at random, with a card at a random roll in its middle (2 mm off it)."""
    width, height = BOARD_SIZE_M
    lo = np.full(3, _BOARD_CLEARANCE_M)
    hi = np.asarray(size, np.float64) - _BOARD_CLEARANCE_M
    side_walls = room_walls(size)[:4]
    perimeter = np.array([wall.width for wall in side_walls])
    z = np.array([0.0, 0.0, 1.0])
    paint = plain_paint(_BOARD_GREY, side_wall=False)
    boards: list[TexturedQuad] = []
    cards: list[PlacedTarget] = []
    centres: list[np.ndarray] = []
    for _ in range(10000):
        if len(boards) == n_boards:
            break
        wall = side_walls[int(rng.choice(4, p=perimeter / perimeter.sum()))]
        right, _ = _frame_of(wall.centre, wall.inward, wall.up)
        along = rng.uniform(-wall.width / 2 + width, wall.width / 2 - width)
        foot = wall.centre + right * along + wall.inward * rng.uniform(*BOARD_FROM_WALL_M)
        foot[2] = rng.uniform(*BOARD_FOOT_M)
        turn = np.deg2rad(rng.uniform(-BOARD_TURN_DEG, BOARD_TURN_DEG))
        facing = np.cos(turn) * wall.inward + np.sin(turn) * right  # horizontal
        lean = np.deg2rad(rng.uniform(*BOARD_LEAN_DEG))
        normal = np.cos(lean) * facing + np.sin(lean) * z  # leant back: its face turns up
        up = np.cos(lean) * z - np.sin(lean) * facing
        centre = foot + up * height / 2
        quad = _plane_quad(centre, normal, up, width, height, paint)
        if (quad.corners < lo).any() or (quad.corners > hi).any():
            continue
        if any(np.linalg.norm(centre - c) < _BOARD_SPACING_M for c in centres):
            continue
        board_right, board_down = _frame_of(centre, normal, up)
        roll = rng.uniform(-np.pi, np.pi)
        x_axis = np.cos(roll) * board_right + np.sin(roll) * board_down
        y_axis = -np.sin(roll) * board_right + np.cos(roll) * board_down
        card_centre = centre + normal * 0.002
        cards.append(PlacedTarget(
            id=first_id + len(cards), family=family, size_m=marker_size_m,
            origin=card_centre - marker_size_m / 2 * (x_axis + y_axis), x_axis=x_axis, y_axis=y_axis,
            bend_m=float(rng.uniform(0.0, max_bend_m)),
        ))
        boards.append(quad)
        centres.append(centre)
    if len(boards) < n_boards:
        raise ValueError(f"cannot place {n_boards} boards in a {size} room")
    return boards, cards


def _spread_cards(rng: np.random.Generator, side_walls: list[Wall], n_targets: int, marker_size_m: float,
                  family: str, max_bend_m: float) -> list[PlacedTarget]:
    """Cards evenly round the side walls: the walls laid end to end, one card every
    perimeter / n metres from a random start, each moved by up to a quarter of that
    spacing, none within `_SPREAD_CORNER_M` of a wall's end."""
    widths = np.array([wall.width for wall in side_walls])
    starts = np.concatenate([[0.0], np.cumsum(widths)[:-1]])
    spacing = widths.sum() / max(n_targets, 1)
    first = rng.uniform(0.0, spacing)
    targets: list[PlacedTarget] = []
    for k in range(n_targets):
        along = (first + k * spacing + rng.uniform(-0.25, 0.25) * spacing) % widths.sum()
        j = int(np.searchsorted(starts, along, side="right") - 1)
        wall = side_walls[j]
        end_margin = min(max(_SPREAD_CORNER_M, marker_size_m), wall.width / 2)
        a = float(np.clip(along - starts[j], end_margin, wall.width - end_margin)) - wall.width / 2
        right, down = _frame_of(wall.centre, wall.inward, wall.up)
        height = rng.uniform(0.7, min(wall.height - 0.3, 2.3))
        centre = wall.centre + right * a + wall.up * (height - wall.height / 2) + wall.inward * 0.002
        if any(np.linalg.norm(centre - t.point(np.array([[0.5, 0.5]]))[0]) < 1.6 * marker_size_m for t in targets):
            raise ValueError(f"cannot spread {n_targets} targets of {marker_size_m} m round the walls: too many")
        roll = rng.uniform(-np.pi, np.pi)
        x_axis = np.cos(roll) * right + np.sin(roll) * down
        y_axis = -np.sin(roll) * right + np.cos(roll) * down
        origin = centre - marker_size_m / 2 * (x_axis + y_axis)
        targets.append(PlacedTarget(id=k, family=family, size_m=marker_size_m, origin=origin, x_axis=x_axis,
                                    y_axis=y_axis, bend_m=float(rng.uniform(0.0, max_bend_m))))
    return targets


# --- single frames ------------------------------------------------------------------


def single_frame_scene(
    rng: np.random.Generator,
    camera: Camera,
    n_targets: int = 1,
    distance_m: tuple[float, float] = (0.8, 3.0),
    tilt_deg: tuple[float, float] = (0.0, 60.0),
    marker_size_m: float = 0.15,
    family: str = DEFAULT_FAMILY,
    ids: Sequence[int] | None = None,
    photos: Sequence[np.ndarray] | None = None,
    clutter_tiles: tuple[int, int] = (3, 4),
) -> Scene:
    """Cards in front of a camera at the origin, over a photo background plane.

    The camera has the identity pose: it looks along +z, y down.

    Parameters
    ----------
    rng : numpy.random.Generator
    camera : Camera
    n_targets : int, optional
    distance_m : tuple of float, optional
        Range of the cards' depths, metres.
    tilt_deg : tuple of float, optional
        Range of the cards' tilts away from facing the camera, degrees.
    marker_size_m : float, optional
        Side of a card, metres.
    family : str, optional
    ids : sequence of int, optional
        The cards' ids; by default drawn at random from the family.
    photos : sequence of ndarray, optional
        Background photographs; by default `builtin_photos`.
    clutter_tiles : tuple of int, optional
        (rows, cols) of photo tiles on the background.

    Returns
    -------
    Scene

    Raises
    ------
    ValueError
        If `ids` does not list `n_targets` ids or the cards do not fit into the view.
    """
    photos = photos if photos is not None else builtin_photos()
    if ids is not None and len(ids) != n_targets:
        raise ValueError("ids must list n_targets ids")
    chosen = list(ids) if ids is not None else [int(i) for i in rng.permutation(len(get_family(family)))[:n_targets]]
    fx, fy = camera.K[0, 0], camera.K[1, 1]
    cx, cy = camera.K[0, 2], camera.K[1, 2]
    far = distance_m[1] * rng.uniform(1.3, 3.0)
    half_w = (camera.width / 2) / fx * far * 1.3
    half_h = (camera.height / 2) / fy * far * 1.3
    rows, cols = clutter_tiles
    texture = photo_mosaic(photos, rows, cols, max(64, 1024 // cols), rng)
    background = [
        _plane_quad(np.array([0.0, 0.0, far]), np.array([0.0, 0.0, -1.0]), np.array([0.0, -1.0, 0.0]),
                    2 * half_w, 2 * half_h, texture)
    ]
    targets: list[PlacedTarget] = []
    attempts = 0
    while len(targets) < n_targets:
        attempts += 1
        if attempts > 2000:
            raise ValueError("cannot fit the requested targets into the view")
        z = rng.uniform(*distance_m)
        margin = 0.75 * marker_size_m * max(fx, fy) / z
        u = rng.uniform(margin, camera.width - 1 - margin) if camera.width > 2 * margin else cx
        v = rng.uniform(margin, camera.height - 1 - margin) if camera.height > 2 * margin else cy
        centre = np.array([(u - cx) / fx * z, (v - cy) / fy * z, z])
        if any(np.linalg.norm(centre - t.point(np.array([[0.5, 0.5]]))[0]) < 1.5 * marker_size_m for t in targets):
            continue
        tilt = np.deg2rad(rng.uniform(*tilt_deg))
        tilt_axis = rng.uniform(0, np.pi)
        roll = rng.uniform(-np.pi, np.pi)
        # Start facing the camera (normal -z), roll in the card plane, then tilt.
        x0 = np.array([np.cos(roll), np.sin(roll), 0.0])
        y0 = np.array([-np.sin(roll), np.cos(roll), 0.0])
        axis = np.array([np.cos(tilt_axis), np.sin(tilt_axis), 0.0])
        rot, _ = cv2.Rodrigues(axis * tilt)
        x_axis, y_axis = rot @ x0, rot @ y0
        origin = centre - marker_size_m / 2 * (x_axis + y_axis)
        targets.append(PlacedTarget(id=chosen[len(targets)], family=family, size_m=marker_size_m,
                                    origin=origin, x_axis=x_axis, y_axis=y_axis))
    return Scene(background=background, targets=targets)


# --- ground truth and rendering -----------------------------------------------------


@dataclass(frozen=True)
class TargetTruth:
    """The ground truth of one target in one frame.

    Attributes
    ----------
    id : int
    discs_px : (4, 2) ndarray
        Projections of the 3D disc centres, pixels (NaN behind the camera).
    disc_visible : (4,) ndarray of bool
        In front, inside the image, within the lens's field, facing the camera and not
        occluded.
    distance_m : float
        Distance from the camera centre to the card's centre, metres.
    facing_cos : float
        Cosine between the card normal and the direction to the camera.
    disc_diameter_px : float
        Approximate imaged disc diameter, pixels.
    occluded : bool
        Whether an occluder was drawn over the card.
    """

    id: int
    discs_px: np.ndarray  # (4,2) projections of the 3D disc centres
    disc_visible: np.ndarray  # (4,) in front, inside the image, facing the camera, not occluded
    distance_m: float
    facing_cos: float  # cosine between the card normal and the direction to the camera
    disc_diameter_px: float  # approximate imaged disc diameter
    occluded: bool = False

    @property
    def visible(self) -> bool:
        """All four discs visible."""
        return bool(self.disc_visible.all())

    def to_dict(self) -> dict[str, Any]:
        """The truth as JSON-able values (rounded).

        Returns
        -------
        dict
        """
        return {
            "id": self.id,
            "discs_px": self.discs_px.round(4).tolist(),
            "disc_visible": self.disc_visible.tolist(),
            "visible": self.visible,
            "distance_m": round(self.distance_m, 4),
            "facing_cos": round(self.facing_cos, 4),
            "disc_diameter_px": round(self.disc_diameter_px, 3),
            "occluded": self.occluded,
        }


@dataclass(frozen=True)
class FrameTruth:
    """The ground truth of one rendered frame.

    Attributes
    ----------
    pose : Pose
        Map-to-camera transform of the frame.
    camera : Camera
    targets : list of TargetTruth
        Every target with a disc in front of the camera.
    degradation : dict
        The frame's `Degradation.to_dict` (empty when none).
    """

    pose: Pose
    camera: Camera
    targets: list[TargetTruth]
    degradation: dict[str, Any]

    def visible_targets(self) -> list[TargetTruth]:
        """The targets whose four discs are all visible.

        Returns
        -------
        list of TargetTruth
        """
        return [t for t in self.targets if t.visible]

    def to_dict(self) -> dict[str, Any]:
        """The truth as JSON-able values: the pose, its targets, the degradation.

        Returns
        -------
        dict
        """
        return {
            "R": self.pose.R.round(9).tolist(),
            "t": self.pose.t.round(9).tolist(),
            "position": self.pose.position.round(9).tolist(),
            "targets": [t.to_dict() for t in self.targets],
            "degradation": self.degradation,
        }


#: A disc is visible only if its ray lies within this multiple of the image corners'
#: radius (Camera.in_field): 1.0 is exactly the image's rays for a radial lens; the 2%
#: covers tangential distortion, so no disc genuinely in the image is dropped.
_FIELD_MARGIN = 1.02


def target_truth(camera: Camera, pose: Pose, target: PlacedTarget, border_px: float = 2.0) -> TargetTruth | None:
    """Ground truth of one target seen from `pose`.

    A disc is visible when it projects inside the image (``border_px`` in) and its ray
    is within the lens's field: far off axis (~70 degrees for k1 = -0.12) the distortion
    polynomial folds points back into the image, where the renderer draws nothing.

    Parameters
    ----------
    camera : Camera
    pose : Pose
        Map-to-camera transform.
    target : PlacedTarget
    border_px : float, optional
        A visible disc's centre lies at least this far inside the image, pixels.

    Returns
    -------
    TargetTruth or None
        None when no disc is in front of the camera.
    """
    discs = target.discs
    cam = pose.transform(discs)
    if (cam[:, 2] <= 0.01).all():
        return None
    in_front = cam[:, 2] > 0.01
    uv = np.full((4, 2), np.nan)
    uv[in_front] = camera.project(cam[in_front])
    inside = (
        in_front
        & camera.in_field(cam, _FIELD_MARGIN)
        & (uv[:, 0] >= border_px) & (uv[:, 0] <= camera.width - 1 - border_px)
        & (uv[:, 1] >= border_px) & (uv[:, 1] <= camera.height - 1 - border_px)
    )
    centre = discs.mean(axis=0)
    to_camera = pose.position - centre
    distance = float(np.linalg.norm(to_camera))
    facing = float(np.dot(target.normal, to_camera) / max(distance, 1e-12))
    radius_m = marker_layout(target.family, target.id).disc_radius * target.size_m
    z = float(np.mean(cam[in_front, 2]))
    diameter = 2 * radius_m * float(camera.K[0, 0]) / max(z, 1e-6)
    return TargetTruth(
        id=target.id,
        discs_px=uv,
        disc_visible=inside & (facing > 0.05),
        distance_m=distance,
        facing_cos=facing,
        disc_diameter_px=diameter,
    )


def frame_truth(camera: Camera, pose: Pose, scene: Scene, degradation: dict[str, Any] | None = None) -> FrameTruth:
    """Ground truth of a frame without rendering it.

    Parameters
    ----------
    camera : Camera
    pose : Pose
        Map-to-camera transform.
    scene : Scene
    degradation : dict, optional
        Recorded in the truth as given.

    Returns
    -------
    FrameTruth
    """
    truths = []
    for target in scene.targets:
        truth = target_truth(camera, pose, target)
        if truth is None:
            continue
        if scene.furniture:
            hidden = _hidden(pose.position, target.discs, [q.corners for q in scene.furniture])
            if hidden.any():
                truth = dataclasses.replace(truth, disc_visible=truth.disc_visible & ~hidden)
        truths.append(truth)
    return FrameTruth(pose=pose, camera=camera, targets=truths, degradation=degradation or {})


#: A disc counts as hidden by a board only if the board lies this much nearer along its
#: ray (metres): a card on the board itself lies 2 mm in front of it.
_HIDDEN_MARGIN_M = 1e-3


def _hidden(eye: np.ndarray, points: np.ndarray, boards: Sequence[np.ndarray]) -> np.ndarray:
    """(N,) whether a board lies between `eye` and each of `points` (N, 3)."""
    d = points - eye
    length = np.linalg.norm(d, axis=1)
    hidden = np.zeros(len(points), bool)
    for corners in boards:
        t, meets = quad_hits(eye, d, corners)  # t along d: 1 at the point
        hidden |= meets & (t * length < length - _HIDDEN_MARGIN_M)
    return hidden


#: The depth given to pixels that see no surface (a backdrop's edge), metres.
_FAR_M = 1e3


def render_frame(
    scene: Scene,
    camera: Camera,
    pose: Pose,
    rng: np.random.Generator,
    degradation: degrade.Degradation | None = None,
    occlusion_probability: float = 0.0,
    supersample: int = 2,
    exposure: Sequence[Pose] = (),
    lens: degrade.ThinLens | None = None,
    lighting: Lighting | None = None,
    readout: RollingReadout | None = None,
) -> tuple[np.ndarray, FrameTruth]:
    """Render one frame and its ground truth.

    Parameters
    ----------
    scene : Scene
    camera : Camera
    pose : Pose
        Map-to-camera transform.
    rng : numpy.random.Generator
        Draws the occlusion and the sensor noise.
    degradation : Degradation, optional
        Applied to the rendered image; none by default.
    occlusion_probability : float, optional
        Chance that a visible target is partly covered by a piece of photograph; discs
        whose centre it covers are marked not visible.
    supersample : int, optional
        Samples per pixel along each axis (`render`).
    exposure : sequence of Pose, optional
        The camera's poses through the exposure, evenly in time: the frame is the mean
        of their renders, as a sensor integrates the light while the camera moves (the
        truth stays `pose`'s: give the exposure-averaged pose, `walks.exposure_average`).
    lens : ThinLens, optional
        The lens's depth of field: each pixel blurred by its depth's blur circle
        (`degrade.depth_defocus`, the depths from `Scene.surfaces`), before the other
        degradations.
    lighting : Lighting, optional
        Lamps: each pixel lit by its surface's irradiance, glossy cards' highlights
        added, the frame auto-exposed (`lighting.shade`), before the depth of field.
        With `exposure`, lit as seen from `pose`. None: every surface lit alike.
    readout : RollingReadout, optional
        A rolling shutter's poses through the frame's readout, `pose` the middle one:
        the rendered frame is warped as the shutter reads it (`shutter.rolling_warp`,
        before the sensor's degradations) and the truth's disc projections are where
        the shutter puts them (`shutter.rolling_projection`). None: a global shutter.

    Returns
    -------
    image : (height, width) ndarray of uint8
        The greyscale frame.
    truth : FrameTruth
    """
    if exposure:
        image = np.mean([render(camera, p, scene.quads(), background=0.5, supersample=supersample)
                         for p in exposure], axis=0)
    else:
        image = render(camera, pose, scene.quads(), background=0.5, supersample=supersample)
    if lens is not None or lighting is not None or readout is not None:
        surfaces = scene.surfaces(camera, pose)
        if lighting is not None:
            image = shade(image, surfaces, lighting, pose.position)
        if lens is not None:
            depth = np.where(np.isfinite(surfaces.depth), surfaces.depth, _FAR_M)
            image = degrade.depth_defocus(image, depth, lens, camera.fx)
        if readout is not None:
            image = rolling_warp(image, camera, pose, readout, surfaces.depth)
    truth = frame_truth(camera, pose, scene, degradation.to_dict() if degradation else {})
    if readout is not None:
        truth = _rolled(truth, camera, readout, scene)
    visible = truth.visible_targets()
    if visible and occlusion_probability > 0 and rng.random() < occlusion_probability:
        image, truth = _occlude_one(image, truth, visible[int(rng.integers(len(visible)))], rng)
    if degradation is not None:
        image = degradation.apply(image, rng)
    return degrade.to_uint8(image), truth


def _rolled(truth: FrameTruth, camera: Camera, readout: RollingReadout, scene: Scene) -> FrameTruth:
    """The truth's disc projections as a rolling shutter places them (visibility stays
    the mid-readout pose's)."""
    discs = {t.id: t.discs for t in scene.targets}
    targets = []
    for t in truth.targets:
        uv = t.discs_px.copy()
        finite = np.isfinite(uv).all(axis=1)
        if finite.any():
            uv[finite] = rolling_projection(camera, readout, discs[t.id][finite])
        targets.append(dataclasses.replace(t, discs_px=uv))
    return dataclasses.replace(truth, targets=targets)


def _occlude_one(image: np.ndarray, truth: FrameTruth, target: TargetTruth,
                 rng: np.random.Generator) -> tuple[np.ndarray, FrameTruth]:
    # A blob (hand, cable, furniture) covering one side of the card.
    corners = target.discs_px
    centre = corners.mean(axis=0)
    side = int(rng.integers(4))
    a, b = corners[side], corners[(side + 1) % 4]
    depth = rng.uniform(0.3, 0.7)
    inner_a = a + (corners[(side + 3) % 4] - a) * depth
    inner_b = b + (corners[(side + 2) % 4] - b) * depth
    outward = (a + b) / 2 - centre
    polygon = np.array([a + outward * 0.6, b + outward * 0.6, inner_b, inner_a])
    photos = builtin_photos()
    patch = photos[int(rng.integers(len(photos)))]
    image, mask = degrade.occlude(image, polygon, cv2.resize(patch, (image.shape[1], image.shape[0])))
    targets = []
    for t in truth.targets:
        if t.id != target.id:
            targets.append(t)
            continue
        covered = np.array([
            mask[int(round(y)), int(round(x))] > 0.5 if np.isfinite(x) else True for x, y in t.discs_px
        ])
        targets.append(TargetTruth(
            id=t.id, discs_px=t.discs_px, disc_visible=t.disc_visible & ~covered, distance_m=t.distance_m,
            facing_cos=t.facing_cos, disc_diameter_px=t.disc_diameter_px, occluded=True,
        ))
    return image, FrameTruth(truth.pose, truth.camera, targets, truth.degradation)


# --- named single-frame scenarios (training, tests, benchmarks) ---------------------


@dataclass(frozen=True)
class FrameScenario:
    """How to draw one single-frame test image: targets, distances, degradations.

    Attributes
    ----------
    name : str
    n_targets : tuple of int
        Inclusive range of the number of cards.
    distance_m, tilt_deg : tuple of float
        Ranges of the cards' depths (metres) and tilts (degrees).
    degradation : str
        Name of a `degrade.PRESETS` entry.
    marker_size_m : float
        Side of a card, metres.
    occlusion_probability : float
        Chance that a visible card is partly occluded.
    specular_on_target : bool
        Put a glare blob on the first card.
    clutter_tiles : tuple of int
        (rows, cols) of photo tiles on the background.
    focal_px : tuple of float
        Range of the pinhole camera's focal length, pixels.
    """

    name: str
    n_targets: tuple[int, int] = (1, 3)
    distance_m: tuple[float, float] = (0.8, 3.0)
    tilt_deg: tuple[float, float] = (0.0, 55.0)
    degradation: str = "default"
    marker_size_m: float = 0.2
    occlusion_probability: float = 0.0
    specular_on_target: bool = False
    clutter_tiles: tuple[int, int] = (3, 4)
    focal_px: tuple[float, float] = (700.0, 900.0)


#: The named single-frame scenarios, by name.
SCENARIOS: dict[str, FrameScenario] = {
    s.name: s
    for s in (
        FrameScenario("default"),
        FrameScenario("far", distance_m=(4.0, 8.0), tilt_deg=(0.0, 40.0)),
        FrameScenario("blur", degradation="blur"),
        FrameScenario("dark", degradation="dark"),
        FrameScenario("bright", distance_m=(1.5, 10.0), tilt_deg=(0.0, 50.0), degradation="bright"),
        FrameScenario("tiny", distance_m=(9.0, 13.0), tilt_deg=(0.0, 40.0)),
        FrameScenario("grazing", distance_m=(1.5, 6.0), tilt_deg=(60.0, 80.0)),
        FrameScenario("clutter", n_targets=(1, 2), clutter_tiles=(8, 10)),
        FrameScenario("specular", specular_on_target=True),
        FrameScenario("occluded", n_targets=(2, 3), occlusion_probability=1.0),
        FrameScenario("clean", degradation="none", tilt_deg=(0.0, 0.0)),
        FrameScenario("empty", n_targets=(0, 0)),
        FrameScenario("full", n_targets=(1, 4), distance_m=(0.5, 6.0), tilt_deg=(0.0, 65.0), degradation="full",
                      occlusion_probability=0.15),
    )
}


def scenario_frame(
    scenario: FrameScenario | str,
    rng: np.random.Generator,
    width: int = 640,
    height: int = 480,
    family: str = DEFAULT_FAMILY,
    photos: Sequence[np.ndarray] | None = None,
    artwork: Callable[[int], CardArtwork] | None = None,
) -> tuple[np.ndarray, FrameTruth]:
    """One rendered frame of a named scenario and its ground truth.

    The camera is a pinhole at the identity pose (looking along +z) with a focal
    length drawn from the scenario's range.

    Parameters
    ----------
    scenario : FrameScenario or str
        A scenario or the name of one in `SCENARIOS`.
    rng : numpy.random.Generator
        Draws everything: the same seed gives the same frame.
    width, height : int, optional
        Image size, pixels.
    family : str, optional
        Code family of the cards.
    photos : sequence of ndarray, optional
        Background photographs; by default `builtin_photos`.
    artwork : callable, optional
        Target id -> CardArtwork: the cards carry other markers in exactly the same
        places, with the same geometry and degradations for the same seed.

    Returns
    -------
    image : (height, width) ndarray of uint8
    truth : FrameTruth

    Raises
    ------
    KeyError
        If the scenario name is unknown.
    """
    spec = SCENARIOS[scenario] if isinstance(scenario, str) else scenario
    photos = photos if photos is not None else builtin_photos()
    camera = Camera.pinhole(float(rng.uniform(*spec.focal_px)), width, height)
    n = int(rng.integers(spec.n_targets[0], spec.n_targets[1] + 1))
    scene = single_frame_scene(
        rng, camera, n_targets=n, distance_m=spec.distance_m, tilt_deg=spec.tilt_deg,
        marker_size_m=spec.marker_size_m, family=family, photos=photos, clutter_tiles=spec.clutter_tiles,
    )
    if artwork is not None:
        scene = Scene(scene.background, [dataclasses.replace(t, artwork=artwork(t.id)) for t in scene.targets])
    degradation = degrade.PRESETS[spec.degradation].sample(rng)
    if spec.specular_on_target and scene.targets:
        truth = target_truth(camera, Pose.identity(), scene.targets[0])
        if truth is not None:
            x, y = np.nanmean(truth.discs_px, axis=0)
            spread = max(truth.disc_diameter_px, 4.0)
            specular = degrade.Specular(
                centre_rel=(float(x + rng.normal(0, spread)) / (width - 1), float(y + rng.normal(0, spread)) / (height - 1)),
                radius_rel=float(rng.uniform(0.5, 1.5)) * spread / min(width, height),
                strength=float(rng.uniform(0.4, 0.9)),
            )
            degradation = dataclasses.replace(degradation, specular=specular)
    return render_frame(scene, camera, Pose.identity(), rng, degradation, spec.occlusion_probability)


def render_walk(
    scene: Scene,
    camera: Camera,
    poses: Sequence[Pose],
    rng: np.random.Generator,
    degradation: str | degrade.DegradationRanges = "default",
    supersample: int = 2,
    blur: Sequence[ExposureBlur] | None = None,
    video: PhoneVideo | None = None,
    fps: float = FPS,
    follow_path: bool = False,
    lens: degrade.ThinLens | None = None,
    lighting: Lighting | None = None,
    readouts: Sequence[RollingReadout] | None = None,
) -> Iterator[tuple[np.ndarray, FrameTruth]]:
    """Frames of a camera walk, each with its own sampled degradation, and their truth.

    Parameters
    ----------
    scene : Scene
    camera : Camera
    poses : sequence of Pose
        Map-to-camera transforms, one per frame (with `blur`, at mid-exposure).
    rng : numpy.random.Generator
        Draws each frame's degradation and noise, in frame order.
    degradation : str or DegradationRanges, optional
        Name of a `degrade.PRESETS` entry, or the ranges themselves.
    supersample : int, optional
        Samples per pixel along each axis (`render`).
    blur : sequence of ExposureBlur, optional
        Each frame's motion blur from the camera's motion (`Walk.exposure_blur`): it
        replaces the preset's random one, the frame's other degradations are drawn as
        without it.
    video : PhoneVideo, optional
        Record the walk as a phone's video (`video.record`: H.264 encoded and decoded)
        instead of storing each frame as the preset says (its JPEG is left out; every
        other degradation is drawn as without it).
    fps : float, optional
        Frames a second, for the video's bit budget.
    follow_path : bool, optional
        With `blur`: render each frame along its exposure's path (`ExposureBlur.path`,
        the mean of the renders from the poses through the exposure, the truth at their
        average pose) instead of smearing it straight: a roll, a turn and the depths
        across the image blur each part of it as they do in a camera.
    lens : ThinLens, optional
        The lens's depth of field (`render_frame`).
    lighting : Lighting, optional
        The scene's lamps (`render_frame`).
    readouts : sequence of RollingReadout, optional
        Each frame's rolling-shutter readout (`Walk.readouts`, centred on the frame's
        pose; `render_frame`). None: a global shutter.

    Yields
    ------
    image : (height, width) ndarray of uint8
    truth : FrameTruth

    Raises
    ------
    ValueError
        If `blur` does not give one blur per pose.
    """
    ranges = degradation if isinstance(degradation, degrade.DegradationRanges) else degrade.PRESETS[degradation]
    if blur is not None and len(blur) != len(poses):
        raise ValueError(f"blur gives {len(blur)} frames for {len(poses)} poses")
    if readouts is not None and len(readouts) != len(poses):
        raise ValueError(f"readouts gives {len(readouts)} frames for {len(poses)} poses")

    def frames() -> Iterator[tuple[np.ndarray, FrameTruth]]:
        for k, pose in enumerate(poses):
            sampled = ranges.sample(rng)
            path: tuple[Pose, ...] = ()
            if blur is not None and follow_path and blur[k].path:
                path = blur[k].path
                pose = exposure_average(path)
                sampled = dataclasses.replace(sampled, blur_length=0.0, blur_angle=0.0)
            elif blur is not None:
                sampled = dataclasses.replace(sampled, blur_length=blur[k].length_px, blur_angle=blur[k].angle_rad)
            if video is not None:
                sampled = dataclasses.replace(sampled, jpeg_quality=None)
            yield render_frame(scene, camera, pose, rng, sampled, supersample=supersample, exposure=path, lens=lens,
                               lighting=lighting, readout=None if readouts is None else readouts[k])

    if video is None:
        yield from frames()
        return
    truths: deque[FrameTruth] = deque()

    def images() -> Iterator[np.ndarray]:
        for image, truth in frames():
            truths.append(truth)
            yield image

    for image in record(images(), fps, video):
        yield image, truths.popleft()
