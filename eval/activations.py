"""Where the CNN looks: conv5 activations over the frames (the paper's Fig. 6).

The paper overlays the fifth conv layer's activation, in the "jet" colour map, on
real frames to show that the network attends to the cloth and its moving edges
rather than the background. Here: the channel mean of the last ReLU of
``model.cnn.features`` (conv5), normalised over the whole clip (so frames are
comparable), upsampled bilinearly to the frame and blended over it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def conv5_maps(model, frames: np.ndarray) -> np.ndarray:
    """(T, H, W, 3) uint8 frames -> (T, H, W) activation in [0, 1] (clip-wide normalisation)."""
    import torch
    import torch.nn.functional as F
    from torch import nn

    relus = [m for m in model.cnn.features if isinstance(m, nn.ReLU)]
    if not relus:
        raise ValueError("model.cnn.features has no ReLU layer to read conv5 from")
    captured = {}
    hook = relus[-1].register_forward_hook(lambda _m, _i, out: captured.__setitem__("conv5", out.detach()))
    try:
        x = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float().div(255)
        device = next(model.parameters()).device
        with torch.no_grad():
            model(x.to(device)[None])   # the whole model: it adds the inputs its CNN reads (frame differences)
    finally:
        hook.remove()
    maps = captured["conv5"].mean(dim=1, keepdim=True)
    maps = F.interpolate(maps, size=frames.shape[1:3], mode="bilinear", align_corners=False)[:, 0].cpu().numpy()
    lo, hi = maps.min(), maps.max()
    return (maps - lo) / (hi - lo) if hi > lo else np.zeros_like(maps)


def overlay(frames: np.ndarray, maps: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """Frames blended with the jet-coloured maps, uint8."""
    from matplotlib import colormaps

    jet = colormaps["jet"](maps)[..., :3]
    blend = (1 - alpha) * frames / 255.0 + alpha * jet
    return (np.clip(blend, 0, 1) * 255).astype(np.uint8)


def overlay_figure(rows: dict[str, np.ndarray], model, picks: int = 4):
    """Per named clip (T, H, W, 3): a row of frames and a row of conv5 overlays, ``picks`` frames each."""
    from eval import figures

    images, labels = {}, []
    for name, frames in rows.items():
        idx = np.unique(np.linspace(0, len(frames) - 1, picks).round().astype(int))
        maps = conv5_maps(model, frames)
        images[name] = [frames[i] for i in idx]
        images[f"{name}: conv5"] = [overlay(frames[i:i + 1], maps[i:i + 1])[0] for i in idx]
        labels = [f"frame {i}" for i in idx]
    return figures.frame_grid(images, labels)


def clip_frames(clip_dir: Path, size: int) -> np.ndarray:
    """A rendered clip's frames at the model's input size (the same reader as prediction)."""
    from learn.dataset import read_frames

    return read_frames(clip_dir, size)
