"""The paper's CNN+LSTM and its three baselines, built by name.

Every model maps a batch of clips, float (B, T, 3, H, W) in [0, 1], to per-step
logits (B, T, 54) (plus (B, T, 6) stretching and (B, T, 9) bending logits with
``factored``). How steps become one answer is the model's ``readout``:
``"mean"`` trains on every step and averages the step probabilities (LRCN's
own recipe), ``"last"`` trains and predicts from the last step only.

With ``bottleneck`` the CNN is a pixels -> cloth-shape regressor: its geometry
head predicts the 8 x 8 lattice of each frame (trained on the simulation's own
lattice, ``learn.geometry``), and the recurrent layer and the class heads read
only that prediction and its change from the previous frame, never the CNN's
features. The class loss does not reach the CNN, so the network cannot learn a
clip's class from its texture (every clip has its own), which is how it
otherwise memorises training clips; it has to go through the shape the
simulation says carries the material (docs/learnability.md).

The models (lrcn, base1, base2, base3) are entries of ``learn.registry``, which
says which parts ``build_model`` puts together for each.
"""

from __future__ import annotations

from pathlib import Path
import torch
import torch.nn.functional as F
from torch import nn

from clothgap.errors import MissingInputError
from learn.config import IMAGE_SIZES, READOUTS
from learn.registry import get_model_entry
from sim.lattice import LATTICE

NUM_CLASSES = 54
GEOMETRY_DIM = LATTICE * LATTICE * 3    # the auxiliary target: the 8 x 8 lattice of cloth points (learn.geometry)
NUM_STRETCH = 6      # class index = NUM_BEND * stretching index + bending index
NUM_BEND = 9
# The frames' mean and spread (roughly ImageNet's), taken out inside the model so
# that every caller feeds plain [0, 1] pixels.
_PIXEL_MEAN, _PIXEL_STD = 0.45, 0.225


def _conv(c_in: int, c_out: int, k: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(c_in, c_out, k, stride=stride, padding=k // 2, bias=False), nn.BatchNorm2d(c_out),
            nn.ReLU(inplace=True)]


class FrameCNN(nn.Module):
    """Five conv layers in AlexNet's pattern (conv, normalisation, ReLU, max-pool) and fc6.

    Channels scale from ``width`` as AlexNet's 64-192-384-256-256 do, and the
    strides are AlexNet's (conv1 11x11 stride 4, three 3x3 stride-2 max-pools: 32
    in all), then an adaptive pool to size/32, at most 6x6 (AlexNet's grid at 224
    px) and at least 1x1 (32 px). A stride-16 variant learned no better on
    synthetic clips and cost 4x the time per step (1.66 vs 0.39 s at 112 px, CPU).
    Batch norm stands in for AlexNet's local response norm: trained from scratch
    on a few thousand clips, the LRN version's LSTM inputs barely differed
    between clips and the recurrent models hardly learned (tiny-batch tests).
    """

    def __init__(self, image_size: int, width: int, fc6: int, dropout: float = 0.5, in_channels: int = 3,
                 conv5_pool: bool = True):
        super().__init__()
        if image_size not in IMAGE_SIZES:
            raise ValueError(f"image_size={image_size}: must be a multiple of 16 from 32 to 224")
        c1, c2, c3, c4, c5 = width, 3 * width, 6 * width, 4 * width, 4 * width
        self.features = nn.Sequential(
            *_conv(in_channels, c1, 11, stride=4), nn.MaxPool2d(3, 2, padding=1),
            *_conv(c1, c2, 5), nn.MaxPool2d(3, 2, padding=1),
            *_conv(c2, c3, 3), *_conv(c3, c4, 3), *_conv(c4, c5, 3),
            *([nn.MaxPool2d(3, 2, padding=1)] if conv5_pool else []),
        )
        # Without the last max-pool fc6 sees conv5's own map (size/16, at most 7 x 7): the same
        # convolutions, four times the positions, for a head that has to say where the cloth is.
        grid = max(min(image_size // 32, 6), 1) if conv5_pool else min(image_size // 16, 7)
        self.pool = nn.AdaptiveAvgPool2d(grid)
        self.fc6 = nn.Sequential(nn.Flatten(), nn.Linear(c5 * grid * grid, fc6), nn.ReLU(inplace=True),
                                 nn.Dropout(dropout))
        self.out_features = fc6
        # He initialisation: torch's default shrinks activations layer by layer, and
        # a CNN trained from scratch then barely moves its features at first.
        for layer in self.modules():
            if isinstance(layer, (nn.Conv2d, nn.Linear)):
                nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
                if layer.bias is not None:
                    nn.init.zeros_(layer.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) in [0, 1] (C = 3, or 6 with frame differences) -> (N, fc6)."""
        return self.fc6(self.pool(self.features((x - _PIXEL_MEAN) / _PIXEL_STD)))


class TemporalGeometryHead(nn.Module):
    """The lattice of frame t from the fc6 features of frames t - w//2 .. t + w//2 (a convolution over
    time, the clip's first and last frames repeated at its ends): neighbouring frames tell where a
    point that one frame shows poorly has gone."""

    def __init__(self, in_features: int, out_features: int, window: int):
        super().__init__()
        self.window = window
        self.conv = nn.Conv1d(in_features, out_features, window)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        """(B, T, in_features) -> (B, T, out_features)."""
        half = self.window // 2
        x = F.pad(feats.transpose(1, 2), (half, half), mode="replicate")
        return self.conv(x).transpose(1, 2)


class ClipClassifier(nn.Module):
    """A FrameCNN on every frame, optionally a recurrent layer over frames, per-step heads."""

    def __init__(self, cnn: FrameCNN, temporal: str | None, hidden: int, readout: str = "mean",
                 factored: bool = False, freeze_cnn: bool = False, num_classes: int = NUM_CLASSES,
                 motion: bool = False, geometry_dim: int = 0, bottleneck: bool = False,
                 bottleneck_noise: float = 0.0, geometry_window: int = 1):
        super().__init__()
        # motion: each frame goes in beside its difference from the previous frame (zero for the
        # first), so the first convolution sees motion directly, not only through the recurrence.
        # geometry_dim: a per-frame regression head on the CNN's features (learn.geometry), trained
        # as an auxiliary target and unused at prediction.
        self.motion, self.geometry_dim = motion, geometry_dim
        if bottleneck and not geometry_dim:
            raise ValueError("bottleneck needs the geometry head (geometry_dim > 0)")
        self.bottleneck, self.bottleneck_noise = bottleneck, bottleneck_noise
        self.channels_last = False   # set by the trainer on CUDA: the convolutions' fast layout
        if readout not in READOUTS:
            raise ValueError(f"readout={readout!r}: known readouts are {', '.join(READOUTS)}")
        self.cnn, self.readout, self.freeze_cnn = cnn, readout, freeze_cnn
        per_frame = cnn.out_features
        if bottleneck:
            # The shape and its change since the previous frame, read by a small MLP: a linear
            # map of raw point positions is a poor per-frame classifier (base1) or LSTM input.
            per_frame = hidden
            self.reader = nn.Sequential(nn.Linear(2 * geometry_dim, hidden), nn.ReLU(inplace=True),
                                        nn.Linear(hidden, hidden), nn.ReLU(inplace=True))
        if temporal == "lstm":
            self.temporal = nn.LSTM(per_frame, hidden, batch_first=True)
        elif temporal == "rnn":
            self.temporal = nn.RNN(per_frame, hidden, nonlinearity="tanh", batch_first=True)
        elif temporal is None:
            self.temporal = None
        else:
            raise ValueError(f"temporal={temporal!r}: expected 'lstm', 'rnn' or None")
        features = hidden if self.temporal is not None else per_frame
        self.head = nn.Linear(features, num_classes)
        self.factored = factored
        if factored:
            self.head_stretch = nn.Linear(features, NUM_STRETCH)
            self.head_bend = nn.Linear(features, NUM_BEND)
        if geometry_dim:
            self.head_geometry = (nn.Linear(cnn.out_features, geometry_dim) if geometry_window == 1 else
                                  TemporalGeometryHead(cnn.out_features, geometry_dim, geometry_window))
        if freeze_cnn:
            self.cnn.requires_grad_(False)

    def train(self, mode: bool = True) -> "ClipClassifier":
        super().train(mode)
        if self.freeze_cnn:
            self.cnn.eval()  # a frozen CNN also keeps its dropout off
        return self

    def forward(self, x: torch.Tensor, lattice: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """(B, T, 3, H, W) -> {"logits": (B, T, 54)[, "stretch": (B, T, 6), "bend": (B, T, 9)]
        [, "geometry": (B, T, geometry_dim)][, "truth_logits": (B, T, 54)]}.

        ``lattice``, the simulation's own (B, T, geometry_dim) lattice, is read by the bottleneck's
        readers as well while training (``truth_logits``, weighed by ``train.reader_truth``)."""
        feats = self._features(x)
        geometry = self.head_geometry(feats) if self.geometry_dim else None
        out = self.read_shape(geometry, lattice) if self.bottleneck else self._classify(feats)
        if geometry is not None:
            out["geometry"] = geometry
        return out

    def _features(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, 3, H, W) -> the CNN's (B, T, fc6) features of every frame."""
        b, t = x.shape[:2]
        if self.motion:
            x = torch.cat([x, x - torch.cat([x[:, :1], x[:, :-1]], dim=1)], dim=2)
        frames = x.flatten(0, 1)
        if self.channels_last:
            frames = frames.contiguous(memory_format=torch.channels_last)
        return self.cnn(frames).unflatten(0, (b, t))

    def predicted_shape(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, 3, H, W) -> the lattice head's (B, T, geometry_dim) shape of every frame."""
        return self.head_geometry(self._features(x))

    def read_shape(self, geometry: torch.Tensor, lattice: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The bottleneck's outputs from a predicted (B, T, geometry_dim) shape; gradients stop at the shape."""
        shape = self._noised(geometry.detach().float())
        if not (self.training and lattice is not None):
            return self.read_lattice(shape)
        # The readers also learn from the true shape, which carries the material more precisely than any
        # prediction, noised like the predicted one. Both go through the readers as one batch: half the launches
        # of a step that launches bound (the readers of a shared regressor), the same sums a clip.
        both = self.read_lattice(torch.cat([shape, self._noised(lattice.float())]))
        b = shape.shape[0]
        out = {key: value[:b] for key, value in both.items()}
        out["truth_logits"] = both["logits"][b:]
        return out

    def _noised(self, shape: torch.Tensor) -> torch.Tensor:
        """``shape`` with the bottleneck's training noise: training clips' shapes come out cleaner than new
        clips' (the CNN has seen them), and noise keeps the readers from relying on precision they will not get."""
        if self.training and self.bottleneck_noise:
            return shape + self.bottleneck_noise * torch.randn_like(shape)
        return shape

    def read_lattice(self, shape: torch.Tensor) -> dict[str, torch.Tensor]:
        """The bottleneck's classes from a (B, T, geometry_dim) lattice sequence: the reader MLP on each
        frame's shape and its change since the previous frame, then the recurrent layer and heads."""
        change = shape - torch.cat([shape[:, :1], shape[:, :-1]], dim=1)
        return self._classify(self.reader(torch.cat([shape, change], dim=-1)))

    def _classify(self, feats: torch.Tensor) -> dict[str, torch.Tensor]:
        if self.temporal is not None:
            feats, _ = self.temporal(feats)
        out = {"logits": self.head(feats)}
        if self.factored:
            out["stretch"] = self.head_stretch(feats)
            out["bend"] = self.head_bend(feats)
        return out

    def _steps(self, z: torch.Tensor) -> torch.Tensor:
        return z if self.readout == "mean" else z[:, -1:]

    def loss(self, out: dict[str, torch.Tensor], labels: torch.Tensor, *, geometry: torch.Tensor | None = None,
             geometry_weight: float = 0.0, label_smoothing: float = 0.0, truth_weight: float = 0.0) -> torch.Tensor:
        """Cross-entropy on the steps the readout uses (and on both factors when factored), plus
        ``geometry_weight`` x the smooth-L1 error of the geometry head on every frame when a target is given,
        plus ``truth_weight`` x the cross-entropy of the readers on the true lattice when ``out`` has it."""
        def ce(z: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            z = self._steps(z).float()
            return F.cross_entropy(z.flatten(0, 1), y[:, None].expand(-1, z.shape[1]).flatten(),
                                   label_smoothing=label_smoothing)

        total = ce(out["logits"], labels)
        if self.factored:
            total = total + ce(out["stretch"], labels // NUM_BEND) + ce(out["bend"], labels % NUM_BEND)
        if geometry is not None and geometry_weight and "geometry" in out:
            total = total + geometry_weight * F.smooth_l1_loss(out["geometry"].float(), geometry)
        if truth_weight and "truth_logits" in out:
            total = total + truth_weight * ce(out["truth_logits"], labels)
        return total

    def probs(self, out: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B, 54) class probabilities of each clip under the readout."""
        return self._steps(out["logits"]).float().softmax(-1).mean(1)


class ShapeReader(nn.Module):
    """A bottleneck model's readers alone: (B, T, geometry_dim) predicted shapes in, the model's outputs out.
    What trains when the CNN and lattice head are another model's, frozen (``train.shared_regressor``)."""

    def __init__(self, model: ClipClassifier):
        super().__init__()
        if not model.bottleneck:
            raise ValueError("only a bottleneck model's readers read a shape alone")
        self.model = model

    def forward(self, shape: torch.Tensor, lattice: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        return self.model.read_shape(shape, lattice)


# ---------------------------------------------------------------- built by name

def build_model(name: str, *, image_size: int, width: int, fc6: int, hidden: int, dropout: float = 0.5,
                readout: str = "mean", factored: bool = False, motion: bool = False, geometry_dim: int = 0,
                bottleneck: bool = False, bottleneck_noise: float = 0.0, conv5_pool: bool = True,
                geometry_window: int = 1, num_classes: int = NUM_CLASSES) -> ClipClassifier:
    """A model by its ``learn.registry`` name; ``model_args(cfg)`` gives the keyword arguments from a TrainConfig."""
    entry = get_model_entry(name)
    cnn = FrameCNN(image_size, width, fc6, dropout, in_channels=6 if motion else 3, conv5_pool=conv5_pool)
    return ClipClassifier(cnn, entry.temporal, hidden, entry.readout or readout, factored, entry.freeze_cnn,
                          num_classes, motion=motion, geometry_dim=geometry_dim, geometry_window=geometry_window,
                          bottleneck=bottleneck, bottleneck_noise=bottleneck_noise)


def model_args(cfg) -> dict:
    """The ``build_model`` keyword arguments a TrainConfig asks for (stored in checkpoints).

    The bottleneck, conv5_pool and geometry_window keys appear only when they differ from the old behaviour, so
    checkpoints written before they existed compare and load with the same arguments."""
    args = dict(image_size=cfg.image_size, width=cfg.width, fc6=cfg.fc6, hidden=cfg.hidden,
                dropout=cfg.dropout, readout=cfg.readout, factored=cfg.factored, motion=cfg.motion,
                geometry_dim=GEOMETRY_DIM if cfg.aux_geometry > 0 or cfg.bottleneck else 0)
    if cfg.bottleneck:
        args.update(bottleneck=True, bottleneck_noise=cfg.bottleneck_noise)
    if not cfg.conv5_pool:
        args.update(conv5_pool=False)
    if cfg.geometry_window != 1:
        args.update(geometry_window=cfg.geometry_window)
    return args


def take_regressor(model: ClipClassifier, checkpoint: Path | str) -> None:
    """Put a trained bottleneck model's CNN and lattice head into ``model`` and freeze both: what every model
    but the named one starts from under ``train.shared_regressor``."""
    path = Path(checkpoint)
    if not path.is_file():
        raise MissingInputError(f"the shared regressor's checkpoint {path} does not exist")
    state = torch.load(path, map_location="cpu", weights_only=True)["model"]
    load_cnn_weights(model, state)
    head = {k[len("head_geometry."):]: v for k, v in state.items() if k.startswith("head_geometry.")}
    if not model.geometry_dim or not head:
        raise ValueError(f"{path}: a shared regressor needs a lattice head in both models (train.bottleneck=true)")
    model.head_geometry.load_state_dict(head)
    model.cnn.requires_grad_(False)
    model.head_geometry.requires_grad_(False)


def load_cnn_weights(model: ClipClassifier, source: Path | str | dict) -> None:
    """Put CNN (conv layers + fc6) weights into ``model``.

    ``source`` is a weights file or a state dict: a whole clothgap checkpoint
    (its ``"model"`` entry, keys ``cnn.*``), a model state dict, or a bare
    FrameCNN state dict. Every CNN tensor must be present with the right shape.
    """
    where = str(source) if not isinstance(source, dict) else "the given state dict"
    if not isinstance(source, dict):
        path = Path(source)
        if not path.is_file():
            raise MissingInputError(f"CNN weights file {path} does not exist (nothing is ever downloaded)")
        source = torch.load(path, map_location="cpu", weights_only=True)
    state = source.get("model", source)
    if any(k.startswith("cnn.") for k in state):
        state = {k[len("cnn."):]: v for k, v in state.items() if k.startswith("cnn.")}
    own = model.cnn.state_dict()
    missing = sorted(set(own) - set(state))
    wrong = sorted(k for k in own if k in state and state[k].shape != own[k].shape)
    if missing or wrong:
        detail = ", ".join([f"{k} missing" for k in missing] +
                           [f"{k} {tuple(state[k].shape)} != {tuple(own[k].shape)}" for k in wrong])
        raise ValueError(f"CNN weights in {where} do not fit this model ({detail}); "
                         "were they trained with the same image_size and width/fc6?")
    model.cnn.load_state_dict({k: state[k] for k in own})
