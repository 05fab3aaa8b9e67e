"""A frame's composite, camera effects, tone map and 8-bit sRGB encoding on the render backend.

``ClipRenderer.finish`` makes the network's uint8 frame on the host, in numpy,
from the read-back float32 RGBA (16 bytes a pixel). ``DeviceFinish`` does the
same arithmetic in Dr.Jit arrays on the backend that rendered the frame
(cuda_ad_rgb, llvm_ad_rgb), so only the uint8 image crosses to the host (3 bytes
a pixel) and the host does no per-pixel work. One kernel over the H*W*3 output
values: each gathers its pixel's radiance and alpha from the film, composites
over the clip's background (uploaded once per clip), multiplies by the camera's
gain and lens falloff, applies the variant's operator (``render.tonemap``, the
same function as the host's) and looks its code up in ``encode_srgb8``'s table.

Why it gives the host's bytes: every step is the host's operation in the host's
precision (composite and gain in float32; vignetting, the curved operators and
the motion-blur average in float64), the curves and table are the host's own
(``render.tonemap``: the operators take the array namespace, the table is
``srgb8_table``), and a code depends only on which table entries a value lies
between. Add, multiply, divide and float conversions round the same way in
numpy and Dr.Jit (divisions by constants are kept exact through opaque values);
on llvm_ad_rgb the frames come out byte-identical (tests/test_render_tonemap_device.py).
On CUDA, ptxas may fuse a multiply and an add into one rounding (an fma), which
moves a value by an ulp or so: a code then differs by 1 where a value sits on a
code's step, never by more (codes are at least 1/3,300 apart).

What stays on the host (``unsupported`` says why; the stage then uses the host
path by itself): the scalar backend (no device arrays), sensor noise (drawn from
numpy's normal stream per frame), and several frames per launch (render.batch).
"""

from __future__ import annotations

import numpy as np

from render.camera import CameraState, adds_noise, camera_gain, vignette
from render.tonemap import OPERATORS, device_ops, encode_srgb8_device, srgb8_table, srgb_clip
from render.variants import RenderVariant


def unsupported(mitsuba_variant: str, variant: RenderVariant) -> str | None:
    """None when ``DeviceFinish`` can finish this variant's frames on ``mitsuba_variant``; else why not."""
    if not mitsuba_variant.startswith(("cuda", "llvm")):
        return f"{mitsuba_variant} has no device arrays"
    if adds_noise(variant):
        return "sensor noise is drawn on the host (numpy's normal stream per frame)"
    return None


class DeviceFinish:
    """Turns a frame's linear RGBA on the device (flat Float, H*W*4) into its uint8 sRGB image (flat, H*W*3)."""

    def __init__(self, mi, variant: RenderVariant, camera: CameraState, background: np.ndarray):
        import drjit as dr  # imported here: render.backend picks libLLVM before drjit is first imported

        reason = unsupported(mi.variant(), variant)
        if reason is not None:
            raise ValueError(f"frames of variant {variant.name!r} cannot be finished on the device: {reason}")
        self.dr = dr
        self.Float, self.Float64 = mi.Float, dr.float64_array_t(mi.Float)
        self.UInt32, self.UInt8 = dr.uint32_array_t(mi.Float), dr.uint8_array_t(mi.Float)
        h, w = background.shape[:2]
        self.shape = (h, w, 3)
        self.operator = OPERATORS[variant.tonemap]
        self.ops = device_ops(self.Float64)
        # Per-clip values are arrays (kernel inputs), never literals: a literal would make a kernel per clip.
        self.background = self.Float(np.ascontiguousarray(background, np.float32).ravel())
        self.gain = self.Float(camera_gain(camera))
        falloff = vignette(variant, h, w)
        self.falloff = None if falloff is None else self.Float64(falloff.ravel())
        # srgb_clip encodes the float32 recorded frame, the other operators their float64 result (as tonemap()).
        precision = np.float32 if self.operator is srgb_clip else np.float64
        base, inside = srgb8_table(precision)
        self.base = self.UInt32(base.astype(np.uint32))
        self.inside = (self.Float if precision is np.float32 else self.Float64)(inside)
        dr.eval(self.background, self.gain, self.falloff, self.base, self.inside)

    def __call__(self, linear):
        """The uint8 codes (flat UInt8, H*W*3, row-major RGB) of a frame's linear RGBA (flat Float, H*W*4)."""
        dr = self.dr
        h, w, _ = self.shape
        i = dr.arange(self.UInt32, h * w * 3)
        pixel, channel = i // 3, i % 3
        rgb = dr.gather(self.Float, linear, 4 * pixel + channel)
        alpha = dr.clip(dr.gather(self.Float, linear, 4 * pixel + 3), 0.0, 1.0)
        composite = rgb + (1.0 - alpha) * dr.gather(self.Float, self.background, i)  # rgb is premultiplied
        recorded = composite * dr.gather(self.Float, self.gain, channel)
        if self.falloff is not None:  # float32 x float64 in numpy: float64, then float32 after the clamp
            recorded = self.Float(self.Float64(recorded) * dr.gather(self.Float64, self.falloff, pixel))
        recorded = dr.maximum(recorded, 0.0)
        if self.operator is srgb_clip:
            display = recorded
        else:
            display = self.operator(self.Float64(recorded), self.ops)
        return self.UInt8(encode_srgb8_device(display, self.base, self.inside))

    def to_host(self, codes) -> np.ndarray:
        """Read a frame's codes back as an (H, W, 3) uint8 array."""
        return np.asarray(codes, np.uint8).reshape(self.shape)
