"""The model registry: shapes, losses that fall, the frozen CNN, CNN weights from files."""

from __future__ import annotations

import pytest
import torch

from learn.config import TrainConfig

from learn.models import NUM_BEND, build_model, load_cnn_weights
from learn.registry import MODEL_NAMES

TINY = dict(width=8, fc6=32, hidden=16, dropout=0.0)


def test_unknown_model_lists_the_known_ones():
    with pytest.raises(ValueError, match="known models: lrcn, base1, base2, base3"):
        build_model("alexnet", image_size=32, **TINY)


@pytest.mark.parametrize("size", [32, 48, 224])
def test_any_multiple_of_16_from_32_to_224(size):
    model = build_model("lrcn", image_size=size, factored=True, **TINY)
    out = model(torch.rand(2, 3, 3, size, size))
    assert out["logits"].shape == (2, 3, 54) and out["stretch"].shape == (2, 3, 6) and out["bend"].shape == (2, 3, 9)
    assert torch.allclose(model.probs(out).sum(-1), torch.ones(2))
    with pytest.raises(ValueError, match="multiple of 16"):
        build_model("lrcn", image_size=40, **TINY)


def _fit(model, steps: int = 60) -> tuple[float, float, torch.Tensor]:
    """Adam on one fixed batch of 4 clips: (first loss, last loss, eval-mode predictions)."""
    torch.manual_seed(0)
    x, y = torch.rand(4, 3, 3, 32, 32), torch.tensor([0, 8, 45, 53])
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-2)
    first = model.loss(model(x), y).item()
    for _ in range(steps):
        loss = model.loss(model(x), y)
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        return first, loss.item(), model.probs(model(x)).argmax(-1)


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_each_model_overfits_a_tiny_batch(name):
    torch.manual_seed(0)
    first, last, pred = _fit(build_model(name, image_size=32, **TINY))
    assert last < 0.2 * first
    assert pred.tolist() == [0, 8, 45, 53]


def test_factored_heads_train_with_the_main_head():
    torch.manual_seed(0)
    first, last, _ = _fit(build_model("lrcn", image_size=32, factored=True, **TINY))
    assert last < 0.3 * first


def test_base2_keeps_its_cnn_frozen_and_in_eval_mode():
    model = build_model("base2", image_size=32, width=8, fc6=32, hidden=16)
    before = {k: v.clone() for k, v in model.cnn.state_dict().items()}
    model.train()
    assert not model.cnn.training and model.temporal.training
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-2)
    model.loss(model(torch.rand(2, 3, 3, 32, 32)), torch.tensor([1, 2])).backward()
    opt.step()
    assert all(torch.equal(before[k], v) for k, v in model.cnn.state_dict().items())


def test_readouts_and_factored_labels():
    last = build_model("lrcn", image_size=32, readout="last", **TINY)
    out = {"logits": torch.zeros(1, 3, 54)}
    out["logits"][0, -1, 7] = 10.0
    assert last.probs(out).argmax().item() == 7
    assert build_model("base1", image_size=32, readout="last", **TINY).readout == "mean"
    assert divmod(53, NUM_BEND) == (5, 8)   # class index = 9 * stretching + bending
    with pytest.raises(ValueError, match="readout"):
        build_model("lrcn", image_size=32, readout="max", **TINY)


def test_cnn_weights_load_from_files_and_mismatches_are_named(tmp_path):
    source = build_model("base1", image_size=32, **TINY)
    path = tmp_path / "cnn.pt"
    torch.save({"model": source.state_dict()}, path)
    target = build_model("base2", image_size=32, **TINY)
    load_cnn_weights(target, path)
    assert all(torch.equal(v, source.cnn.state_dict()[k]) for k, v in target.cnn.state_dict().items())
    torch.save(source.cnn.state_dict(), path)   # a bare CNN state dict works as well
    load_cnn_weights(target, path)
    with pytest.raises(ValueError, match="fc6.1.weight"):
        load_cnn_weights(build_model("lrcn", image_size=64, **TINY), path)
    with pytest.raises(FileNotFoundError, match="nothing is ever downloaded"):
        load_cnn_weights(target, tmp_path / "absent.pt")


def test_motion_input_adds_frame_differences():
    model = build_model("lrcn", image_size=32, width=8, fc6=16, hidden=8, motion=True).eval()
    assert model.cnn.features[0].in_channels == 6
    still = torch.rand(1, 1, 3, 32, 32).expand(2, 5, 3, 32, 32)
    seen = {}
    model.cnn.register_forward_pre_hook(lambda _m, inp: seen.update(x=inp[0]))
    assert model(still)["logits"].shape == (2, 5, 54)
    assert seen["x"].shape == (10, 6, 32, 32) and float(seen["x"][:, 3:].abs().max()) == 0   # nothing moves


def test_bottleneck_classes_read_only_the_predicted_shape():
    torch.manual_seed(0)
    model = build_model("lrcn", image_size=32, geometry_dim=192, bottleneck=True, **TINY)
    x, y = torch.rand(2, 4, 3, 32, 32), torch.tensor([3, 40])
    out = model(x)
    model.loss(out, y).backward()                         # the class loss alone
    assert all(p.grad is None or float(p.grad.abs().max()) == 0 for p in model.cnn.parameters())
    assert all(p.grad is None for p in model.head_geometry.parameters())
    assert float(model.reader[0].weight.grad.abs().max()) > 0
    model.zero_grad()
    model.loss(model(x), y, geometry=torch.randn(2, 4, 192), geometry_weight=1.0).backward()
    assert float(model.cnn.fc6[1].weight.grad.abs().max()) > 0   # the shape loss trains the CNN
    # Frames that differ but give the same predicted shape give the same class scores.
    model.eval()
    model.head_geometry.weight.data.zero_()
    assert torch.equal(model(x)["logits"], model(torch.rand_like(x))["logits"])
    with pytest.raises(ValueError, match="geometry head"):
        build_model("lrcn", image_size=32, bottleneck=True, **TINY)


def test_without_the_conv5_pool_fc6_reads_conv5s_own_map():
    from learn.models import FrameCNN

    pooled, fine = FrameCNN(112, 8, 16), FrameCNN(112, 8, 16, conv5_pool=False)
    maps = {}
    for name, cnn in (("pooled", pooled), ("fine", fine)):
        cnn.pool.register_forward_hook(lambda _m, _i, out, name=name: maps.update({name: out.shape[-2:]}))
        assert cnn(torch.rand(2, 3, 112, 112)).shape == (2, 16)
    assert maps == {"pooled": (3, 3), "fine": (7, 7)}
    # The convolutions are the same layers: a pooled CNN's conv weights load into the fine one.
    conv = {k: v for k, v in pooled.state_dict().items() if k.startswith("features.")}
    fine.load_state_dict(conv, strict=False)
    assert torch.equal(fine.features[0].weight, pooled.features[0].weight)
    model = build_model("lrcn", image_size=64, geometry_dim=192, bottleneck=True, conv5_pool=False, **TINY)
    assert model(torch.rand(1, 3, 3, 64, 64))["geometry"].shape == (1, 3, 192)


def test_a_geometry_window_reads_the_neighbouring_frames_only():
    from learn.models import TemporalGeometryHead

    torch.manual_seed(0)
    head = TemporalGeometryHead(4, 6, 3)
    feats = torch.randn(2, 7, 4)
    out = head(feats)
    assert out.shape == (2, 7, 6)
    changed = feats.clone()
    changed[:, 5] += 1.0                                        # frame 5 changes
    moved = (head(changed) - out).abs().amax(dim=(0, 2))
    assert moved[:4].max() == 0 and moved[4:].min() > 0         # only frames 4, 5, 6 see it
    # At the clip's ends the first and last frames stand in for the frames before and after.
    padded = torch.cat([feats[:, :1], feats, feats[:, -1:]], dim=1)
    assert torch.allclose(out, head.conv(padded.transpose(1, 2)).transpose(1, 2))
    model = build_model("lrcn", image_size=32, geometry_dim=192, bottleneck=True, geometry_window=3, **TINY)
    assert model(torch.rand(1, 4, 3, 32, 32))["geometry"].shape == (1, 4, 192)
    assert TrainConfig(geometry_window=2).problems() and not TrainConfig(geometry_window=3).problems()


def test_reader_truth_trains_the_readers_on_the_true_lattice_only():
    torch.manual_seed(0)
    model = build_model("lrcn", image_size=32, geometry_dim=192, bottleneck=True, **TINY)
    x, y, lattice = torch.rand(2, 4, 3, 32, 32), torch.tensor([3, 40]), torch.randn(2, 4, 192)
    out = model(x, lattice)
    # The true-lattice logits are what the same readers make of the true lattice.
    assert torch.allclose(out["truth_logits"], model.read_lattice(lattice)["logits"])
    plain = model.loss(out, y)
    with_truth = model.loss(out, y, truth_weight=0.5)
    assert float(with_truth) > float(plain)
    model.zero_grad()
    (with_truth - plain).backward()                  # the true-lattice term alone
    assert float(model.reader[0].weight.grad.abs().max()) > 0
    assert all(p.grad is None or float(p.grad.abs().max()) == 0 for p in model.cnn.parameters())
    model.eval()
    assert "truth_logits" not in model(x, lattice)   # prediction reads pixels only


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_each_model_builds_with_the_bottleneck(name):
    model = build_model(name, image_size=32, geometry_dim=192, bottleneck=True, **TINY)
    assert model(torch.rand(2, 3, 3, 32, 32))["logits"].shape == (2, 3, 54)


def test_conv5_maps_of_a_model_reading_frame_differences():
    import numpy as np

    from eval.activations import conv5_maps

    model = build_model("lrcn", image_size=32, motion=True, **TINY).eval()
    frames = np.random.default_rng(0).integers(0, 256, (5, 32, 32, 3), dtype=np.uint8)
    maps = conv5_maps(model, frames)
    assert maps.shape == (5, 32, 32) and 0 <= maps.min() and maps.max() <= 1



def test_the_readers_read_the_predicted_and_the_true_shape_as_one_batch_with_the_same_sums():
    torch.manual_seed(0)
    model = build_model("base2", image_size=32, geometry_dim=192, bottleneck=True, bottleneck_noise=0.2,
                        factored=True, **TINY).train()
    shape, lattice = torch.randn(3, 5, 192), torch.randn(3, 5, 192)
    torch.manual_seed(1)
    fused = model.read_shape(shape, lattice)
    torch.manual_seed(1)                                   # the same noise, drawn in the same order
    noised_shape = model._noised(shape)
    noised_lattice = model._noised(lattice)
    apart = model.read_lattice(noised_shape)
    for key in ("logits", "stretch", "bend"):
        torch.testing.assert_close(fused[key], apart[key], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(fused["truth_logits"], model.read_lattice(noised_lattice)["logits"], rtol=1e-5,
                               atol=1e-6)
    assert fused["logits"].shape == (3, 5, 54) and fused["truth_logits"].shape == (3, 5, 54)
