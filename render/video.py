"""Video compression as a camera effect: encode a clip's frames with H.264 and decode them again (PyAV).

Real footage reaches the network through a codec: blocking, ringing and chroma
subsampling (yuv420p) that clean renders lack. Encoding in memory and decoding
the result gives exactly those artifacts at a chosen quality (CRF: 0 lossless,
23 default, 51 worst).
"""

from __future__ import annotations

import io
from fractions import Fraction

import numpy as np


def compress_frames(frames: list[np.ndarray], crf: int, fps: float = 25.0) -> list[np.ndarray]:
    """The (H, W, 3) uint8 frames as they come out of an H.264 round trip at ``crf``."""
    import av  # only the video-compression variants need PyAV

    if not frames:
        return []
    h, w = frames[0].shape[:2]
    # yuv420p needs even sides: pad by edge replication, crop after decoding.
    ph, pw = h + h % 2, w + w % 2
    buffer = io.BytesIO()
    with av.open(buffer, mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1000))
        stream.width, stream.height, stream.pix_fmt = pw, ph, "yuv420p"
        stream.options = {"crf": str(int(crf)), "preset": "veryfast"}
        for image in frames:
            padded = np.pad(image, ((0, ph - h), (0, pw - w), (0, 0)), mode="edge")
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(padded), format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    buffer.seek(0)
    with av.open(buffer, mode="r") as container:
        decoded = [f.to_ndarray(format="rgb24")[:h, :w] for f in container.decode(video=0)]
    if len(decoded) != len(frames):
        raise RuntimeError(f"H.264 round trip returned {len(decoded)} frames for {len(frames)}")
    return decoded
