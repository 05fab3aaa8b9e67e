"""The camera augmentation (train.augment_camera): what it does to frames, its determinism, and training with it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import learn.windows
from clothgap import seeding
from clothgap.config import StudyConfig, apply_overrides, invalidating_settings
from clothgap.runs import Run, mark_done
from learn.config import TrainConfig
from learn.dataset import build_cache
from learn.synthetic import synthetic_run
from learn.train import train_one
from learn.windows import AUG_PARAMS, WindowSet, camera_augment_batch, linear_to_srgb, srgb_to_linear
from render.camera import vignette
from render.config import RenderConfig
from render.variants import RenderVariant
from sim.config import SimConfig
from tests.conftest import SETTING, VARIANT, tiny_train_config

# Camera draws that change nothing: exposure, white balance and gamma at their middle, no vignetting, no noise.
IDENTITY = (0.5, 0.5, 0.5, 0.5, 0.5, 0.0, 0.0)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    cfg = StudyConfig(sim=SimConfig(classes=(0, 53), sequences_per_class=2, frames=12),
                      render=RenderConfig(resolution=40), train=TrainConfig(image_size=32))
    cache = build_cache(synthetic_run(tmp_path_factory.mktemp("camera") / "run", cfg), VARIANT, SETTING, 32,
                        progress=False)
    return WindowSet(cache, sorted(cache.clips), clip_len=4, clip_stride=4)


def params_of(b: int, **columns) -> torch.Tensor:
    """(b, 7) camera draws: ``IDENTITY`` with the named columns set."""
    names = ("exposure", "red", "green", "blue", "gamma", "vignetting", "noise")
    row = [columns.get(name, value) for name, value in zip(names, IDENTITY)]
    return torch.tensor([row], dtype=torch.float32).repeat(b, 1)


def grey(b: int = 2, t: int = 3, size: int = 16, value: float = 0.5) -> torch.Tensor:
    return torch.full((b, t, 3, size, size), value)


def test_without_the_camera_the_augment_table_and_batches_are_what_they_were(data, monkeypatch):
    # The augment table keeps its own stream: a run without augment_camera draws exactly what it drew before.
    gen = torch.Generator().manual_seed(seeding.derive_int(5, 0, seeding.TRAIN, "augment", 2))
    assert torch.equal(data.augment_table(5, 2), torch.rand(len(data), AUG_PARAMS, generator=gen))
    assert not torch.equal(data.camera_table(5, 2)[:, :7], data.augment_table(5, 2)[:, :7])
    order, table = data.order(5, 2), data.augment_table(5, 2)
    with_camera = list(data.batches(3, order=order, augment=table, camera=data.camera_table(5, 2)))

    def no_camera(*args, **kwargs):
        raise AssertionError("the camera is off")

    # off, the camera's code never runs, whatever noise seed is passed, and the batches are augment's alone
    monkeypatch.setattr(learn.windows, "camera_augment_batch", no_camera)
    before = list(data.batches(3, order=order, augment=table))
    for (x, y, _), (x2, y2, _), (xc, _, _) in zip(before, data.batches(3, order=order, augment=table, camera=None,
                                                                          camera_noise_seed=99), with_camera,
                                                   strict=True):
        assert torch.equal(x, x2) and torch.equal(y, y2) and not torch.equal(x, xc)


def test_the_same_seed_and_epoch_give_the_same_batches_another_epoch_others(data):
    def epoch(seed, number, with_augment=False):
        order = data.order(seed, number)
        return [x for x, _, _ in data.batches(4, order=order, camera=data.camera_table(seed, number),
                                              camera_noise_seed=data.camera_noise_seed(seed, number),
                                              augment=data.augment_table(seed, number) if with_augment else None)]

    first = epoch(3, 0)
    assert all(torch.equal(a, b) for a, b in zip(first, epoch(3, 0), strict=True))      # noise included
    assert all(not torch.equal(a, b) for a, b in zip(first, epoch(3, 1), strict=True))
    plain = [x for x, _, _ in data.batches(4, order=data.order(3, 0))]
    assert all(not torch.allclose(a, b, atol=1e-3) for a, b in zip(first, plain, strict=True))
    assert all(0 <= float(x.min()) and float(x.max()) <= 1 for x in first + epoch(3, 0, with_augment=True))
    # Another rank's noise is not this rank's.
    assert WindowSet.camera_noise_seed(3, 0, 0) != WindowSet.camera_noise_seed(3, 0, 1)


def test_the_camera_comes_after_augment_s_transforms(data):
    order, table, camera = data.order(1, 4), data.augment_table(1, 4), data.camera_table(1, 4)
    augmented = list(data.batches(4, order=order, augment=table))
    both = list(data.batches(4, order=order, augment=table, camera=camera, camera_noise_seed=11))
    noise = torch.Generator()
    for number, ((x, _, _), (xc, _, _)) in enumerate(zip(augmented, both, strict=True)):
        idx = order[4 * number:4 * number + 4]
        noise.manual_seed(seeding.derive_int(11, number, seeding.TRAIN, "camera_noise"))
        assert torch.equal(xc, camera_augment_batch(x, camera[idx], noise))


def test_middle_draws_leave_frames_as_they_are_and_the_srgb_curve_round_trips():
    x = torch.rand(2, 3, 3, 8, 8)
    assert torch.allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-6)
    assert torch.allclose(camera_augment_batch(x.clone(), params_of(2), torch.Generator()), x, atol=1e-5)


def test_exposure_scales_linear_radiance_by_two_to_the_stops():
    x = torch.rand(2, 3, 3, 16, 16)
    linear = srgb_to_linear(x)
    brighter = srgb_to_linear(camera_augment_batch(x.clone(), params_of(2, exposure=1.0)))     # +1 stop
    unclipped = linear < 0.5
    assert float(brighter[unclipped].mean() / linear[unclipped].mean()) == pytest.approx(2.0, rel=1e-3)
    assert float(brighter.max()) == 1.0                                                         # highlights clip
    darker = srgb_to_linear(camera_augment_batch(x.clone(), params_of(2, exposure=0.0)))       # -1 stop
    assert float(darker.mean() / linear.mean()) == pytest.approx(0.5, rel=1e-3)


def test_white_balance_gains_each_channel_in_linear_light():
    out = srgb_to_linear(camera_augment_batch(grey(), params_of(2, red=1.0, blue=0.0)))
    means = (out.mean(dim=(0, 1, 3, 4)) / srgb_to_linear(torch.tensor(0.5))).tolist()
    assert means == pytest.approx([1.1, 1.0, 0.9], rel=1e-4)


def test_vignetting_darkens_the_corners_as_the_renderer_does():
    size = 16
    out = camera_augment_batch(grey(size=size), params_of(2, vignetting=1.0))                  # strength 0.3
    frame = out[0, 0, 0]
    assert float(frame[0, 0]) < float(frame[size // 2, size // 2]) < 0.5 + 1e-6
    assert torch.equal(frame[0, 0], frame[-1, -1]) and torch.equal(frame[0, -1], frame[-1, 0])
    falloff = srgb_to_linear(out[0, 0, 0]) / srgb_to_linear(torch.tensor(0.5))
    expected = vignette(RenderVariant(vignetting=0.3), size, size)
    np.testing.assert_allclose(falloff.numpy(), expected, atol=1e-5)
    half = camera_augment_batch(grey(size=size), params_of(2, vignetting=0.5))[0, 0, 0]
    assert float(frame[0, 0]) < float(half[0, 0]) < 0.5


def test_tone_gamma_bends_the_encoded_values_both_ways():
    x = torch.rand(2, 3, 3, 8, 8)
    assert torch.allclose(camera_augment_batch(x.clone(), params_of(2, gamma=1.0)), x ** 1.25, atol=1e-5)
    assert torch.allclose(camera_augment_batch(x.clone(), params_of(2, gamma=0.0)), x ** 0.8, atol=1e-5)


def test_sensor_noise_is_fresh_per_pixel_and_frame_at_the_drawn_strength():
    x = grey(b=2, t=4, size=64)
    params = params_of(2, noise=1.0)                                                            # std 0.02
    params[1, 6] = 0.25                                                                         # std 0.005
    noise = (camera_augment_batch(x.clone(), params, torch.Generator().manual_seed(0)) - x)
    assert float(noise[0].std()) == pytest.approx(0.02, rel=0.05)
    assert float(noise[1].std()) == pytest.approx(0.005, rel=0.05)
    assert abs(float(noise[0].mean())) < 1e-3
    assert not torch.equal(noise[0, 0], noise[0, 1])
    assert torch.equal(camera_augment_batch(x.clone(), params), x)                             # no generator: none


def test_frames_of_a_clip_share_their_camera_and_outputs_stay_in_range():
    frame = torch.rand(1, 1, 3, 16, 16)
    x = frame.repeat(4, 5, 1, 1, 1)                     # four clips, each one frame five times
    params = torch.rand(4, 7)
    params[:, 6] = 0.0                                  # no noise: what is left is per clip
    out = camera_augment_batch(x.clone(), params, torch.Generator().manual_seed(1))
    assert all(torch.equal(out[:, t], out[:, 0]) for t in range(5))
    assert all(not torch.allclose(out[i], out[j], atol=1e-3) for i in range(4) for j in range(i))
    extremes = torch.cat([torch.zeros(2, 2, 3, 8, 8), torch.ones(2, 2, 3, 8, 8)])
    wild = torch.tensor([[1.0, 1.0, 1.0, 1.0, 0.0, 1.0, 1.0], [0.0] * 7] * 2)
    out = camera_augment_batch(extremes, wild, torch.Generator().manual_seed(2))
    assert 0 <= float(out.min()) and float(out.max()) <= 1


def test_training_with_the_camera_resumes_to_the_same_weights_and_differs_from_training_without(
        tmp_path, monkeypatch):
    from tests.test_learn_train import kill_after_first_epoch

    def weights(run):
        out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
        return torch.load(out / "checkpoint.pt", weights_only=True)["model"], out

    cfg = tiny_train_config(augment_camera=True, epochs=2)
    whole, out = weights(synthetic_run(tmp_path / "whole", cfg))
    assert json.loads((out / "config.json").read_text())["train"]["augment_camera"] is True
    killed = synthetic_run(tmp_path / "killed", cfg)
    kill_after_first_epoch(killed, monkeypatch)
    resumed, _ = weights(killed)
    assert all(torch.equal(resumed[k], v) for k, v in whole.items())

    def no_camera(*args, **kwargs):
        raise AssertionError("augment_camera is off")

    monkeypatch.setattr(learn.windows, "camera_augment_batch", no_camera)
    without, _ = weights(synthetic_run(tmp_path / "without", tiny_train_config(epochs=2)))
    assert not all(torch.equal(without[k], v) for k, v in whole.items())


def test_a_run_refuses_a_change_of_augment_camera_once_models_are_trained_as_it_does_augment(tmp_path):
    cfg = tiny_train_config()
    for key in ("train.augment", "train.augment_camera"):
        assert invalidating_settings(cfg, apply_overrides(cfg, [f"{key}=true"])) == {key: "train"}
    # A run made before the setting existed, with trained models, opens with it off (what it trained with).
    run = Run.create_or_resume(tmp_path / "run", cfg)
    folder = run.train_dir(SETTING, VARIANT, "lrcn", 0)
    folder.mkdir(parents=True)
    mark_done(folder)
    path = run.root / "config.json"
    stored = json.loads(path.read_text())
    del stored["train"]["augment_camera"]
    path.write_text(json.dumps(stored))
    with pytest.warns(UserWarning, match="train.augment_camera"):
        assert Run.open(run.root).config.train.augment_camera is False
