"""Training on a CUDA GPU: batches cut on the device equal those cut on the host, and a training step never makes
the host wait for the GPU (a wait each step leaves the GPU idle while the next step's kernels are launched).

Deselected by default; on the GPU machine: ``pytest -m gpu tests/test_learn_gpu.py``."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

from clothgap.config import StudyConfig
from learn.dataset import build_cache
from learn.models import build_model
from learn.synthetic import synthetic_run
from learn.train import run_epoch
from learn.windows import WindowSet, gather_rows, row_bytes
from render.config import RenderConfig
from sim.config import SimConfig
from learn.config import TrainConfig

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")]
SETTING, VARIANT = "wind-uniform1", "paper"


@pytest.fixture
def cache(tmp_path):
    cfg = StudyConfig(sim=SimConfig(classes=(0, 8, 45, 53), sequences_per_class=3, frames=12),
                      render=RenderConfig(resolution=40), train=TrainConfig(image_size=32))
    return build_cache(synthetic_run(tmp_path / "run", cfg), VARIANT, SETTING, 32, progress=False)


def test_batches_cut_on_the_device_equal_those_cut_on_the_host(cache):
    targets = np.random.default_rng(0).random((cache.frames.shape[0], 4), dtype=np.float32)
    host = WindowSet(cache, sorted(cache.clips), clip_len=4, clip_stride=3, targets=targets)
    gpu = WindowSet(cache, sorted(cache.clips), clip_len=4, clip_stride=3, device="cuda", targets=targets)
    assert gpu.resident and gpu.frames.is_cuda
    order, table = host.order(3, 1), host.augment_table(3, 1)
    for (xh, yh, th), (xg, yg, tg) in zip(host.batches(5, order=order, augment=table, drop_last=True),
                                          gpu.batches(5, order=order, augment=table, drop_last=True), strict=True):
        assert xg.is_cuda and yg.is_cuda and tg.is_cuda
        assert torch.equal(yh, yg.cpu()) and torch.equal(th, tg.cpu())
        assert torch.allclose(xh, xg.cpu(), atol=1e-5)      # the same resample, on two devices' kernels


def test_a_training_step_does_not_wait_for_the_gpu(cache):
    data = WindowSet(cache, sorted(cache.clips), clip_len=4, clip_stride=3, device="cuda")
    model = build_model("lrcn", image_size=32, width=8, fc6=32, hidden=16, motion=True).cuda()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3, fused=True)
    run_epoch(model, model, data.batches(4), torch.device("cuda"), optimizer, amp=True)   # first-use set-up

    def guarded(batches):
        # Every step of the epoch under the sync check; the epoch's one read of its sums comes after.
        torch.cuda.set_sync_debug_mode("error")
        try:
            yield from batches
        finally:
            torch.cuda.set_sync_debug_mode("default")

    order, table, camera = data.order(0, 1), data.augment_table(0, 1), data.camera_table(0, 1)
    sums = run_epoch(model, model, guarded(data.batches(4, order=order, augment=table, drop_last=True)),
                     torch.device("cuda"), optimizer, amp=True)
    assert sums[2] == 4 * (len(data) // 4)
    # The camera augmentation too: its table copied once an epoch, its noise generator seeded on the host.
    sums = run_epoch(model, model, guarded(data.batches(4, order=order, augment=table, drop_last=True, camera=camera,
                                                        camera_noise_seed=data.camera_noise_seed(0, 1))),
                     torch.device("cuda"), optimizer, amp=True)
    assert sums[2] == 4 * (len(data) // 4)


def test_the_camera_augmentation_on_the_device_is_the_host_s_and_reproducible(cache):
    host = WindowSet(cache, sorted(cache.clips), clip_len=4, clip_stride=3)
    gpu = WindowSet(cache, sorted(cache.clips), clip_len=4, clip_stride=3, device="cuda")
    order, table, camera = host.order(2, 0), host.augment_table(2, 0), host.camera_table(2, 0)
    quiet = camera.clone()
    quiet[:, 6] = 0                                     # no sensor noise: the rest is the same arithmetic
    for (xh, _, _), (xg, _, _) in zip(host.batches(5, order=order, augment=table, camera=quiet),
                                      gpu.batches(5, order=order, augment=table, camera=quiet), strict=True):
        assert torch.allclose(xh, xg.cpu(), atol=1e-4)
    noisy = [[x for x, _, _ in gpu.batches(5, order=order, camera=camera, camera_noise_seed=9)] for _ in range(2)]
    assert all(torch.equal(a, b) for a, b in zip(*noisy, strict=True))
    assert all(0 <= float(x.min()) and float(x.max()) <= 1 for x in noisy[0])


def test_rows_go_to_the_device_chunk_by_chunk_unchanged(cache):
    rows = np.random.default_rng(1).choice(cache.frames.shape[0], size=cache.frames.shape[0] // 2 + 1, replace=False)
    row = row_bytes(cache.frames)
    for chunk_bytes in (row, 3 * row, None):      # one row a chunk, three, the default (all at once)
        got = gather_rows(cache.frames, rows, "cuda", chunk_bytes=chunk_bytes)
        assert got.is_cuda and np.array_equal(got.cpu().numpy(), cache.frames[rows]), chunk_bytes


def test_a_reader_trained_by_replaying_its_graphed_step_matches_the_eager_reader():
    from learn.models import ShapeReader
    from learn.steps import GraphedReaderEpochs

    device = torch.device("cuda")
    cfg = _reader_config(epochs=3)
    n = 45                                        # 5 whole batches of 8, the last 5 windows dropped
    data = _random_shapes(n)
    results = {}
    for way in ("eager", "graphed"):
        model, optimizer, scheduler = _fresh_reader(cfg)
        net = ShapeReader(model)
        graphed = GraphedReaderEpochs(net, model, optimizer, data, cfg.batch_size, device, True,
                                      truth_weight=cfg.reader_truth) if way == "graphed" else None
        sums = []
        for epoch in range(cfg.epochs):
            order = torch.randperm(n, generator=torch.Generator().manual_seed(epoch))
            if graphed is not None:
                sums.append(graphed.epoch(order))
            else:
                batches = [(data.shapes[i], data.device_labels[i], data.targets[i])
                           for i in order.to(device).split(cfg.batch_size) if len(i) == cfg.batch_size]
                sums.append(run_epoch(net, model, batches, device, optimizer, amp=True,
                                      truth_weight=cfg.reader_truth))
            scheduler.step()          # the graphed update reads the new rate from the tensor the schedule fills
        results[way] = (sums, {k: v.detach().float().cpu() for k, v in model.state_dict().items()})
        if graphed is not None:
            assert graphed.graph is not None and graphed.failed is None and graphed.eager_steps == 3
    (eager_sums, eager_w), (graph_sums, graph_w) = results["eager"], results["graphed"]
    for a, b in zip(eager_sums, graph_sums, strict=True):      # (loss x clips, right, clips, -)
        assert a[2] == b[2] == 40 and torch.allclose(a[0], b[0], rtol=1e-3) and abs(a[1] - b[1]) <= 2
    for k in eager_w:
        assert torch.allclose(eager_w[k], graph_w[k], rtol=1e-3, atol=1e-4), k


def _reader_config(epochs: int):
    from learn.config import TrainConfig

    # no noise and no dropout: two trainings from the same weights draw nothing at random
    return TrainConfig(bottleneck=True, bottleneck_noise=0.0, dropout=0.0, reader_truth=1.0, batch_size=8,
                       epochs=epochs, schedule="cosine", motion=True, image_size=32, width=8, fc6=32, hidden=16)


def _random_shapes(n: int, frames: int = 6):
    """A ShapeSet of random shapes, lattices and labels on the GPU."""
    from learn.models import GEOMETRY_DIM
    from learn.shapes import ShapeSet

    gen = torch.Generator().manual_seed(0)
    shapes = torch.randn(n, frames, GEOMETRY_DIM, generator=gen).cuda()
    targets = torch.randn(n, frames, GEOMETRY_DIM, generator=gen)
    return ShapeSet.of_tensors(shapes, torch.randint(0, 54, (n,), generator=gen), targets)


def _fresh_reader(cfg):
    """base2 at the same starting weights each time, its CNN and lattice head frozen (a shared regressor's
    reader), with its optimiser and schedule."""
    from learn.models import model_args
    from learn.train import make_optimizer, make_scheduler

    torch.manual_seed(0)
    model = build_model("base2", **model_args(cfg)).cuda()
    model.cnn.requires_grad_(False)
    model.head_geometry.requires_grad_(False)
    optimizer = make_optimizer(model, cfg, torch.device("cuda"))
    return model, optimizer, make_scheduler(optimizer, cfg.schedule, cfg.epochs)


def test_a_reader_on_a_shared_regressor_trains_by_graph_replay_through_train_one(tmp_path):
    import warnings

    import pandas as pd

    from clothgap.runs import is_done
    from learn.train import train_one
    from tests.conftest import tiny_train_config
    from tests.test_learn_train import _sim_clips_for

    cfg = tiny_train_config(bottleneck=True, dropout=0.0, reader_truth=1.0, bottleneck_noise=0.2, epochs=3,
                            models=("lrcn", "base2"), shared_regressor="lrcn", reader_graphs=True, device="cuda")
    run = synthetic_run(tmp_path / "run", cfg)
    _sim_clips_for(run, cfg.sim.frames)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = train_one(run, SETTING, VARIANT, "base2", 0, progress=False)      # trains lrcn first
    assert is_done(out)
    assert not [w for w in caught if "could not be captured" in str(w.message)]
    metrics = pd.read_csv(out / "metrics.csv")
    assert len(metrics) == 3 and metrics.train_loss.notna().all() and metrics.lr.map(type).eq(float).all()
    assert metrics.lr.iloc[1] < metrics.lr.iloc[0]             # the schedule reached the replayed update


def test_a_graphed_reader_resumed_from_its_saved_state_follows_the_schedule_as_an_unbroken_one():
    import io

    from learn.models import ShapeReader
    from learn.steps import GraphedReaderEpochs

    device = torch.device("cuda")
    cfg = _reader_config(epochs=4)
    data = _random_shapes(40)
    fresh = functools.partial(_fresh_reader, cfg)

    def epochs(model, optimizer, scheduler, which):
        graphed = GraphedReaderEpochs(ShapeReader(model), model, optimizer, data, cfg.batch_size, device, True,
                                      truth_weight=cfg.reader_truth)
        for epoch in which:
            graphed.epoch(torch.randperm(40, generator=torch.Generator().manual_seed(epoch)))
            scheduler.step()

    whole = fresh()
    epochs(*whole, range(4))
    first = fresh()
    epochs(*first, range(2))
    saved = io.BytesIO()       # as last.pt: written, then read onto the CPU
    torch.save({"model": first[0].state_dict(), "optimizer": first[1].state_dict(),
                "scheduler": first[2].state_dict()}, saved)
    saved.seek(0)
    state = torch.load(saved, map_location="cpu", weights_only=True)
    resumed = fresh()
    resumed[0].load_state_dict(state["model"])
    resumed[1].load_state_dict(state["optimizer"])
    resumed[2].load_state_dict(state["scheduler"])
    epochs(*resumed, range(2, 4))
    assert resumed[1].param_groups[0]["lr"].is_cuda
    for (k, a), b in zip(whole[0].state_dict().items(), resumed[0].state_dict().values()):
        assert torch.allclose(a.float(), b.float(), rtol=1e-3, atol=1e-4), k
