"""FreeD D1 packets: bytes against packets written out by hand, the checksum, range
limits, round trips, and the axis and angle conventions against ground truth built
here from look-at vectors and from what Unreal's Live Link FreeD source does with the
bytes (its decoding and its FRotator matrix, written out in this file)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.core.freed import PACKET_SIZE, FreeDPacket, decode, encode, packet_from_pose, pose_from_packet

# --------------------------------------------------------------------------------------
# Ground truth, independent of the module
# --------------------------------------------------------------------------------------


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def look(eye: tuple[float, float, float], forward: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])
         ) -> tuple[np.ndarray, np.ndarray]:
    """Map-to-camera (R, t) of a camera at `eye` looking along `forward`, the image's top
    towards `up` (OpenCV's camera: rows of R are image right, image down, optical axis)."""
    z = _unit(forward)
    x = _unit(np.cross(z, up))  # image right: forward x up, in a right-handed map
    y = np.cross(z, x)  # image down
    R = np.stack([x, y, z])
    return R, -R @ np.asarray(eye, dtype=np.float64)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def checksum(body: bytes) -> int:
    return (0x40 - sum(body)) % 256


def ue_source_view(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """What Unreal's Live Link FreeD source makes of a packet: the camera's location (cm)
    and its axes (rows: forward X, right Y, up Z), in Unreal's world coordinates.

    As its LiveLinkFreeDSource.cpp does it: Yaw, Pitch, Roll from bytes 2, 5, 8 over
    32768 (negative values read by subtracting 0xFFFFFF, one count high); Position.X from
    FreeD Y, Position.Y from FreeD X, Position.Z from Z, each over 640 (cm); then
    FTransform(FRotator, Position), whose rotation rows are FRotationTranslationMatrix's.
    """
    def signed(offset: int, divisor: float) -> float:
        raw = (data[offset] << 16) | (data[offset + 1] << 8) | data[offset + 2]
        if data[offset] & 0x80:
            raw -= 0x00FFFFFF
        return raw / divisor

    yaw, pitch, roll = (math.radians(signed(o, 32768.0)) for o in (2, 5, 8))
    location = np.array([signed(14, 640.0), signed(11, 640.0), signed(17, 640.0)])
    SP, CP, SY, CY, SR, CR = (math.sin(pitch), math.cos(pitch), math.sin(yaw), math.cos(yaw),
                              math.sin(roll), math.cos(roll))
    axes = np.array([
        [CP * CY, CP * SY, SP],
        [SR * SP * CY - CR * SY, SR * SP * SY + CR * CY, -SR * CP],
        [-(CR * SP * CY + SR * SY), CY * SR - CR * SP * SY, CR * CP],
    ])
    return location, axes


def to_ue(v: np.ndarray) -> np.ndarray:
    """A map vector in Unreal's axes as the plugin maps FreeD's: X <- y, Y <- x, Z <- z."""
    return np.array([v[1], v[0], v[2]])


def grid_packet(rng: np.random.Generator) -> FreeDPacket:
    """A packet whose values lie on the wire's grid, so encoding loses nothing."""
    return FreeDPacket(
        camera_id=int(rng.integers(0, 256)),
        pan_deg=int(rng.integers(-180 * 32768, 180 * 32768 + 1)) / 32768,
        tilt_deg=int(rng.integers(-90 * 32768, 90 * 32768 + 1)) / 32768,
        roll_deg=int(rng.integers(-180 * 32768, 180 * 32768 + 1)) / 32768,
        x_mm=int(rng.integers(-(1 << 23), 1 << 23)) / 64,
        y_mm=int(rng.integers(-(1 << 23), 1 << 23)) / 64,
        z_mm=int(rng.integers(-(1 << 23), 1 << 23)) / 64,
        zoom=int(rng.integers(0, 1 << 24)), focus=int(rng.integers(0, 1 << 24)), user=int(rng.integers(0, 1 << 16)),
    )


# --------------------------------------------------------------------------------------
# Bytes
# --------------------------------------------------------------------------------------

#: camera 7; pan +90 deg (90 * 32768 = 0x2D0000), tilt -30 deg (-983040 = 0xF10000),
#: roll +0.5 deg (16384 = 0x004000); X +1000 mm (64000 = 0x00FA00), Y -2000 mm
#: (-128000 = 0xFE0C00), Z +1500 mm (96000 = 0x017700); zoom 0x123456, focus 0xABCDEF,
#: user 0xBEEF; checksum 0x40 minus the sum of the 28 bytes before it (0x962), mod 256.
HAND_PACKET = FreeDPacket(camera_id=7, pan_deg=90.0, tilt_deg=-30.0, roll_deg=0.5, x_mm=1000.0, y_mm=-2000.0,
                          z_mm=1500.0, zoom=0x123456, focus=0xABCDEF, user=0xBEEF)
HAND_BYTES = bytes.fromhex(
    "D1" "07"
    "2D0000" "F10000" "004000"
    "00FA00" "FE0C00" "017700"
    "123456" "ABCDEF" "BEEF"
    "DE"
)


def test_hand_written_packet_has_a_valid_checksum() -> None:
    assert len(HAND_BYTES) == PACKET_SIZE == 29
    assert sum(HAND_BYTES[:28]) == 0x962
    assert (0x40 - 0x962) % 256 == 0xDE == HAND_BYTES[28]


def test_encode_gives_the_hand_written_bytes() -> None:
    assert encode(HAND_PACKET) == HAND_BYTES


def test_decode_reads_the_hand_written_bytes() -> None:
    assert decode(HAND_BYTES) == HAND_PACKET


def test_a_level_camera_at_the_origin() -> None:
    # Everything zero but the type byte: the checksum is 0x40 - 0xD1 = 0x6F.
    expected = bytes([0xD1, 0x00] + [0x00] * 26 + [0x6F])
    assert encode(FreeDPacket(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)) == expected


@pytest.mark.parametrize(("field", "value", "offset", "raw"), [
    # The specification's own range ends: pan and roll +-180 deg, tilt +-90 deg.
    ("pan_deg", 180.0, 2, "5A0000"), ("pan_deg", -180.0, 2, "A60000"),
    ("tilt_deg", 90.0, 5, "2D0000"), ("tilt_deg", -90.0, 5, "D30000"),
    ("roll_deg", 180.0, 8, "5A0000"), ("roll_deg", -180.0, 8, "A60000"),
    # Positions: -131072 mm and nearly +131072 mm, one count (1/64 mm) either side of 0.
    ("x_mm", -131072.0, 11, "800000"), ("x_mm", 131072.0 - 1 / 64, 11, "7FFFFF"),
    ("y_mm", -1 / 64, 14, "FFFFFF"), ("z_mm", 1 / 64, 17, "000001"),
    # The smallest angle step, and rounding to the nearest count.
    ("pan_deg", -1 / 32768, 2, "FFFFFF"), ("tilt_deg", 0.6 / 32768, 5, "000001"),
])
def test_fields_sit_at_their_offsets_as_24_bit_twos_complement(field: str, value: float, offset: int,
                                                               raw: str) -> None:
    fields = dict(camera_id=1, pan_deg=0.0, tilt_deg=0.0, roll_deg=0.0, x_mm=0.0, y_mm=0.0, z_mm=0.0)
    fields[field] = value
    data = encode(FreeDPacket(**fields))
    assert data[offset:offset + 3] == bytes.fromhex(raw)
    others = bytearray(data[2:20])
    others[offset - 2:offset + 1] = b"\0\0\0"
    assert not any(others)
    assert data[28] == checksum(data[:28])


def test_zoom_focus_and_user_are_unsigned_big_endian() -> None:
    data = encode(FreeDPacket(255, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, zoom=0xFFFFFF, focus=0x000001, user=0xFFFF))
    assert data[1] == 0xFF
    assert data[20:23] == b"\xff\xff\xff" and data[23:26] == b"\x00\x00\x01" and data[26:28] == b"\xff\xff"


# --------------------------------------------------------------------------------------
# Limits and malformed packets
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("changes", [
    {"camera_id": -1}, {"camera_id": 256}, {"camera_id": 1.0}, {"camera_id": True},
    {"pan_deg": 180.0001}, {"pan_deg": -181.0}, {"roll_deg": 360.0},
    {"tilt_deg": 90.0001}, {"tilt_deg": -100.0},
    {"x_mm": 131072.0}, {"y_mm": -131072.01}, {"z_mm": 200_000.0},
    {"pan_deg": math.nan}, {"z_mm": math.inf},
    {"zoom": -1}, {"zoom": 1 << 24}, {"focus": 1 << 24}, {"user": 1 << 16}, {"user": -1},
])
def test_values_the_packet_cannot_carry_are_refused(changes: dict) -> None:
    fields = dict(camera_id=1, pan_deg=10.0, tilt_deg=5.0, roll_deg=0.0, x_mm=1.0, y_mm=2.0, z_mm=3.0)
    fields.update(changes)
    with pytest.raises(ValueError, match="FreeD"):
        encode(FreeDPacket(**fields))


def test_decode_refuses_wrong_length_type_and_checksum() -> None:
    with pytest.raises(ValueError, match="29 bytes"):
        decode(HAND_BYTES[:-1])
    with pytest.raises(ValueError, match="29 bytes"):
        decode(HAND_BYTES + b"\0")
    other_type = bytes([0xD0]) + HAND_BYTES[1:28]
    with pytest.raises(ValueError, match="type byte 0xD0"):
        decode(other_type + bytes([checksum(other_type)]))
    corrupted = bytearray(HAND_BYTES)
    corrupted[5] ^= 0x01
    with pytest.raises(ValueError, match="checksum"):
        decode(bytes(corrupted))


def test_decode_takes_out_of_spec_values_as_sent() -> None:
    body = bytes([0xD1, 3]) + bytes.fromhex("7FFFFF") + bytes(23)  # pan 256 deg minus a count
    packet = decode(body + bytes([checksum(body)]))
    assert packet.pan_deg == (2**23 - 1) / 32768


def test_a_camera_too_far_from_the_origin_is_refused_not_clamped() -> None:
    R, t = look((140.0, 0.0, 1.5), np.array([1.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="X"):
        packet_from_pose(R, t, camera_id=1)
    R, t = look((-131.0, 131.0, 1.5), np.array([1.0, 0.0, 0.0]))
    assert packet_from_pose(R, t, camera_id=1).x_mm == pytest.approx(-131_000.0)


def test_packet_from_pose_refuses_what_is_not_a_pose() -> None:
    R, t = look((1.0, 2.0, 1.5), np.array([1.0, 0.0, 0.0]))
    with pytest.raises(ValueError):
        packet_from_pose(R * np.array([[1.0], [1.0], [-1.0]]), t, camera_id=1)  # a reflection
    with pytest.raises(ValueError):
        packet_from_pose(R, [0.0, math.nan, 0.0], camera_id=1)
    with pytest.raises(ValueError, match="camera_id"):
        packet_from_pose(R, t, camera_id=300)


# --------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------


def test_packets_on_the_grid_round_trip_exactly() -> None:
    rng = np.random.default_rng(1)
    for _ in range(500):
        packet = grid_packet(rng)
        data = encode(packet)
        assert decode(data) == packet
        assert encode(decode(data)) == data


def test_poses_round_trip_through_the_angles() -> None:
    rng = np.random.default_rng(2)
    for _ in range(500):
        R = random_rotation(rng)
        centre = rng.uniform(-50.0, 50.0, size=3)
        packet = packet_from_pose(R, -R @ centre, camera_id=4)
        R2, t2 = pose_from_packet(packet)
        np.testing.assert_allclose(R2, R, atol=1e-12)
        np.testing.assert_allclose(-R2.T @ t2, centre, atol=1e-9)
        assert -180.0 <= packet.pan_deg <= 180.0 and -90.0 <= packet.tilt_deg <= 90.0
        assert -180.0 <= packet.roll_deg <= 180.0


def test_poses_survive_the_wire_to_its_resolution() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        R = random_rotation(rng)
        centre = rng.uniform(-20.0, 20.0, size=3)
        R2, t2 = pose_from_packet(decode(encode(packet_from_pose(R, -R @ centre, camera_id=4))))
        # 1/32768 degree per angle and 1/64 mm per axis, half of it after rounding.
        assert np.abs(R2 - R).max() < 3 * math.radians(0.5 / 32768)
        assert np.abs(-R2.T @ t2 - centre).max() <= 0.5 / 64 / 1000 + 1e-12


# --------------------------------------------------------------------------------------
# Conventions against look-at ground truth
# --------------------------------------------------------------------------------------

EYE = (1.0, 2.0, 1.5)


def _angles(forward: list[float], up: list[float] | None = None) -> tuple[float, float, float]:
    R, t = look(EYE, np.array(forward)) if up is None else look(EYE, np.array(forward), np.array(up))
    packet = packet_from_pose(R, t, camera_id=1)
    return packet.pan_deg, packet.tilt_deg, packet.roll_deg


def test_position_is_the_camera_centre_in_map_millimetres() -> None:
    R, t = look(EYE, np.array([1.0, 0.0, 0.0]))
    packet = packet_from_pose(R, t, camera_id=9, zoom=5, focus=6, user=7)
    assert (packet.x_mm, packet.y_mm, packet.z_mm) == pytest.approx((1000.0, 2000.0, 1500.0), abs=1e-9)
    assert (packet.camera_id, packet.zoom, packet.focus, packet.user) == (9, 5, 6, 7)
    assert packet_from_pose(R, t, camera_id=1).zoom == 0 and packet_from_pose(R, t, camera_id=1).focus == 0


@pytest.mark.parametrize(("forward", "pan"), [
    ([0.0, 1.0, 0.0], 0.0),  # along +y: the specification's zero
    ([1.0, 0.0, 0.0], 90.0),  # along +x: a pan to the right, clockwise seen from above
    ([-1.0, 0.0, 0.0], -90.0),
    ([1.0, 1.0, 0.0], 45.0),
    ([1.0, -1.0, 0.0], 135.0),
    ([-1.0, -1.0, 0.0], -135.0),
])
def test_pan_is_the_heading_from_plus_y_clockwise_seen_from_above(forward: list[float], pan: float) -> None:
    assert _angles(forward) == pytest.approx((pan, 0.0, 0.0), abs=1e-9)


def test_looking_along_minus_y_is_pan_180() -> None:
    pan, tilt, roll = _angles([0.0, -1.0, 0.0])
    assert abs(pan) == pytest.approx(180.0) and tilt == pytest.approx(0.0) and roll == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(("forward", "expected"), [
    ([0.0, math.cos(math.radians(30)), math.sin(math.radians(30))], (0.0, 30.0, 0.0)),  # 30 deg up
    ([math.cos(math.radians(20)), 0.0, -math.sin(math.radians(20))], (90.0, -20.0, 0.0)),  # 20 deg down
    ([1.0, 1.0, math.sqrt(2.0)], (45.0, 45.0, 0.0)),
])
def test_tilt_is_the_elevation_of_the_optical_axis(forward: list[float], expected: tuple) -> None:
    assert _angles(forward) == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize("angle", [20.0, -35.0, 170.0])
def test_roll_is_positive_clockwise_seen_from_behind(angle: float) -> None:
    # Looking along +x the camera's right is -y; rolled clockwise (seen from behind) by
    # `angle`, the image's top turns from +z towards the camera's right.
    a = math.radians(angle)
    up = np.array([0.0, -math.sin(a), math.cos(a)])
    assert _angles([1.0, 0.0, 0.0], list(up)) == pytest.approx((90.0, 0.0, angle), abs=1e-9)


def test_a_rolled_camera_puts_a_point_on_its_right_higher_in_the_image() -> None:
    # Clockwise roll seen from behind turns the image's content anticlockwise: a point
    # straight ahead and to the camera's right (-y when looking along +x) moves up the
    # image (smaller v in OpenCV's pixel convention).
    a = math.radians(10.0)
    R, t = look(EYE, np.array([1.0, 0.0, 0.0]), np.array([0.0, -math.sin(a), math.cos(a)]))
    assert packet_from_pose(R, t, camera_id=1).roll_deg == pytest.approx(10.0)
    x = R @ np.array([EYE[0] + 5.0, EYE[1] - 1.0, EYE[2]]) + t
    assert x[1] / x[2] < 0


def test_looking_straight_down_or_up_puts_the_turn_in_the_pan() -> None:
    # Straight down at the floor with the image's top towards +x: as a camera panned to
    # +x (90 deg) and tilted down by 90 deg, without roll.
    R, t = look(EYE, np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0]))
    packet = packet_from_pose(R, t, camera_id=1)
    assert (packet.pan_deg, packet.tilt_deg, packet.roll_deg) == pytest.approx((90.0, -90.0, 0.0), abs=1e-9)
    np.testing.assert_allclose(pose_from_packet(packet)[0], R, atol=1e-12)
    # Straight up with the image's top towards -y: panned to 0 and tilted up by 90 deg.
    R, t = look(EYE, np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0]))
    packet = packet_from_pose(R, t, camera_id=1)
    assert (packet.pan_deg, packet.tilt_deg, packet.roll_deg) == pytest.approx((0.0, 90.0, 0.0), abs=1e-9)
    np.testing.assert_allclose(pose_from_packet(packet)[0], R, atol=1e-12)


def test_the_rotation_order_is_roll_then_tilt_then_pan() -> None:
    """camera_to_map = Rz(-pan) @ Rx(tilt) @ Ry(roll), applied to a camera looking along
    +y with its right along +x and its top along +z (right-handed elementary rotations)."""
    def rx(a: float) -> np.ndarray:
        c, s = math.cos(a), math.sin(a)
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])

    def ry(a: float) -> np.ndarray:
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])

    def rz(a: float) -> np.ndarray:
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])

    rng = np.random.default_rng(4)
    for _ in range(100):
        pan, tilt, roll = rng.uniform(-180, 180), rng.uniform(-89, 89), rng.uniform(-180, 180)
        M = rz(-math.radians(pan)) @ rx(math.radians(tilt)) @ ry(math.radians(roll))
        right, forward, up = M[:, 0], M[:, 1], M[:, 2]
        R, t = look(EYE, forward, up)
        np.testing.assert_allclose(R[0], right, atol=1e-12)  # `look` agrees on the image's right
        packet = packet_from_pose(R, t, camera_id=1)
        assert (packet.pan_deg, packet.tilt_deg, packet.roll_deg) == pytest.approx((pan, tilt, roll), abs=1e-9)
        np.testing.assert_allclose(pose_from_packet(packet)[0], R, atol=1e-12)


# --------------------------------------------------------------------------------------
# What Unreal's Live Link FreeD source shows
# --------------------------------------------------------------------------------------


def test_unreal_places_its_camera_where_the_real_one_is() -> None:
    """Unreal's camera looks along its local +X, right +Y, up +Z; driven by the packet,
    it must look where the tracked camera looks, with the same up and right, at the same
    place, once the map is read in Unreal's axes (X <- y, Y <- x, Z <- z, centimetres)."""
    rng = np.random.default_rng(5)
    for _ in range(300):
        R = random_rotation(rng)
        centre = rng.uniform(-30.0, 30.0, size=3)
        data = encode(packet_from_pose(R, -R @ centre, camera_id=2))
        location, axes = ue_source_view(data)
        right, down, forward = R
        np.testing.assert_allclose(location, to_ue(centre) * 100.0, atol=0.01)  # 1/640 cm steps
        np.testing.assert_allclose(axes[0], to_ue(forward), atol=1e-5)
        np.testing.assert_allclose(axes[1], to_ue(right), atol=1e-5)
        np.testing.assert_allclose(axes[2], to_ue(-down), atol=1e-5)


def test_unreal_sees_the_look_at_cases() -> None:
    # Looking along map +x (pan 90): Unreal's yaw 90 looks along its +Y, which is map +x.
    R, t = look(EYE, np.array([1.0, 0.0, 0.0]))
    location, axes = ue_source_view(encode(packet_from_pose(R, t, camera_id=1)))
    np.testing.assert_allclose(location, [200.0, 100.0, 150.0])
    np.testing.assert_allclose(axes[0], [0.0, 1.0, 0.0], atol=1e-9)
    # 30 deg up: Unreal's pitch is positive up too.
    R, t = look(EYE, np.array([0.0, math.cos(math.radians(30)), math.sin(math.radians(30))]))
    _, axes = ue_source_view(encode(packet_from_pose(R, t, camera_id=1)))
    np.testing.assert_allclose(axes[0], [math.cos(math.radians(30)), 0.0, 0.5], atol=1e-6)
