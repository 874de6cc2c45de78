"""optim.all_finite (the trainer's skip test; a C++ pass over float32 CPU tensors) against
torch.isfinite, on gradients with NaN and infinities planted anywhere, on the largest and the
smallest finite floats, and on what the kernel does not take (float64, strided)."""

from __future__ import annotations

import pytest
import torch

from stg_node.avatar.optim import all_finite

pytestmark = pytest.mark.usefixtures("cpu_kernels")  # skips where the kernels cannot build


def grads(seed: int) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    shapes = [(2000, 3), (2000,), (2000, 24), (8, 207), (3,), (1,), (0,), (33, 7)]
    return [torch.randn(s, generator=gen) * 1e3 for s in shapes]


def oracle(tensors) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in tensors)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf"), -float("nan")])
def test_one_bad_element_anywhere_is_found(bad):
    for seed in range(12):
        ts = grads(seed)
        gen = torch.Generator().manual_seed(100 + seed)
        which = int(torch.randint(len(ts), (1,), generator=gen))
        if ts[which].numel() == 0:
            which = 0
        flat = ts[which].view(-1)
        flat[int(torch.randint(flat.numel(), (1,), generator=gen))] = bad
        assert all_finite(ts) is False
        assert oracle(ts) is False


def test_finite_extremes_pass():
    info = torch.finfo(torch.float32)
    edge = torch.tensor(
        [info.max, -info.max, info.tiny, info.tiny / 8, -0.0, 0.0, info.min]
    )  # tiny/8: denormal
    ts = [*grads(0), edge]
    assert all_finite(ts) is True and oracle(ts) is True
    assert all_finite([]) is True


def test_what_the_kernel_does_not_take_goes_the_torch_way():
    ts = [t.double() for t in grads(1)]
    assert all_finite(ts) is True
    ts[2][5, 3] = float("inf")
    assert all_finite(ts) is False
    strided = torch.randn(40, 6)[:, ::2]
    assert all_finite([strided]) is True
    strided[3, 1] = float("nan")
    assert all_finite([strided]) is False
