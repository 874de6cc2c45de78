"""optim._fused_adam_step (torch._fused_adam_ called straight, per group) against torch's own
Adam.step on a copy: bit-identical parameters and moments over several steps, groups with their
own rates, a parameter without a gradient, and the fallback where state is missing."""

import torch

from stg_node.avatar.optim import _fused_adam_step


def _pair(seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    shapes = [(50, 3), (50, 4), (7,), (3, 5)]
    params = [torch.randn(s, generator=gen) for s in shapes]

    def build():
        ps = [torch.nn.Parameter(p.clone()) for p in params]
        groups = [
            {"params": ps[:1], "lr": 1e-2},
            {"params": ps[1:3], "lr": 3e-3},
            {"params": ps[3:], "lr": 0.0},
        ]
        return ps, torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)

    return build(), build(), gen


def _grads(ps, gen, skip=None):
    for i, p in enumerate(ps):
        p.grad = None if i == skip else torch.randn(p.shape, generator=gen)


def test_bit_identical_to_torch_adam_over_steps():
    (ours, adam_a), (theirs, adam_b), gen = _pair()
    for step in range(6):
        state = gen.get_state()
        _grads(ours, gen, skip=2 if step == 3 else None)
        gen.set_state(state)
        _grads(theirs, gen, skip=2 if step == 3 else None)
        if step == 2:
            adam_a.param_groups[1]["lr"] = adam_b.param_groups[1]["lr"] = 7e-4
        done = _fused_adam_step(adam_a)
        assert done == (step > 0)  # the first step creates the state: torch's own step does it
        if not done:
            adam_a.step()
        adam_b.step()
        for a, b in zip(ours, theirs, strict=True):
            assert torch.equal(a, b)
            sa, sb = adam_a.state[a], adam_b.state[b]
            assert torch.equal(sa["step"], sb["step"])
            assert torch.equal(sa["exp_avg"], sb["exp_avg"]) and torch.equal(
                sa["exp_avg_sq"], sb["exp_avg_sq"]
            )
    assert float(adam_a.state[ours[2]]["step"]) == 5  # skipped once without a gradient


def test_unfused_adam_is_left_to_torch():
    p = torch.nn.Parameter(torch.ones(3))
    adam = torch.optim.Adam([p], lr=0.1)
    p.grad = torch.ones(3)
    adam.step()
    p.grad = torch.ones(3)
    before = p.detach().clone()
    assert not _fused_adam_step(adam)
    assert torch.equal(p.detach(), before)
