"""Training batches cut straight out of a resident frame array, augmented on the device.

The frame cache of a (variant, setting) is one uint8 array (frames, H, W, 3);
``WindowSet`` holds it as a tensor on the training device when it fits (a
paper-scale setting at 112 px is ~3.9 GB) and builds every batch by index
arithmetic: row ``offset + start + t`` for t < clip_len. No worker processes,
no per-item Python, no host-to-device copy per step; augmentation is one
batched affine resample and a colour transform on the device.

Reproducible and resumable: the order of an epoch is a permutation drawn from
(seed, epoch), and the augmentation parameters of every window from (seed,
epoch) as one table, so a batch's content does not depend on the batch size,
the number of DDP ranks, or whether the run was resumed. The camera
augmentation's per-pixel sensor noise is the exception: it is drawn per batch
from (seed, epoch, rank, batch number), so it follows the batching too.
"""

from __future__ import annotations

import warnings
from typing import Iterator

import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F

from clothgap import seeding
from learn import predictions
from learn.dataset import FrameCache, subsequence_starts

AUG_PARAMS = 8        # shift, crop side, crop x, crop y, flip, brightness, contrast, saturation
CAMERA_PARAMS = 7     # exposure, white-balance gains r, g, b, tone gamma, vignetting, noise std
# The camera augmentation's ranges (train.augment_camera), each as wide as or wider than the heldout look's camera
# (assets/render_variants/heldout.toml: +-0.5 stop, +-8 % white balance, vignetting 0.3), so that look lies inside.
CAMERA_EXPOSURE_STOPS = 1.0     # linear radiance x 2^u, u uniform in +-1 stop
CAMERA_WHITE_BALANCE = 0.1      # per-channel linear gains uniform in 1 +- 0.1
CAMERA_TONE_GAMMA = 1.25        # encoded values ^ g, g log-uniform in [1 / 1.25, 1.25]: as likely darker as lighter
CAMERA_VIGNETTING = 0.3         # strength uniform in [0, 0.3]: the light lost at the corners (render.camera.vignette)
CAMERA_NOISE_STD = 0.02         # per-clip std uniform in [0, 0.02] of Gaussian noise on the encoded values
# What a training keeps free of its GPU's free memory beside its frames: a quarter of it, and at least 8 GiB (an
# lrcn at batch 16, 384 a class, peaked at 28,527 MiB (27.9 GiB) on its GPU with 24.2 GiB of training and
# validation frames: table3-arm384-h100x4.json's gpu_timings). A setting's training frames at 768 a class (~46 GB) then stay resident on an 80 GB
# GPU, where half its free memory would not hold them.
_KEEP_FREE_SHARE, _KEEP_FREE_MIN = 0.25, 8 << 30
# Rows travel to a device through two pinned buffers of this size: the host holds a chunk, not the set.
UPLOAD_CHUNK_BYTES = 64 << 20


def _fits_on_device(nbytes: int, device: torch.device) -> bool:
    if device.type != "cuda":
        return True
    free, _total = torch.cuda.mem_get_info(device)
    return nbytes <= free - max(_KEEP_FREE_SHARE * free, _KEEP_FREE_MIN)


def row_bytes(frames: np.ndarray) -> int:
    """Bytes of one row (one frame) of a frame array."""
    return int(np.prod(frames.shape[1:], dtype=np.int64)) * frames.dtype.itemsize


def _torch_dtype(frames: np.ndarray) -> torch.dtype:
    return torch.from_numpy(np.empty(0, frames.dtype)).dtype     # (not the read-only memmap itself: a warning)


def gather_rows(frames: np.ndarray, rows: np.ndarray, device: torch.device | str,
                chunk_bytes: int | None = None, pin_memory: bool = False) -> torch.Tensor:
    """``frames[rows]`` as a tensor on ``device``.

    ``frames`` is usually the frame cache's memory map: a setting's training rows at 384 sequences a class are
    ~23 GB. To a CUDA device they go ``chunk_bytes`` at a time (default ``UPLOAD_CHUNK_BYTES``) through two
    pinned buffers, the next chunk gathered while the last one copies, so a training's host memory does not
    grow with the data (one process a model, several models a host). On the CPU the gathered array is the
    tensor, unless ``chunk_bytes`` asks for the chunked path there too; with ``pin_memory`` it is gathered
    straight into pinned memory (one copy of the set on the host, not a pageable one and a pinned one)."""
    device = torch.device(device)
    rows = np.asarray(rows, dtype=np.int64)
    if len(rows) and (rows.min() < 0 or rows.max() >= len(frames)):
        raise IndexError(f"rows {rows.min()}..{rows.max()} of an array of {len(frames)} frames")
    cuda = device.type == "cuda"
    if not cuda and chunk_bytes is None and not pin_memory:
        return torch.from_numpy(np.ascontiguousarray(frames[rows]))
    shape = (len(rows),) + tuple(frames.shape[1:])
    out = torch.empty(shape, dtype=_torch_dtype(frames), device=device, pin_memory=not cuda and pin_memory)
    if not cuda and pin_memory:
        np.take(frames, rows, axis=0, out=out.numpy(), mode="clip")   # (checked above; no temporary)
        return out
    step = max(1, (UPLOAD_CHUNK_BYTES if chunk_bytes is None else chunk_bytes) // max(1, row_bytes(frames)))
    buffers = [torch.empty((min(step, len(rows)),) + shape[1:], dtype=out.dtype, pin_memory=cuda)
               for _ in range(2 if len(rows) > step else 1)]
    copied: list = [None] * len(buffers)
    for k, lo in enumerate(range(0, len(rows), step)):
        b = k % len(buffers)
        if copied[b] is not None:
            copied[b].synchronize()      # that buffer's last copy has left it
        n = min(step, len(rows) - lo)
        # mode "clip": the rows are checked above, and "raise" would gather through a temporary
        np.take(frames, rows[lo:lo + n], axis=0, out=buffers[b].numpy()[:n], mode="clip")
        out[lo:lo + n].copy_(buffers[b][:n], non_blocking=cuda)
        if cuda:
            copied[b] = torch.cuda.Event()
            copied[b].record(torch.cuda.current_stream(device))
    if cuda:
        torch.cuda.current_stream(device).synchronize()
    return out


class WindowSet:
    """The ``clip_len``-frame windows of some clips of a frame cache, as batches on ``device``.

    ``clips``: clip ids (every window of each), or ``{clip_id: window starts or
    None}`` (``learn.split.part_windows``). Clips the cache left out are skipped
    (the cache warned about them when it was built). ``targets``, when given,
    is a per-frame array aligned with the cache rows (e.g. the cloth's lattice,
    ``learn.geometry``) sliced like the frames.
    """

    def __init__(self, cache: FrameCache, clips, clip_len: int, clip_stride: int,
                 device: torch.device | str = "cpu", targets: np.ndarray | None = None):
        self.device = torch.device(device)
        self.clip_len, self.clip_stride = clip_len, clip_stride
        windows = clips if isinstance(clips, dict) else dict.fromkeys(clips)
        ids, offsets, lengths, starts, labels = [], [], [], [], []
        for cid, chosen in windows.items():
            clip = cache.clips.get(cid)
            if clip is None:
                continue
            found = subsequence_starts(clip.num_frames, clip_len, clip_stride)
            if chosen is not None:
                keep = set(chosen)
                found = [s for s in found if s in keep]
            if not found:
                warnings.warn(f"clip {cid} has {clip.num_frames} frames, fewer than clip_len={clip_len}; left out",
                              stacklevel=2)
            for s in found:
                ids.append(cid)
                offsets.append(clip.offset)
                lengths.append(clip.num_frames)
                starts.append(s)
                labels.append(clip.class_index)
        self.clip_ids = ids
        self.starts = torch.tensor(starts, dtype=torch.long)
        self.labels = torch.tensor(labels, dtype=torch.long)
        # Only the rows some window reads travel to the device; the row map re-bases them.
        frames = cache.frames
        if len(ids):
            used = np.unique(np.concatenate([np.arange(o, o + n) for o, n in
                                             dict(zip(offsets, lengths)).items()]))
        else:
            used = np.zeros(0, np.int64)
        row_of = np.full(frames.shape[0] if frames.shape[0] else 1, -1, np.int64)
        row_of[used] = np.arange(len(used))
        self.resident = _fits_on_device(len(used) * row_bytes(frames), self.device)
        if self.resident:
            self.frames = gather_rows(frames, used, self.device)
        else:       # batches are cut on the host and copied each step: pinned, so the copy does not block
            self.frames = gather_rows(frames, used, "cpu", pin_memory=self.device.type == "cuda")
        # The index tables a batch is cut with live where the frames do: a step of a resident set copies nothing
        # to the device (a copy from pageable host memory would make the host wait for the GPU every step).
        self._ix = self.device if self.resident else torch.device("cpu")
        self._starts_ix, self._labels_ix = self.starts.to(self._ix), self.labels.to(self._ix)
        self._offsets, self._lengths, self._row_of = (torch.as_tensor(a, dtype=torch.long, device=self._ix)
                                                      for a in (offsets, lengths, row_of))
        self.targets = None
        if targets is not None:
            self.targets = torch.from_numpy(np.ascontiguousarray(targets[used], dtype=np.float32)).to(self.device)

    def __len__(self) -> int:
        return len(self.clip_ids)

    def _on(self, t: torch.Tensor) -> torch.Tensor:
        return t.to(self.device, non_blocking=True)

    def _to_index_device(self, t: torch.Tensor) -> torch.Tensor:
        if self._ix.type == "cuda" and t.device.type == "cpu":
            return t.pin_memory().to(self._ix, non_blocking=True)
        return t.to(self._ix)

    # ---------------------------------------------------------------- batches

    def augment_table(self, seed: int, epoch: int) -> torch.Tensor:
        """(windows, 8) uniform draws in [0, 1) of one epoch: the same for every rank and batch size."""
        gen = torch.Generator().manual_seed(seeding.derive_int(seed, 0, seeding.TRAIN, "augment", epoch))
        return torch.rand(len(self), AUG_PARAMS, generator=gen)

    def camera_table(self, seed: int, epoch: int) -> torch.Tensor:
        """(windows, 7) uniform draws in [0, 1) of one epoch for ``camera_augment_batch``; a stream of its own, so
        that the ``augment_table`` of a run is the same with or without the camera augmentation."""
        gen = torch.Generator().manual_seed(seeding.derive_int(seed, 0, seeding.TRAIN, "augment_camera", epoch))
        return torch.rand(len(self), CAMERA_PARAMS, generator=gen)

    @staticmethod
    def camera_noise_seed(seed: int, epoch: int, rank: int = 0) -> int:
        """The seed that the sensor noise of each batch of this rank's epoch is derived from (``batches``)."""
        return seeding.derive_int(seed, rank, seeding.TRAIN, "augment_camera_noise", epoch)

    def order(self, seed: int, epoch: int, rank: int = 0, world: int = 1) -> torch.Tensor:
        """This rank's share of the epoch's shuffled window order (padded so every rank gets as many)."""
        return epoch_order(len(self), seed, epoch, rank, world)

    @torch.no_grad()
    def predict(self, model, batch_size: int = 256, amp: bool | None = None) -> pd.DataFrame:
        """``model``'s prediction frame (``learn.predictions``) on every window, in order, unaugmented, in eval
        mode (bf16 autocast on CUDA unless ``amp`` says otherwise)."""
        return prediction_frame(self, model.eval(), model.probs, batch_size, amp)

    def batches(self, batch_size: int, *, order: torch.Tensor | None = None, augment: torch.Tensor | None = None,
                drop_last: bool = False, crop: bool = True, camera: torch.Tensor | None = None,
                camera_noise_seed: int = 0) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]]:
        """(frames float (B, T, 3, H, W) in [0, 1], labels (B,), targets (B, T, ...) or None) on the device.

        ``order``: window indices in the order to visit (default: as listed);
        ``augment``: ``augment_table(seed, epoch)`` to augment, else None;
        ``crop``: the augmentation's random resized crop and flip (``augment_batch``);
        ``camera``: ``camera_table(seed, epoch)`` to pass the frames through an imperfect camera
        (``camera_augment_batch``, after ``augment``'s transforms), else None; ``camera_noise_seed``
        (``camera_noise_seed(seed, epoch, rank)``) and the batch's number seed its sensor noise.
        """
        # One copy an epoch of the order and the augmentation tables, none a step; from pinned memory, so that
        # the host does not wait for the GPU even then.
        order = torch.arange(len(self), device=self._ix) if order is None else self._to_index_device(order)
        augment = self._to_index_device(augment) if augment is not None else None
        camera = self._to_index_device(camera) if camera is not None else None
        # Seeding a generator on the device is host-side bookkeeping (CUDA's Philox seed and offset): no copy.
        noise = torch.Generator(device=self.device) if camera is not None else None
        stop = len(order) - (len(order) % batch_size if drop_last and len(order) >= batch_size else 0)
        steps = torch.arange(self.clip_len, device=self._ix)
        for number, lo in enumerate(range(0, stop, batch_size)):
            idx = order[lo:lo + batch_size]
            starts = self._starts_ix[idx]
            params = augment[idx] if augment is not None else None
            if params is not None:
                # Temporal shift of up to half a stride either way, kept inside the clip.
                half = self.clip_stride // 2
                shift = (params[:, 0] * (2 * half + 1)).long() - half
                starts = torch.minimum(torch.clamp(starts + shift, min=0), self._lengths[idx] - self.clip_len)
            rows = self._row_of[self._offsets[idx, None] + starts[:, None] + steps]      # (B, T)
            raw = self.frames[rows] if self.resident else self._on(self.frames[rows])
            x = raw.permute(0, 1, 4, 2, 3).float().div_(255)                                # (B, T, 3, H, W)
            if params is not None:
                x = augment_batch(x, self._on(params), crop=crop)
            if camera is not None:
                noise.manual_seed(seeding.derive_int(camera_noise_seed, number, seeding.TRAIN, "camera_noise"))
                x = camera_augment_batch(x, self._on(camera[idx]), noise)
            target = self.targets[self._on(rows)] if self.targets is not None else None
            yield x, self._on(self._labels_ix[idx]), target


def prediction_frame(windows, forward, probs, batch_size: int, amp: bool | None) -> pd.DataFrame:
    """The prediction frame (``learn.predictions``) of ``probs(forward(x))`` on every batch of ``windows`` (a
    ``WindowSet`` or a ``learn.shapes.ShapeSet``), in order; bf16 autocast on CUDA unless ``amp`` says otherwise."""
    amp = windows.device.type == "cuda" if amp is None else amp
    out = []
    with torch.no_grad(), torch.autocast(windows.device.type, dtype=torch.bfloat16, enabled=amp):
        for x, _, _ in windows.batches(batch_size):
            out.append(probs(forward(x)).float().cpu().numpy())
    table = np.concatenate(out) if out else np.empty((0, predictions.NUM_CLASSES), np.float32)
    return predictions.frame(windows.clip_ids, windows.starts.numpy(), windows.labels.numpy(), table)


def epoch_order(n: int, seed: int, epoch: int, rank: int = 0, world: int = 1) -> torch.Tensor:
    """This rank's share of an epoch's shuffled order of ``n`` windows, drawn from (seed, epoch) alone (padded so
    that every rank gets as many)."""
    gen = torch.Generator().manual_seed(seeding.derive_int(seed, 0, seeding.TRAIN, "order", epoch))
    perm = torch.randperm(n, generator=gen)
    if world > 1:
        pad = (-len(perm)) % world
        perm = torch.cat([perm, perm[:pad]])
        perm = perm[rank::world]
    return perm


def augment_batch(x: torch.Tensor, params: torch.Tensor, crop: bool = True) -> torch.Tensor:
    """Per clip, the same for all its frames: a random resized crop (70-100 % of the side), a
    horizontal flip and a brightness/contrast/saturation jitter of +-20 %, of float (B, T, 3, H, W).
    Without ``crop`` only the jitter: the cloth stays where its lattice target says it is.

    ``params``: (B, 8) uniform draws; columns 1-7 are read here (column 0 is the temporal shift).
    """
    b, t, c, h, w = x.shape
    if crop:
        x = _crop_and_flip(x, params)
    brightness, contrast, saturation = (0.8 + 0.4 * params[:, i].view(b, 1, 1, 1, 1) for i in (5, 6, 7))
    x = x * brightness
    mean = x.mean(dim=(1, 2, 3, 4), keepdim=True)
    x = (x - mean) * contrast + mean
    grey = x.mean(dim=2, keepdim=True)
    x = (x - grey) * saturation + grey
    return x.clamp_(0, 1)


def _crop_and_flip(x: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
    b, t, c, h, w = x.shape
    side = 0.7 + 0.3 * params[:, 1]
    # Crop centre in normalised coordinates, so that the crop stays inside the frame.
    cx = (2 * params[:, 2] - 1) * (1 - side)
    cy = (2 * params[:, 3] - 1) * (1 - side)
    flip = torch.where(params[:, 4] < 0.5, -1.0, 1.0)
    theta = torch.zeros(b, 2, 3, device=x.device, dtype=x.dtype)
    theta[:, 0, 0], theta[:, 0, 2] = side * flip, cx
    theta[:, 1, 1], theta[:, 1, 2] = side, cy
    theta = theta.repeat_interleave(t, dim=0)
    flat = x.reshape(b * t, c, h, w)
    grid = F.affine_grid(theta, list(flat.shape), align_corners=False)
    flat = F.grid_sample(flat, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return flat.reshape(b, t, c, h, w)


def camera_augment_batch(x: torch.Tensor, params: torch.Tensor, noise: torch.Generator | None = None) -> torch.Tensor:
    """The frames as an imperfect camera would have recorded them, of float (B, T, 3, H, W) sRGB-encoded in [0, 1].

    Per clip, the same for all its frames: an exposure error and white-balance gains on the linear values, the
    lens's vignetting (``render.camera.vignette``'s falloff), then a gamma on the encoded values (a tone curve that
    is not the one trained on); last, Gaussian sensor noise fresh per pixel and frame, drawn from ``noise`` (none
    without it), so that it is not smoothed by any resample. The ranges are the ``CAMERA_*`` constants.

    ``params``: (B, 7) uniform draws in [0, 1]: exposure, white balance r, g, b, tone gamma, vignetting, noise std;
    0.5 is no change for the first five, 0 no vignetting and no noise.
    """
    b, t, c, h, w = x.shape
    params = params.to(x.dtype)

    def per_clip(column: int) -> torch.Tensor:
        return params[:, column].view(b, 1, 1, 1, 1)

    gain = torch.exp2(CAMERA_EXPOSURE_STOPS * (2 * per_clip(0) - 1))
    white_balance = (1 + CAMERA_WHITE_BALANCE * (2 * params[:, 1:4] - 1)).view(b, 1, c, 1, 1)
    falloff = 1 - CAMERA_VIGNETTING * per_clip(5) * _corner_distance2(h, w, x.device, x.dtype)
    linear = srgb_to_linear(x) * (gain * white_balance) * falloff
    x = linear_to_srgb(linear.clamp_(0, 1))
    x = x.pow(CAMERA_TONE_GAMMA ** (2 * per_clip(4) - 1))
    if noise is not None:
        std = CAMERA_NOISE_STD * per_clip(6)
        x = x + torch.randn(x.shape, generator=noise, device=x.device, dtype=x.dtype) * std
    return x.clamp_(0, 1)


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer function's inverse (IEC 61966-2-1), of encoded values in [0, 1]."""
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer function (IEC 61966-2-1), of linear values in [0, 1]."""
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def _corner_distance2(h: int, w: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """(h, w): each pixel centre's squared distance from the image centre over the corners' (0.5), in image-relative
    coordinates: 0 at the centre, 1 at the corners, as ``render.camera.vignette`` measures it. Built on the device,
    so that no step copies it there."""
    y = (torch.arange(h, device=device, dtype=dtype) + 0.5) / h - 0.5
    x = (torch.arange(w, device=device, dtype=dtype) + 0.5) / w - 0.5
    return (y[:, None] ** 2 + x[None, :] ** 2) / 0.5
