"""The render stage's settings (no heavy imports here)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RenderConfig:
    variants: tuple[str, ...] = ("paper",)  # names from the variant registry (`clothgap render --list-variants`)
    resolution: int = 64                    # square frames, pixels
    spp: int = 4                            # samples per pixel
    backend: str = "auto"                   # Mitsuba variant: "auto", "cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb"
    write_hdr: bool = True                  # keep the linear OpenEXR frames beside the tone-mapped ones
