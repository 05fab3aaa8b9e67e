"""The render stage's settings (no heavy imports here)."""

from __future__ import annotations

from dataclasses import dataclass

from clothgap import checks

# frames_per_launch = 0 ("auto") resolves per backend. On CPU backends batching does not pay (the path tracer
# already keeps every core busy: 0.8-1.07x measured). On a GPU it amortises launch overhead, but a batched frame
# is noisier at equal spp (next-event estimation spreads over every slot's lights: RMS error x1.6 at K=4, x2.0
# at K=8, measured), so it stays 1 until benchmarks/render_throughput.py shows equal_noise_frames_per_s above
# the baseline on the GPU; then set the cuda entry to the best K (or pass render.frames_per_launch=K).
AUTO_FRAMES_PER_LAUNCH = {"cuda_ad_rgb": 1, "llvm_ad_rgb": 1, "scalar_rgb": 1}


@dataclass(frozen=True)
class RenderConfig:
    variants: tuple[str, ...] = ("paper",)  # names from the variant registry (`clothgap render --list-variants`)
    variant_settings: tuple[str, ...] = ()  # "VARIANT:SETTING" pairs: a variant named here is rendered (and
                                            # trained on) only for its listed settings, e.g. "grid:wind-adaptive"
                                            # (the paper's Table 3 has grid and colour on adaptive meshes only);
                                            # a variant not named here goes with every setting
    resolution: int = 64                    # square frames, pixels
    spp: int = 4                            # samples per pixel
    backend: str = "auto"                   # Mitsuba variant: "auto", "cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb"
    write_hdr: bool = True                  # also write linear OpenEXR frames (hdr/); tone mapping needs none
    write_png: bool = True                  # also write the tone-mapped frames as PNGs (ldr/) to look at; the
                                            # network reads frames.npy, written always (render.frames)
    pack_frames: bool = False               # the network's frames straight into one array a (variant, setting),
                                            # frames-<H>px.npy, instead of a frames.npy a clip: the frame cache at
                                            # the render resolution is that array, so the frames are on disk once
    frames_per_launch: int = 0              # frames of a clip per Mitsuba launch (render.batch); 1 = one scene,
                                            # one frame per render call; 0 = auto (AUTO_FRAMES_PER_LAUNCH)
    writer_threads: int = 4                 # threads that tone-map (and write EXR/PNG) while the next frames render
    frames_in_flight: int = 1               # frames finished on the device: how many are launched before the
                                            # oldest is read back (2: frame t+1's geometry and launch overlap
                                            # frame t's path tracing); the frames are the same either way
    reuse_scenes: bool = True               # one Mitsuba scene per structure, retargeted clip to clip (render.scene
                                            # ScenePool); False = a new scene per clip (on CUDA: an OptiX compile each)
    freeze: bool = True                     # replay mi.render's recorded kernels (dr.freeze) instead of re-tracing
                                            # them every frame: 1.8-2.7x per process on an H100, frames equal to
                                            # 1e-8. CUDA only: on llvm_ad_rgb the replay kept the BVH of the frame
                                            # it was recorded on (wrong frames), so it is ignored there

    def settings_of(self, variant: str, settings: list[str]) -> list[str]:
        """The settings (of ``settings``, in order) that ``variant`` is rendered for."""
        listed = [p.partition(":")[2] for p in self.variant_settings if p.partition(":")[0] == variant]
        return [s for s in settings if s in listed] if listed else list(settings)

    def problems(self) -> list[str]:
        """What is wrong with these settings, one message each (empty when they are valid).

        Every variant is looked up in the registry (``render.variants``: TOML files, no Mitsuba), so an
        unknown name or a broken variant file (e.g. an unknown tonemap) is found before any work."""
        from render.backend import BACKENDS
        from render.variants import VariantError, get_variant, list_variants

        out = []
        try:
            known = list_variants()
        except VariantError as e:                   # e.g. $CLOTHGAP_VARIANTS_DIR is not a folder
            return [f"render.variants: {e}"]
        out += checks.names("render.variants", self.variants, known, "render variant")
        for pair in self.variant_settings:
            variant, sep, setting = pair.partition(":")
            if not sep or not variant or not setting:
                out.append(f"render.variant_settings: {pair!r} is not of the form VARIANT:SETTING")
            elif variant not in self.variants:
                out.append(f"render.variant_settings: {pair!r} names variant {variant!r}, which is not in "
                           f"render.variants ({', '.join(self.variants)})")
        for name in dict.fromkeys(v for v in self.variants if v in known):
            try:
                get_variant(name)
            except VariantError as e:
                out.append(f"render.variants: {e}")
        out += checks.number("render.resolution", self.resolution, 1)
        out += checks.number("render.spp", self.spp, 1)
        out += checks.choice("render.backend", self.backend, BACKENDS)
        out += checks.number("render.frames_per_launch", self.frames_per_launch, 0)
        out += checks.number("render.writer_threads", self.writer_threads, 1)
        out += checks.number("render.frames_in_flight", self.frames_in_flight, 1)
        return out


def frames_per_launch(config: RenderConfig, mitsuba_variant: str) -> int:
    """The number of frames per launch ``config`` asks for on ``mitsuba_variant`` (resolving 0 = auto)."""
    if config.frames_per_launch < 0:
        raise ValueError(f"render.frames_per_launch must be >= 0 (0 = auto), got {config.frames_per_launch}")
    if config.frames_per_launch:
        return config.frames_per_launch
    return AUTO_FRAMES_PER_LAUNCH.get(mitsuba_variant, 1)
