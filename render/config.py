"""The render stage's settings (no heavy imports here)."""

from __future__ import annotations

from dataclasses import dataclass

# frames_per_launch = 0 ("auto") resolves per backend: batching pays on a GPU, where one launch per frame
# leaves it idle; on CPU backends the path tracer already keeps every core busy, so one frame per launch.
AUTO_FRAMES_PER_LAUNCH = {"cuda_ad_rgb": 8, "llvm_ad_rgb": 1, "scalar_rgb": 1}


@dataclass(frozen=True)
class RenderConfig:
    variants: tuple[str, ...] = ("paper",)  # names from the variant registry (`clothgap render --list-variants`)
    resolution: int = 64                    # square frames, pixels
    spp: int = 4                            # samples per pixel
    backend: str = "auto"                   # Mitsuba variant: "auto", "cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb"
    write_hdr: bool = True                  # keep the linear OpenEXR frames beside the tone-mapped ones
    frames_per_launch: int = 0              # frames of a clip per Mitsuba launch (render.batch); 1 = one scene,
                                            # one frame per render call; 0 = auto (AUTO_FRAMES_PER_LAUNCH)
    writer_threads: int = 4                 # threads that tone-map and write EXR/PNG while the next frames render


def frames_per_launch(config: RenderConfig, mitsuba_variant: str) -> int:
    """The number of frames per launch ``config`` asks for on ``mitsuba_variant`` (resolving 0 = auto)."""
    if config.frames_per_launch < 0:
        raise ValueError(f"render.frames_per_launch must be >= 0 (0 = auto), got {config.frames_per_launch}")
    if config.frames_per_launch:
        return config.frames_per_launch
    return AUTO_FRAMES_PER_LAUNCH.get(mitsuba_variant, 1)
