"""FreeD D1 packets: the camera pose as studio renderers read it (docs/freed.md).

A D1 packet is 29 bytes: the type byte ``0xD1``, a camera id, pan, tilt and roll
(big-endian signed 24-bit, 1/32768 degree), X, Y and Z (big-endian signed 24-bit,
1/64 mm), zoom and focus (big-endian unsigned 24-bit raw counts), a 16-bit user field
and a checksum, ``(0x40 - sum of bytes 0..27) mod 256``.

The studio frame is the map's aligned world frame (right-handed, ``z`` up, metres):
FreeD ``X, Y, Z`` are the map's ``x, y, z`` in millimetres. Angles follow the FreeD
specification's definitions, which are also what Unreal's Live Link FreeD source assumes
when it turns them into an ``FRotator``:

* pan: heading about the vertical, 0 looking along ``+y``, positive turning towards
  ``+x`` (clockwise seen from above), in ``[-180, 180]``;
* tilt: elevation of the optical axis above the horizontal plane, positive up, in
  ``[-90, 90]``;
* roll: about the optical axis, positive clockwise as seen from behind the camera (the
  top of the image turns towards the camera's right), in ``[-180, 180]``.

Applied to a camera that looks along ``+y`` with its top towards ``+z``, roll comes
first (about the optical axis), then tilt (about the camera's right axis), then pan
(about the vertical): ``camera_to_map = Rz(-pan) @ Rx(tilt) @ Ry(roll)`` with right-
handed elementary rotations. Pure Python and numpy; no I/O.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from app.core.geometry import Pose

__all__ = [
    "ANGLE_SCALE",
    "PACKET_SIZE",
    "PACKET_TYPE",
    "POSITION_SCALE",
    "FreeDPacket",
    "decode",
    "encode",
    "packet_from_pose",
    "pose_from_packet",
]

#: Bytes in a D1 packet.
PACKET_SIZE = 29
#: The type byte of a D1 (camera position and orientation) packet.
PACKET_TYPE = 0xD1
#: Raw counts per degree of pan, tilt and roll.
ANGLE_SCALE = 32768
#: Raw counts per millimetre of X, Y and Z.
POSITION_SCALE = 64

_INT24_MIN, _INT24_MAX = -(1 << 23), (1 << 23) - 1
_UINT24_MAX = (1 << 24) - 1
_UINT16_MAX = (1 << 16) - 1
_CHECKSUM_SEED = 0x40
# Below this horizontal component of the optical axis (a unit vector) the camera looks
# straight up or down: pan and roll then turn about one axis and only their combination
# is defined, so all of it is put in the pan.
_VERTICAL_EPS = 1e-9


@dataclass(frozen=True)
class FreeDPacket:
    """The content of one D1 packet, in the units of the FreeD specification.

    Attributes
    ----------
    camera_id : int
        0..255; Unreal's Live Link names the subject ``Camera <camera_id>``.
    pan_deg, tilt_deg, roll_deg : float
        Degrees (see the module's docstring for the signs and order).
    x_mm, y_mm, z_mm : float
        Camera position in the studio frame, millimetres; ``z_mm`` is the height.
    zoom, focus : int
        Raw lens encoder counts, 0..0xFFFFFF; their meaning is set per lens by the receiver.
    user : int
        The 16-bit user ("spare") field, 0..0xFFFF.
    """

    camera_id: int
    pan_deg: float
    tilt_deg: float
    roll_deg: float
    x_mm: float
    y_mm: float
    z_mm: float
    zoom: int = 0
    focus: int = 0
    user: int = 0


def _checksum(body: bytes) -> int:
    return (_CHECKSUM_SEED - sum(body)) % 256


def _integer(name: str, value: object, high: int) -> int:
    if isinstance(value, bool):
        raise ValueError(f"FreeD {name} must be an integer, got {value!r}")
    try:
        number = operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ValueError(f"FreeD {name} must be an integer, got {value!r}") from None
    if not 0 <= number <= high:
        raise ValueError(f"FreeD {name} {number} is outside 0..{high}")
    return number


def _fixed(name: str, value: float, scale: int, limit: float | None, unit: str) -> int:
    """``value`` in raw counts, refused (not clamped, not wrapped) when out of range."""
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"FreeD {name} must be finite, got {value}")
    if limit is not None and abs(value) > limit:
        raise ValueError(f"FreeD {name} {value:g} {unit} is outside -{limit:g}..{limit:g} {unit}")
    raw = round(value * scale)
    if not _INT24_MIN <= raw <= _INT24_MAX:
        raise ValueError(f"FreeD {name} {value:g} {unit} does not fit the packet's 24 bits "
                         f"({_INT24_MIN / scale:g}..{_INT24_MAX / scale:g} {unit})")
    return raw


def encode(packet: FreeDPacket) -> bytes:
    """The 29 bytes of a D1 packet.

    Nothing is clamped or wrapped: a value the packet cannot carry is refused, so that a
    receiver never gets a pose that looks valid and is not the one measured. Angles are
    held to the specification's ranges (pan and roll -180..180, tilt -90..90 degrees),
    X, Y and Z to the 24-bit range (-131072 to +131071.98 mm). Values are rounded to the
    nearest count (1/32768 degree, 1/64 mm).

    Parameters
    ----------
    packet : FreeDPacket

    Returns
    -------
    bytes
        29 bytes, the last the checksum.

    Raises
    ------
    ValueError
        If the camera id is outside 0..255, an angle or position is not finite or is out
        of range, zoom or focus is outside 0..0xFFFFFF, or user outside 0..0xFFFF.
    """
    camera_id = _integer("camera_id", packet.camera_id, 255)
    angles = [_fixed("pan", packet.pan_deg, ANGLE_SCALE, 180.0, "deg"),
              _fixed("tilt", packet.tilt_deg, ANGLE_SCALE, 90.0, "deg"),
              _fixed("roll", packet.roll_deg, ANGLE_SCALE, 180.0, "deg")]
    position = [_fixed(axis, value, POSITION_SCALE, None, "mm")
                for axis, value in (("X", packet.x_mm), ("Y", packet.y_mm), ("Z", packet.z_mm))]
    zoom = _integer("zoom", packet.zoom, _UINT24_MAX)
    focus = _integer("focus", packet.focus, _UINT24_MAX)
    user = _integer("user", packet.user, _UINT16_MAX)
    body = bytearray([PACKET_TYPE, camera_id])
    for raw in angles + position:
        body += raw.to_bytes(3, "big", signed=True)
    body += zoom.to_bytes(3, "big") + focus.to_bytes(3, "big") + user.to_bytes(2, "big")
    body.append(_checksum(body))
    return bytes(body)


def decode(data: bytes) -> FreeDPacket:
    """A D1 packet's content.

    Values are taken as sent: a sender's pan of 200 degrees decodes as 200.

    Parameters
    ----------
    data : bytes
        One whole packet (a UDP datagram's payload).

    Returns
    -------
    FreeDPacket
        Angles in degrees and positions in millimetres, exact (raw counts over 32768 and 64).

    Raises
    ------
    ValueError
        If `data` is not 29 bytes long, is not a D1 packet, or its checksum is wrong.
    """
    data = bytes(data)
    if len(data) != PACKET_SIZE:
        raise ValueError(f"a FreeD D1 packet is {PACKET_SIZE} bytes, got {len(data)}")
    if data[0] != PACKET_TYPE:
        raise ValueError(f"not a FreeD D1 packet: type byte 0x{data[0]:02X}, expected 0x{PACKET_TYPE:02X}")
    expected = _checksum(data[:-1])
    if data[-1] != expected:
        raise ValueError(f"FreeD checksum 0x{data[-1]:02X} is wrong, the bytes give 0x{expected:02X}")

    def signed(offset: int, scale: int) -> float:
        return int.from_bytes(data[offset:offset + 3], "big", signed=True) / scale

    return FreeDPacket(
        camera_id=data[1],
        pan_deg=signed(2, ANGLE_SCALE), tilt_deg=signed(5, ANGLE_SCALE), roll_deg=signed(8, ANGLE_SCALE),
        x_mm=signed(11, POSITION_SCALE), y_mm=signed(14, POSITION_SCALE), z_mm=signed(17, POSITION_SCALE),
        zoom=int.from_bytes(data[20:23], "big"), focus=int.from_bytes(data[23:26], "big"),
        user=int.from_bytes(data[26:28], "big"),
    )


def _level_axes(pan: float, tilt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The optical axis, and the camera's right and up axes at roll 0 (radians in)."""
    sp, cp, st, ct = math.sin(pan), math.cos(pan), math.sin(tilt), math.cos(tilt)
    forward = np.array([ct * sp, ct * cp, st])
    right = np.array([cp, -sp, 0.0])  # horizontal at roll 0
    up = np.array([-sp * st, -cp * st, ct])  # right x forward
    return forward, right, up


def packet_from_pose(R: ArrayLike, t: ArrayLike, camera_id: int, zoom: int = 0, focus: int = 0,
                     user: int = 0) -> FreeDPacket:
    """The D1 packet of a camera pose in the aligned (world) map frame.

    The map frame must be right-handed with ``z`` up, in metres: a map aligned to the
    studio (docs/map-format.md, "Alignment"), for instance with an origin card lying face
    up on the floor. FreeD X, Y, Z are the camera centre's map ``x, y, z`` in millimetres;
    pan, tilt and roll are as in the module's docstring. When the camera looks straight
    up or down, pan and roll turn about the same axis: the pan takes all of it and the
    roll is 0.

    Parameters
    ----------
    R : (3, 3) array_like
        Rotation, map to camera, OpenCV's camera (x right, y down, z forward):
        ``x_cam = R @ X_map + t``.
    t : (3,) array_like
        Translation, metres.
    camera_id : int
        0..255.
    zoom, focus : int, optional
        Raw lens counts, 0..0xFFFFFF. 0 (the default) when there is no lens encoder:
        the specification leaves their meaning to a per-lens calibration in the receiver.
    user : int, optional
        The user field, 0..0xFFFF.

    Returns
    -------
    FreeDPacket

    Raises
    ------
    ValueError
        If `R` is not a rotation or the values are not finite, or if the packet cannot
        carry the result (a camera more than about 131 m from the origin along an axis,
        a camera id, zoom, focus or user out of range).
    """
    pose = Pose(R, t)  # checks shapes, finiteness and that R is a rotation
    position_mm = pose.position * 1000.0
    up_cam, forward = -pose.R[1], pose.R[2]  # with the optical axis, the image's up fixes the orientation
    horizontal = math.hypot(forward[0], forward[1])
    tilt = math.atan2(forward[2], horizontal)
    if horizontal < _VERTICAL_EPS:
        tilt = math.copysign(math.pi / 2, forward[2])
        # At roll 0 the image's top points along -heading when looking up, +heading down.
        sign = -1.0 if forward[2] > 0 else 1.0
        pan = math.atan2(sign * up_cam[0], sign * up_cam[1])
        roll = 0.0
    else:
        pan = math.atan2(forward[0], forward[1])
        _, right0, up0 = _level_axes(pan, tilt)
        roll = math.atan2(float(up_cam @ right0), float(up_cam @ up0))
    packet = FreeDPacket(
        camera_id=camera_id,
        pan_deg=math.degrees(pan), tilt_deg=math.degrees(tilt), roll_deg=math.degrees(roll),
        x_mm=float(position_mm[0]), y_mm=float(position_mm[1]), z_mm=float(position_mm[2]),
        zoom=zoom, focus=focus, user=user,
    )
    encode(packet)  # refuse here what could not be sent
    return packet


def pose_from_packet(packet: FreeDPacket) -> tuple[np.ndarray, np.ndarray]:
    """The map-to-camera pose a packet describes: `packet_from_pose` inverted.

    Parameters
    ----------
    packet : FreeDPacket
        Any angles are accepted (they are periodic); positions in millimetres.

    Returns
    -------
    R : (3, 3) ndarray
        Rotation, map to camera, OpenCV's camera (x right, y down, z forward).
    t : (3,) ndarray
        Translation in metres: ``x_cam = R @ X_map + t``.
    """
    pan, tilt, roll = (math.radians(a) for a in (packet.pan_deg, packet.tilt_deg, packet.roll_deg))
    forward, right0, up0 = _level_axes(pan, tilt)
    cr, sr = math.cos(roll), math.sin(roll)
    right = cr * right0 - sr * up0
    up = sr * right0 + cr * up0
    R = np.stack([right, -up, forward])
    centre = np.array([packet.x_mm, packet.y_mm, packet.z_mm], dtype=np.float64) / 1000.0
    return R, -R @ centre
