"""Video compression as a phone records it: H.264 through a real encoder.

A phone's camera app does not store frames as JPEGs: it encodes the stream with H.264
(AVC) at a bit rate set for the resolution, a keyframe about every second and the other
frames predicted from the ones before, and what reaches the survey is the decoded video.
Its errors are not JPEG's: blocks copied from earlier frames with motion vectors
(edges that lag or smear by a fraction of a pixel), quantisation that grows with the
motion (a fast pan starves the bit budget) and flat areas that lose their texture.

`record` passes frames through libx264 and back through FFmpeg's decoder, frame by
frame (PyAV, whose wheels ship both), so a walk can be rendered, compressed and
detected as a stream. x264 stands in for a phone's hardware encoder: Main profile, no
B-frames, no look-ahead (``tune=zerolatency``: a phone encodes in real time and
streams), the ``veryfast`` preset's motion search, and the phone's bits per pixel.

Needs ``pip install 'fidotrack[sim]'`` (PyAV).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

__all__ = ["PHONE", "PhoneVideo", "record"]


@dataclass(frozen=True)
class PhoneVideo:
    """How a phone's camera app encodes its video.

    Attributes
    ----------
    bits_per_pixel : float
        Bits per pixel and frame. Phones record 1080p at 30 frames a second at about
        16-20 Mbit/s with H.264, 0.26-0.32 bits per pixel; lower is a phone short of
        storage or a video sent over a network (0.1 and below).
    keyframe_s : float
        Seconds between keyframes (intra-coded frames).
    preset : str
        x264's speed preset: how hard the encoder searches for motion.
    """

    bits_per_pixel: float = 0.28
    keyframe_s: float = 1.0
    preset: str = "veryfast"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.bits_per_pixel) and self.bits_per_pixel > 0):
            raise ValueError(f"bits_per_pixel must be positive, got {self.bits_per_pixel}")
        if not (np.isfinite(self.keyframe_s) and self.keyframe_s > 0):
            raise ValueError(f"keyframe_s must be positive, got {self.keyframe_s}")

    def bit_rate(self, width: int, height: int, fps: float) -> int:
        """The encoder's target bit rate for a video of this size and rate, bit/s.

        Parameters
        ----------
        width, height : int
            Frame size, px.
        fps : float
            Frames a second.

        Returns
        -------
        int
        """
        return int(round(self.bits_per_pixel * width * height * fps))


#: A phone's camera app at its default quality.
PHONE = PhoneVideo()


def record(frames: Iterable[np.ndarray], fps: float, video: PhoneVideo = PHONE) -> Iterator[np.ndarray]:
    """Each frame as it comes out of the phone's video: H.264-encoded, then decoded.

    Parameters
    ----------
    frames : iterable of (H, W) ndarray of uint8
        Greyscale frames in video order, all of one size (even width and height:
        H.264 codes 4:2:0 colour).
    fps : float
        Frames a second (sets the bit budget per frame and the keyframe interval).
    video : PhoneVideo, optional
        The encoder's settings.

    Yields
    ------
    (H, W) ndarray of uint8
        The decoded frames, one per input frame, in order.

    Raises
    ------
    ValueError
        If a frame is not a 2-D uint8 image of the first frame's size, or the size is odd.
    """
    import av  # the simulator's optional dependency

    encoder: av.video.codeccontext.VideoCodecContext | None = None
    decoder = av.CodecContext.create("h264", "r")
    shape: tuple[int, ...] | None = None
    for index, image in enumerate(frames):
        image = np.asarray(image)
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError(f"frame {index}: expected a 2-D uint8 image, got {image.dtype} {image.shape}")
        if encoder is None:
            shape = image.shape
            height, width = shape
            if width % 2 or height % 2:
                raise ValueError(f"H.264 with 4:2:0 colour needs an even frame size, got {width}x{height}")
            encoder = av.CodecContext.create("libx264", "w")
            encoder.width, encoder.height, encoder.pix_fmt = width, height, "yuv420p"
            encoder.framerate = Fraction(round(fps * 1000), 1000)
            encoder.time_base = 1 / encoder.framerate
            encoder.bit_rate = video.bit_rate(width, height, fps)
            encoder.gop_size = max(1, round(video.keyframe_s * fps))
            encoder.max_b_frames = 0
            encoder.profile = "Main"
            encoder.options = {"preset": video.preset, "tune": "zerolatency"}
        elif image.shape != shape:
            raise ValueError(f"frame {index}: size {image.shape} differs from the first frame's {shape}")
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="gray").reformat(format="yuv420p")
        frame.pts = index
        for packet in encoder.encode(frame):
            for decoded in decoder.decode(packet):
                yield decoded.to_ndarray(format="gray")
    if encoder is not None:
        for packet in encoder.encode(None):
            for decoded in decoder.decode(packet):
                yield decoded.to_ndarray(format="gray")
    for decoded in decoder.decode(None):
        yield decoded.to_ndarray(format="gray")
