"""learn.steps on the CPU: what makes an optimiser capturable, and the shape set a graphed reader reads (the
graphed reader itself needs a CUDA GPU: tests/test_learn_gpu.py)."""

from __future__ import annotations

import torch

from learn.steps import make_capturable


def test_a_capturable_optimiser_reads_its_rate_from_a_float32_tensor_on_the_device_after_a_resume():
    weights = [torch.nn.Parameter(torch.zeros(3))]
    optimizer = torch.optim.AdamW(weights, lr=1e-3)
    weights[0].grad = torch.ones(3)
    optimizer.step()
    cpu = torch.device("cpu")
    # what last.pt gives back: the rate a float, or a tensor of another dtype (read onto the CPU)
    for saved_lr in (2e-4, torch.tensor(2e-4, dtype=torch.float64)):
        state = optimizer.state_dict()
        state["param_groups"][0]["lr"] = saved_lr
        optimizer.load_state_dict(state)
        make_capturable(optimizer, cpu)
        group = optimizer.param_groups[0]
        assert group["capturable"] and torch.is_tensor(group["lr"]) and group["lr"].dtype == torch.float32
        assert group["lr"].device == cpu and abs(float(group["lr"]) - 2e-4) < 1e-9


def test_a_shape_set_of_given_tensors_serves_them_as_a_regressor_s_would():
    from learn.shapes import ShapeSet

    shapes, targets = torch.randn(5, 4, 3), torch.randn(5, 4, 3)
    labels = torch.tensor([7, 1, 0, 53, 2])
    data = ShapeSet.of_tensors(shapes, labels, targets)
    assert len(data) == 5 and data.clip_len == 4 and data.device == shapes.device
    x, y, t = next(data.batches(2, order=torch.tensor([3, 0, 4, 1, 2])))
    assert torch.equal(x, shapes[[3, 0]]) and torch.equal(y, labels[[3, 0]]) and torch.equal(t, targets[[3, 0]])
