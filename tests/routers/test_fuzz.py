"""Fuzzing the image and map endpoints: whatever a client sends, the reply is a 2xx or a
4xx with a JSON ``detail``, no exception escapes the application, and the server still
answers ``/livez`` afterwards.

Inputs are generated from fixed seeds (the same cases every run): random bytes, real
JPEG/PNG files with flipped bits, truncations, duplicated segments/chunks and edited
header fields (sizes, lengths, CRCs), wrong content types, empty bodies, lying
Content-Length headers, broken multipart forms, deeply nested / huge / NaN JSON, and the
hostile requests of a security review (cheap files that decode to gigabytes, bodies of
megabytes of JSON, extreme numbers in maps).

The whole module runs once per database engine (SQLite, PostgreSQL). Every reply's
status is tallied per engine; the last test checks that none was a 5xx, and that
PostgreSQL answered every case as SQLite did.
"""

from __future__ import annotations

import json
import random
import struct
import zlib
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.sim import scenes
from app.main import create_app
from app.settings import Settings
from tests.conftest import DATABASES, PostgresCluster, example_map

# --- the application under test, with a recorder of escaped exceptions ------------------


class _Recorder:
    """ASGI wrapper that remembers every exception the application lets escape (what a
    server would log as "Exception in ASGI application")."""

    def __init__(self, app: Any) -> None:
        self.app = app
        self.errors: list[tuple[str, BaseException]] = []

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        try:
            await self.app(scope, receive, send)
        except Exception as exc:
            self.errors.append((f"{scope.get('method', scope['type'])} {scope.get('path', '')}", exc))
            raise


#: Status codes of every reply of this module's tests, per database engine.
TALLY: dict[str, Counter[int]] = {engine: Counter() for engine in DATABASES}


class Fuzz:
    def __init__(self, client: TestClient, recorder: _Recorder, environment_id: int, engine: str) -> None:
        self.client = client
        self.recorder = recorder
        self.environment_id = environment_id
        self.engine = engine
        self.failures: list[str] = []
        self.count = 0

    def check(self, case: str, send: Callable[[], Any]) -> None:
        """Send one request and record what is wrong with the reply, if anything."""
        self.count += 1
        before = len(self.recorder.errors)
        try:
            reply = send()
        except Exception as exc:  # the client itself blew up: a dead connection/server
            self.failures.append(f"{case}: request raised {exc!r}")
            return
        TALLY[self.engine][reply.status_code] += 1
        escaped = self.recorder.errors[before:]
        if escaped:
            self.failures.append(f"{case}: application raised {escaped[0][1]!r}")
        problem = _problem(reply)
        if problem:
            self.failures.append(f"{case}: {problem}")

    def assert_clean(self) -> None:
        assert self.client.get("/livez").status_code == 200
        shown = "\n".join(self.failures[:40])
        assert not self.failures, f"{len(self.failures)} of {self.count} cases failed:\n{shown}"


def _problem(reply: Any) -> str | None:
    status = reply.status_code
    if 200 <= status < 300:
        try:
            reply.json()
        except ValueError:
            return f"{status} with a body that is not JSON: {reply.content[:80]!r}"
        return None
    if not 400 <= status < 500:
        return f"status {status}: {reply.content[:200]!r}"
    try:
        body = reply.json()
    except ValueError:
        return f"{status} with a body that is not JSON: {reply.content[:80]!r}"
    detail = body.get("detail") if isinstance(body, dict) else None
    if isinstance(detail, str) and detail:
        return None
    return f"{status} without a detail message: {body!r:.200}"


@pytest.fixture(scope="module", params=DATABASES)
def server(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
           ) -> Iterator[tuple[TestClient, _Recorder, int, str]]:
    database_url = None
    if request.param == "postgresql":
        cluster: PostgresCluster = request.getfixturevalue("postgres_cluster")
        name = cluster.new_database()
        request.addfinalizer(lambda: cluster.drop_database(name))  # after the service below stops
        database_url = cluster.url(name)
    # Thousands of requests from one client, as fast as they go: no request rate limit.
    settings = Settings(data_dir=tmp_path_factory.mktemp("fuzz") / "data", database_url=database_url,
                        max_image_bytes=256 * 1024, max_image_pixels=5_000_000, request_rate_per_address=0)
    recorder = _Recorder(create_app(settings))
    with TestClient(recorder, raise_server_exceptions=False) as client:  # type: ignore[arg-type]
        env = client.post("/environments", json={"name": "fuzz", "marker_size_m": 0.2})
        assert env.status_code == 201, env.text
        environment_id = env.json()["id"]
        assert client.put(f"/environments/{environment_id}/map", json=example_map(3)).status_code == 200
        yield client, recorder, environment_id, request.param


@pytest.fixture
def fuzz(server: tuple[TestClient, _Recorder, int, str]) -> Fuzz:
    return Fuzz(*server)


# --- seed images and their mutations ---------------------------------------------------


@pytest.fixture(scope="module")
def seeds() -> dict[str, bytes]:
    image, _ = scenes.scenario_frame("clean", np.random.default_rng(5), width=160, height=120)
    colour = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return {
        "jpeg": cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes(),
        "jpeg_colour": cv2.imencode(".jpg", colour)[1].tobytes(),
        "jpeg_progressive": cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes(),
        "png": cv2.imencode(".png", image)[1].tobytes(),
        "png_rgba16": cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_GRAY2BGRA).astype(np.uint16) * 257)[1]
        .tobytes(),
    }


def _jpeg_segments(data: bytes) -> list[tuple[int, int]]:
    """(start, end) of each marker segment before the scan data."""
    out, i = [], 2
    while i + 4 <= len(data) and data[i] == 0xFF:
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        out.append((i, i + 2 + length))
        if data[i + 1] == 0xDA:  # start of scan: entropy-coded data follows
            break
        i += 2 + length
    return out


def _png_chunks(data: bytes) -> list[tuple[int, int, bytes]]:
    """(start, end, type) of each chunk."""
    out, i = [], 8
    while i + 12 <= len(data):
        (length,) = struct.unpack(">I", data[i : i + 4])
        out.append((i, i + 12 + length, data[i + 4 : i + 8]))
        i += 12 + length
    return out


def _png_chunk(kind: bytes, payload: bytes, good_crc: bool = True) -> bytes:
    crc = zlib.crc32(kind + payload) & 0xFFFFFFFF
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc if good_crc else crc ^ 1)


def _with_jpeg_size(data: bytes, width: int, height: int) -> bytes:
    for start, _ in _jpeg_segments(data):
        if data[start + 1] in (0xC0, 0xC1, 0xC2):
            return data[: start + 5] + struct.pack(">HH", height, width) + data[start + 9 :]
    raise AssertionError("no SOF segment")


def _with_png_ihdr(data: bytes, width: int, height: int, depth: int | None = None, colour: int | None = None,
                   good_crc: bool = True) -> bytes:
    ihdr = bytearray(data[16:29])
    ihdr[0:8] = struct.pack(">II", width, height)
    if depth is not None:
        ihdr[8] = depth
    if colour is not None:
        ihdr[9] = colour
    return data[:8] + _png_chunk(b"IHDR", bytes(ihdr), good_crc) + data[33:]


def many_scans_jpeg(side: int, scans: int) -> bytes:
    """A progressive JPEG whose last scan is repeated: each repeat is one more decoding
    pass over the whole image for a few dozen bytes of file."""
    data = cv2.imencode(".jpg", np.zeros((side, side), np.uint8), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    last = data.rindex(b"\xff\xda")
    return data[:-2] + data[last:-2] * scans + b"\xff\xd9"


def image_cases(seeds: dict[str, bytes]) -> list[tuple[str, bytes]]:
    """Deterministic list of (name, bytes): a few hundred images, most of them broken."""
    rng = random.Random(20240601)
    cases: list[tuple[str, bytes]] = [(f"valid {k}", v) for k, v in seeds.items()]
    cases += [("empty", b""), ("jpeg magic only", b"\xff\xd8\xff"), ("png magic only", b"\x89PNG\r\n\x1a\n"),
              ("soi eoi", b"\xff\xd8\xff\xd9"), ("gif", b"GIF89a\x01\x00\x01\x00\x00\x00\x00;"),
              ("bmp", b"BM" + bytes(60)), ("tiff", b"II*\x00" + bytes(60)), ("webp", b"RIFF\x00\x00\x00\x00WEBPVP8 "),
              ("svg", b'<svg xmlns="http://www.w3.org/2000/svg"/>'), ("utf8 text", "ü€😀".encode())]
    # Random bytes, bare and behind a real signature.
    for k in range(30):
        blob = rng.randbytes(rng.choice([1, 7, 64, 500, 3000]))
        prefix = [b"", b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff\xe0\x00\x10JFIF\x00"][k % 4]
        cases.append((f"random {k}", prefix + blob))
    for name in ("jpeg", "png", "jpeg_progressive"):
        data = seeds[name]
        # Bit flips anywhere, and concentrated in the header.
        for k in range(20):
            mutated = bytearray(data)
            span = len(data) if k % 2 else min(len(data), 200)
            for _ in range(rng.randint(1, 8)):
                mutated[rng.randrange(span)] ^= 1 << rng.randrange(8)
            cases.append((f"{name} bitflip {k}", bytes(mutated)))
        # Truncations at many points (and the tail kept, the middle cut out).
        for k, cut in enumerate(sorted({1, 2, 3, 4, 8, 16, 33, len(data) - 1, len(data) - 2}
                                       | {rng.randrange(len(data)) for _ in range(12)})):
            cases.append((f"{name} truncated at {cut}", data[:cut]))
            if k % 3 == 0:
                cases.append((f"{name} middle cut at {cut}", data[:cut] + data[-12:]))
        # Overwritten runs of bytes, trailing garbage, doubled file.
        for k in range(6):
            start = rng.randrange(len(data))
            cases.append((f"{name} overwritten {k}", data[:start] + rng.randbytes(16) + data[start + 16 :]))
        cases.append((f"{name} trailing garbage", data + rng.randbytes(300)))
        cases.append((f"{name} twice", data + data))
    jpeg, png = seeds["jpeg"], seeds["png"]
    # JPEG segments: duplicated, dropped, lengths edited.
    for start, end in _jpeg_segments(jpeg):
        marker = jpeg[start + 1]
        cases.append((f"jpeg segment {marker:02x} doubled", jpeg[:end] + jpeg[start:end] + jpeg[end:]))
        cases.append((f"jpeg segment {marker:02x} dropped", jpeg[:start] + jpeg[end:]))
        for length in (0, 1, 2, 0xFFFF):
            cases.append((f"jpeg segment {marker:02x} length {length}",
                          jpeg[: start + 2] + struct.pack(">H", length) + jpeg[start + 4 :]))
    for width, height in [(30000, 30000), (0, 0), (0, 120), (160, 0), (1, 1), (65535, 65535), (65535, 1),
                          (161, 120), (80, 60), (1, 30000), (20, 20)]:
        cases.append((f"jpeg SOF {width}x{height}", _with_jpeg_size(jpeg, width, height)))
    sof = next(s for s, _ in _jpeg_segments(jpeg) if jpeg[s + 1] == 0xC0)
    for offset, value in [(4, 0), (4, 12), (4, 16), (9, 0), (9, 3), (9, 255), (11, 0x00), (11, 0xFF), (12, 9)]:
        cases.append((f"jpeg SOF byte {offset}={value}", jpeg[: sof + offset] + bytes([value]) + jpeg[sof + offset + 1 :]))
    cases.append(("jpeg SOF -> SOF3 (lossless)", jpeg[: sof + 1] + b"\xc3" + jpeg[sof + 2 :]))
    cases.append(("jpeg SOF -> SOF9 (arithmetic)", jpeg[: sof + 1] + b"\xc9" + jpeg[sof + 2 :]))
    # PNG chunks: duplicated, dropped, CRCs broken, IHDR fields edited.
    for start, end, kind in _png_chunks(png):
        cases.append((f"png chunk {kind!r} doubled", png[:end] + png[start:end] + png[end:]))
        cases.append((f"png chunk {kind!r} dropped", png[:start] + png[end:]))
        cases.append((f"png chunk {kind!r} bad crc", png[: end - 1] + bytes([png[end - 1] ^ 0xFF]) + png[end:]))
        cases.append((f"png chunk {kind!r} length huge",
                      png[:start] + struct.pack(">I", 0x7FFFFFFF) + png[start + 4 :]))
    for width, height in [(30000, 30000), (0, 0), (0, 120), (1, 1), (2**31 - 1, 2**31 - 1), (2**32 - 1, 1),
                          (161, 120), (1, 30000), (20, 20), (6000, 6000)]:
        cases.append((f"png IHDR {width}x{height}", _with_png_ihdr(png, width, height)))
        cases.append((f"png IHDR {width}x{height} bad crc", _with_png_ihdr(png, width, height, good_crc=False)))
    for depth, colour in [(16, 0), (1, 0), (8, 2), (8, 3), (8, 4), (8, 6), (7, 0), (8, 5), (0, 0), (255, 255)]:
        cases.append((f"png IHDR depth {depth} colour {colour}", _with_png_ihdr(png, 160, 120, depth, colour)))
    # Valid PNGs of big images (zeros compress to almost nothing): decompression bombs,
    # one within the pixel limit of the fuzzed server (5 Mpx), one over it.
    for side in (2000, 6000):
        idat = zlib.compress(b"\x00" * (1 + side) * side, 9)
        cases.append((f"png bomb {side}x{side}", b"\x89PNG\r\n\x1a\n"
                      + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0))
                      + _png_chunk(b"IDAT", idat) + _png_chunk(b"IEND", b"")))
    cases.append(("png chunk length 0xFFFFFFFF", png[:33] + b"\xff\xff\xff\xff" + png[37:]))
    cases.append(("jpeg 2000 scans", many_scans_jpeg(400, 2000)))
    # Tiny and degenerate images that decode fine.
    for width, height in [(1, 1), (2, 2), (23, 23), (24, 24), (1, 2000), (2000, 1), (24, 2000), (3000, 30)]:
        gray = np.full((height, width), 128, np.uint8)
        cases.append((f"tiny png {width}x{height}", cv2.imencode(".png", gray)[1].tobytes()))
        cases.append((f"tiny jpeg {width}x{height}", cv2.imencode(".jpg", gray)[1].tobytes()))
    return cases


# --- the tests ----------------------------------------------------------------------------


def test_detect_raw_body(fuzz: Fuzz, seeds: dict[str, bytes]) -> None:
    cases = image_cases(seeds)
    assert len(cases) > 300
    content_types = ["image/jpeg", "image/png", "application/octet-stream", None]
    for k, (name, data) in enumerate(cases):
        headers = {"content-type": content_types[k % 4]} if content_types[k % 4] else {}
        fuzz.check(f"detect raw {name}", lambda: fuzz.client.post("/detect", content=data, headers=headers))
    fuzz.assert_clean()


@pytest.mark.parametrize("name", ["png chunk length 0xFFFFFFFF", "jpeg 2000 scans 4000x4000"])
def test_cheap_files_that_are_expensive_to_decode_are_refused_fast(fuzz: Fuzz, seeds: dict[str, bytes],
                                                                  name: str) -> None:
    """A few kB that a decoder would spend 10-20 s of CPU on each (one request per
    client thread would stall the service) are refused from their structure alone."""
    import time

    if name.startswith("png"):
        png = seeds["png"]
        data = png[:33] + b"\xff\xff\xff\xff" + png[37:]
    else:
        data = many_scans_jpeg(4000, 2000)
    assert len(data) < 200_000
    started = time.perf_counter()
    reply = fuzz.client.post("/detect", content=data, headers={"content-type": "image/jpeg"})
    assert time.perf_counter() - started < 1.0
    assert reply.status_code == 422 and reply.json()["detail"]


def test_detect_multipart(fuzz: Fuzz, seeds: dict[str, bytes]) -> None:
    cases = image_cases(seeds)[::3]  # every third: the decoder is the same as for raw bodies
    for name, data in cases:
        fuzz.check(f"detect multipart {name}",
                   lambda: fuzz.client.post("/detect?candidates=true", files={"image": ("f.jpg", data, "image/jpeg")}))
    jpeg = seeds["jpeg"]
    forms: list[tuple[str, dict[str, Any]]] = [
        ("image as text field", {"data": {"image": "not a file"}}),
        ("no fields", {"data": {"x": "1"}}),
        ("two images", {"files": [("image", ("a.jpg", jpeg, "image/jpeg")), ("image", ("b.jpg", jpeg, "image/jpeg"))]}),
        ("many fields", {"data": {f"f{i}": "v" for i in range(50)}, "files": {"image": ("a.jpg", jpeg, "image/jpeg")}}),
        ("empty file", {"files": {"image": ("a.jpg", b"", "image/jpeg")}}),
        ("odd filename", {"files": {"image": ("../../etc/passwd\x00.jpg", jpeg, "text/html")}}),
        ("no filename", {"files": {"image": (None, jpeg)}}),
    ]
    for name, kwargs in forms:
        fuzz.check(f"detect form {name}", lambda: fuzz.client.post("/detect", **kwargs))
    boundary = "b0undary"
    raw_forms = [
        ("no boundary", "multipart/form-data", b"--x\r\n"),
        ("empty boundary", "multipart/form-data; boundary=", b"--\r\n"),
        ("unterminated", f"multipart/form-data; boundary={boundary}",
         f'--{boundary}\r\nContent-Disposition: form-data; name="image"; filename="a.jpg"\r\n\r\n'.encode() + jpeg),
        ("no headers", f"multipart/form-data; boundary={boundary}", f"--{boundary}\r\n\r\nxx\r\n--{boundary}--".encode()),
        ("garbage", f"multipart/form-data; boundary={boundary}", random.Random(3).randbytes(2000)),
        ("empty body", f"multipart/form-data; boundary={boundary}", b""),
        ("header only", f"multipart/form-data; boundary={boundary}", f"--{boundary}--\r\n".encode()),
        ("bad disposition", f"multipart/form-data; boundary={boundary}",
         f"--{boundary}\r\nContent-Disposition: ;;;\r\n\r\nxx\r\n--{boundary}--\r\n".encode()),
        ("urlencoded", "application/x-www-form-urlencoded", b"image=%FF%D8%FF"),
    ]
    for name, content_type, body in raw_forms:
        fuzz.check(f"detect raw form {name}", lambda: fuzz.client.post(
            "/detect", content=body, headers={"content-type": content_type}))
    fuzz.assert_clean()


def test_detect_headers_and_lengths(fuzz: Fuzz, seeds: dict[str, bytes]) -> None:
    jpeg = seeds["jpeg"]
    for content_type in ["text/plain", "application/json", "image/gif", "image/png", "", "multipart/form-data",
                         "multipart/mixed; boundary=x", "image/jpeg; charset=utf-8", b"\xff/\xff", b"image/jpeg\x00"]:
        fuzz.check(f"detect content-type {content_type!r}", lambda: fuzz.client.post(
            "/detect", content=jpeg, headers={"content-type": content_type}))
    for length in ["99999999999999999999", "262145", "-1", "abc", "1e9", " 5", "0", str(len(jpeg) + 10)]:
        for body in (b"", jpeg):
            fuzz.check(f"detect content-length {length} body {len(body)}", lambda: fuzz.client.post(
                "/detect", content=body, headers={"content-type": "image/jpeg", "content-length": length}))
    fuzz.check("detect multipart content-length huge", lambda: fuzz.client.post(
        "/detect", content=b"--x\r\n", headers={"content-type": "multipart/form-data; boundary=x",
                                              "content-length": "99999999999"}))
    fuzz.check("detect body over limit", lambda: fuzz.client.post(
        "/detect", content=jpeg + bytes(300 * 1024), headers={"content-type": "image/jpeg"}))
    fuzz.check("detect body over limit, streamed", lambda: fuzz.client.post(
        "/detect", content=iter([jpeg] + [bytes(64 * 1024)] * 6), headers={"content-type": "image/jpeg"}))
    for query in ["candidates=maybe", "classifier_id=-1", "classifier_id=1e99", "classifier_id=99999999999999999999",
                  "family=", "family=%00", "family=" + "x" * 5000, "candidates=true&candidates=false"]:
        fuzz.check(f"detect query {query[:40]}", lambda: fuzz.client.post(
            f"/detect?{query}", content=jpeg, headers={"content-type": "image/jpeg"}))
    for method in ("get", "put", "delete", "patch"):
        fuzz.check(f"detect {method}", lambda: getattr(fuzz.client, method)("/detect"))
    fuzz.assert_clean()


def test_locate(fuzz: Fuzz, seeds: dict[str, bytes]) -> None:
    url = f"/environments/{fuzz.environment_id}/locate"
    for k, (name, data) in enumerate(image_cases(seeds)[::2]):
        query = ["", "?method=posit", "?estimate_focal=true", "?method=single"][k % 4]
        fuzz.check(f"locate {name}", lambda: fuzz.client.post(url + query, content=data,
                                                              headers={"content-type": "image/jpeg"}))
    jpeg = seeds["jpeg"]
    fuzz.check("locate multipart", lambda: fuzz.client.post(url, files={"image": ("a.jpg", jpeg, "image/jpeg")}))
    fuzz.check("locate empty", lambda: fuzz.client.post(url))
    for query in ["method=magic", "method=", "estimate_focal=2", "method=posit&method=mean"]:
        fuzz.check(f"locate query {query}", lambda: fuzz.client.post(f"{url}?{query}", content=jpeg))
    for env in ["0", "-1", "999999", str(2**63 - 1), str(2**63), "99999999999999999999999", "abc", "1.5", "%00"]:
        fuzz.check(f"locate environment {env}", lambda: fuzz.client.post(f"/environments/{env}/locate", content=jpeg))
    empty = fuzz.client.post("/environments", json={"name": "no map", "marker_size_m": 0.2}).json()["id"]
    fuzz.check("locate environment without map",
               lambda: fuzz.client.post(f"/environments/{empty}/locate", content=jpeg))
    fuzz.check("locate length lie", lambda: fuzz.client.post(
        url, content=jpeg, headers={"content-type": "image/jpeg", "content-length": "99999999999"}))
    fuzz.assert_clean()


# --- JSON: maps and environments ------------------------------------------------------------


def _mutate_json(value: Any, rng: random.Random) -> Any:
    """One random structural change somewhere in a JSON value."""
    replacements: list[Any] = [None, True, 0, -1, 1e308, -1e308, float("nan"), float("inf"), "", "x" * 1000, [],
                               {}, [[[]]], 2**70, -(2**70), 1.5, "nan", {"$ref": "#"}]
    if isinstance(value, dict) and value and rng.random() < 0.8:
        key = rng.choice(list(value))
        out = dict(value)
        roll = rng.random()
        if roll < 0.15:
            del out[key]
        elif roll < 0.25:
            out["extra_" + str(rng.randrange(100))] = rng.choice(replacements)
        else:
            out[key] = _mutate_json(value[key], rng)
        return out
    if isinstance(value, list) and value and rng.random() < 0.8:
        out_list = list(value)
        roll = rng.random()
        index = rng.randrange(len(out_list))
        if roll < 0.15:
            del out_list[index]
        elif roll < 0.3:
            out_list.append(out_list[index])
        else:
            out_list[index] = _mutate_json(out_list[index], rng)
        return out_list
    return rng.choice(replacements)


def _nested(depth: int, kind: str) -> str:
    return ("[" * depth + "]" * depth) if kind == "list" else ('{"a":' * depth + "1" + "}" * depth)


def json_bodies(rng: random.Random, valid: dict[str, Any], n_mutations: int) -> list[tuple[str, bytes]]:
    bodies: list[tuple[str, bytes]] = [
        ("empty", b""), ("null", b"null"), ("number", b"1"), ("string", b'"map"'), ("list", b"[]"), ("dict", b"{}"),
        ("NaN", b"NaN"), ("Infinity", b"Infinity"), ("truncated", json.dumps(valid).encode()[:-5]),
        ("not utf-8", b'{"name": "\xff\xfe"}'), ("utf-16", json.dumps(valid).encode("utf-16")),
        ("bom", b"\xef\xbb\xbf" + json.dumps(valid).encode()), ("lone surrogate", b'{"name": "\\ud800"}'),
        ("nul bytes", b'{"name": "a\\u0000b", "marker_size_m": 0.2}'), ("trailing junk", json.dumps(valid).encode() + b"}}"),
        ("duplicate keys", b'{"frame": "survey", "frame": "world"}'),
        ("huge number", b'{"marker_size_m": 1' + b"0" * 5000 + b"}"),
        ("huge exponent", b'{"marker_size_m": 1e999999999}'),
        ("huge string", json.dumps({"name": "x" * 2_000_000, "marker_size_m": 0.2}).encode()),
        ("random bytes", rng.randbytes(500)),
    ]
    for depth in (100, 1000, 100_000):
        for kind in ("list", "dict"):
            bodies.append((f"nested {kind} {depth}", _nested(depth, kind).encode()))
    for k in range(n_mutations):
        mutated = valid
        for _ in range(rng.randint(1, 3)):
            mutated = _mutate_json(mutated, rng)
        # allow_nan: NaN and Infinity go out as the bare words Python's json accepts.
        bodies.append((f"mutation {k}", json.dumps(mutated, allow_nan=True).encode()))
    return bodies


def test_put_map(fuzz: Fuzz) -> None:
    rng = random.Random(7)
    url = f"/environments/{fuzz.environment_id}/map"
    valid = example_map(3)
    bodies = json_bodies(rng, valid, 150)
    many = example_map(1)
    many["targets"] = [dict(many["targets"][0], id=i) for i in range(100_001)]
    bodies.append(("100001 targets", json.dumps(many).encode()))
    many["targets"] = many["targets"][:600]
    bodies.append(("600 targets, ids past the family", json.dumps(many).encode()))
    nan_map = json.loads(json.dumps(valid))
    nan_map["camera"]["K"][0][0] = float("nan")
    bodies.append(("NaN focal", json.dumps(nan_map).encode()))
    nan_map["camera"]["K"] = [[0, 0, 0], [0, 0, 0], [0, 0, 1]]
    bodies.append(("zero K", json.dumps(nan_map).encode()))
    nan_map["camera"]["K"] = [[1e308, 0, 1e308], [0, 1e308, -1e308], [0, 0, 1]]
    bodies.append(("extreme K", json.dumps(nan_map).encode()))
    for k, (name, body) in enumerate(bodies):
        content_type = "application/json" if k % 5 else "text/plain"
        fuzz.check(f"put map {name}", lambda: fuzz.client.put(url, content=body,
                                                             headers={"content-type": content_type}))
    fuzz.check("put map length lie", lambda: fuzz.client.put(
        url, content=b"{}", headers={"content-type": "application/json", "content-length": "99999999999"}))
    for env in ["0", "999999", "-3", "x"]:
        fuzz.check(f"put map environment {env}", lambda: fuzz.client.put(f"/environments/{env}/map", json=valid))
    # The last accepted map still works for locating (or is the valid one, put back).
    assert fuzz.client.put(url, json=valid).status_code == 200
    fuzz.check("locate after map fuzz", lambda: fuzz.client.post(
        f"/environments/{fuzz.environment_id}/locate",
        content=cv2.imencode(".png", np.full((120, 160), 200, np.uint8))[1].tobytes()))
    fuzz.assert_clean()


def test_maps_that_pass_validation_still_locate(fuzz: Fuzz, seeds: dict[str, bytes]) -> None:
    """Every mutated map the server accepts must be usable by /locate without a 5xx."""
    rng = random.Random(11)
    url = f"/environments/{fuzz.environment_id}/map"
    accepted = 0
    for name, body in json_bodies(rng, example_map(3), 80):
        if fuzz.client.put(url, content=body, headers={"content-type": "application/json"}).status_code != 200:
            continue
        accepted += 1
        fuzz.check(f"locate with map {name}", lambda: fuzz.client.post(
            f"/environments/{fuzz.environment_id}/locate", content=seeds["jpeg"]))
    assert accepted >= 3
    assert fuzz.client.put(url, json=example_map(3)).status_code == 200
    fuzz.assert_clean()


def test_create_environment(fuzz: Fuzz) -> None:
    rng = random.Random(9)
    for k, (name, body) in enumerate(json_bodies(rng, {"name": "site", "marker_size_m": 0.2}, 80)):
        content_type = "application/json" if k % 4 else "application/x-www-form-urlencoded"
        fuzz.check(f"create environment {name}", lambda: fuzz.client.post(
            "/environments", content=body, headers={"content-type": content_type}))
    for spec in [{"name": "a", "marker_size_m": 0.2, "marker_family": "nope"},
                 {"name": "a", "marker_size_m": 0.2, "classifier_id": -5},
                 {"name": "a\u0000", "marker_size_m": 0.2}, {"name": "\u202e" * 200, "marker_size_m": 1e-300}]:
        fuzz.check(f"create environment {spec!r:.60}", lambda: fuzz.client.post("/environments", json=spec))
    fuzz.check("list environments afterwards", lambda: fuzz.client.get("/environments"))
    fuzz.assert_clean()


def test_ids_beyond_64_bits(fuzz: Fuzz) -> None:
    for env in [str(2**63), "99999999999999999999999", "-99999999999999999999999"]:
        for method in ("get", "delete", "patch"):
            fuzz.check(f"{method} environment {env}", lambda: getattr(fuzz.client, method)(
                f"/environments/{env}", **({"json": {"name": "x"}} if method == "patch" else {})))
        fuzz.check(f"get map environment {env}", lambda: fuzz.client.get(f"/environments/{env}/map"))
        fuzz.check(f"put map environment {env}", lambda: fuzz.client.put(f"/environments/{env}/map",
                                                                        json=example_map(1)))
    for classifier_id in (2**63, 10**30, -(10**30)):
        fuzz.check(f"create environment classifier {classifier_id}", lambda: fuzz.client.post(
            "/environments", json={"name": "a", "marker_size_m": 0.2, "classifier_id": classifier_id}))
    fuzz.assert_clean()


# --- hostile requests -------------------------------------------------------------------


def _rendered_world() -> tuple[dict[str, Any], bytes]:
    """A map and a frame whose targets the detector finds, so that every pose method runs."""
    from app.core.geometry.camera import Camera, Pose
    from app.sim import degrade

    rng = np.random.default_rng(31)
    camera = Camera.pinhole(820.0, 640, 480)
    scene = scenes.single_frame_scene(rng, camera, n_targets=3, distance_m=(1.2, 2.0), tilt_deg=(0, 30))
    image, _ = scenes.render_frame(scene, camera, Pose.look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.6], up=(0.0, -1.0, 0.0)),
                                   rng, degrade.PRESETS["none"].sample(rng))
    return scene.map_document(camera), cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()


def test_hostile_requests(fuzz: Fuzz, seeds: dict[str, bytes]) -> None:
    """The requests of a security review, each once cheap to send and costly (or fatal)
    to serve: now each a prompt 4xx, or a 2xx where the input is valid."""
    client, env = fuzz.client, fuzz.environment_id
    jpeg = seeds["jpeg"]
    big_map = example_map(1)
    big_map["targets"] = [dict(big_map["targets"][0], id=i) for i in range(60_000)]
    fuzz.check("20 MB JSON map", lambda: client.put(f"/environments/{env}/map", content=json.dumps(big_map).encode(),
                                                      headers={"content-type": "application/json"}))
    many_keys = {**example_map(1), **{f"e{i}": 0 for i in range(100_000)}}
    fuzz.check("1 MB JSON of unknown keys", lambda: client.put(f"/environments/{env}/map", json=many_keys))
    fuzz.check("333-byte JPEG declaring 6324x6324", lambda: client.post(
        "/detect", content=_with_jpeg_size(jpeg, 6324, 6324)[:333] + b"\xff\xd9",
        headers={"content-type": "image/jpeg"}))
    rgba16 = cv2.imencode(".png", np.zeros((2000, 2000, 4), np.uint16))[1].tobytes()
    fuzz.check("16-bit RGBA PNG, 2000x2000", lambda: client.post("/detect", content=rgba16))
    fuzz.check("JPEG cut short, end marker added", lambda: client.post(
        "/detect", content=jpeg[: len(jpeg) // 2] + b"\xff\xd9"))
    sos = jpeg.index(b"\xff\xda")
    comment = b"\xff\xda" * 100
    fuzz.check("FF DA inside a comment", lambda: client.post(
        "/detect", content=jpeg[:sos] + b"\xff\xfe" + struct.pack(">H", len(comment) + 2) + comment + jpeg[sos:]))
    for path_id in ("1%20", "+1", "01", "1.0", "%D9%A1"):
        fuzz.check(f"delete environment {path_id}", lambda: client.delete(f"/environments/{path_id}"))
    for name in ("a\u0000b", "a\nb", "\u001b[31mred"):
        fuzz.check(f"environment named {name!r}", lambda: client.post(
            "/environments", json={"name": name, "marker_size_m": 0.2}))
    # Extreme but finite numbers: refused where they enter ...
    document, frame = _rendered_world()
    extreme = []
    for edit in ("K 1e300", "K 1e-300", "dist 1e300", "disc 1e307"):
        bad = json.loads(json.dumps(document))
        if edit.startswith("K"):
            bad["camera"]["K"][0][0] = bad["camera"]["K"][1][1] = float(edit.split()[1])
        elif edit.startswith("dist"):
            bad["camera"]["dist"][0] = 1e300
        else:
            bad["targets"][0]["discs"][0][0] = 1e307
        extreme.append((edit, bad))
    for edit, bad in extreme:
        fuzz.check(f"map with {edit}", lambda: client.put(f"/environments/{env}/map", json=bad))
    # ... and at the edges of what is accepted, every pose method still answers.
    edges = []
    for edit in ("K 1e7", "K 1e-3", "dist 1e4", "dist -1e4", "discs 1e6 away"):
        edge = json.loads(json.dumps(document))
        if edit.startswith("K"):
            edge["camera"]["K"][0][0] = edge["camera"]["K"][1][1] = float(edit.split()[1])
        elif edit.startswith("dist"):
            edge["camera"]["dist"] = [float(edit.split()[1])] * 5
        else:
            for target in edge["targets"]:
                target["discs"] = [[c + 9.9e5 for c in disc] for disc in target["discs"]]
        edges.append((edit, edge))
    accepted = 0
    for edit, edge in [("as rendered", document), *edges]:
        if client.put(f"/environments/{env}/map", json=edge).status_code != 200:
            continue
        accepted += 1
        for method in ("nonlinear", "posit", "mean", "single"):
            for focal in ("false", "true"):
                fuzz.check(f"locate {method} focal={focal}, map {edit}", lambda: client.post(
                    f"/environments/{env}/locate?method={method}&estimate_focal={focal}", content=frame))
    assert accepted == 6
    assert client.put(f"/environments/{env}/map", json=example_map(3)).status_code == 200
    fuzz.assert_clean()


# --- the tally -------------------------------------------------------------------------

def test_no_reply_was_a_5xx_and_postgresql_answers_as_sqlite(request: pytest.FixtureRequest,
                                                             server: tuple[TestClient, _Recorder, int, str]) -> None:
    # Runs last for each engine (it takes `server`, so it comes at the end of each engine's run).
    engine = server[3]
    tally = TALLY[engine]
    assert tally and not [s for s in tally if s >= 500], tally
    module = request.node.module
    selected = {item.name.split("[")[0] for item in request.session.items if item.module is module}
    every = {name for name in dir(module) if name.startswith("test_")}
    if selected != every:  # a -k selection, not a full run of this module
        return
    if engine != "sqlite" and TALLY["sqlite"]:  # (a run of one engine's variants alone has nothing to compare with)
        assert tally == TALLY["sqlite"], f"{engine} answered otherwise than SQLite: {tally} against {TALLY['sqlite']}"
