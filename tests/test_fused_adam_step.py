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


def test_a_torch_whose_private_op_takes_other_arguments_falls_back_to_adam_step(monkeypatch, caplog):
    """The op is private: another torch may rename its arguments. The step then hands the update to
    Adam.step with the step counts as they were (the result still equals torch's), says so once, and
    does not try the op again."""
    from stg_node.avatar import optim

    (ours, adam_a), (theirs, adam_b), gen = _pair(1)
    for _ in range(2):  # states exist from here on
        state = gen.get_state()
        _grads(ours, gen)
        gen.set_state(state)
        _grads(theirs, gen)
        adam_a.step()
        adam_b.step()
    calls = []

    def renamed(*args, **kwargs):
        calls.append(1)
        raise TypeError("_fused_adam_() got an unexpected keyword argument 'lr'")

    real = torch._fused_adam_
    monkeypatch.setattr(optim, "_FUSED_CALL", {"broken": False})  # this test's own process-wide flag
    for _ in range(3):
        state = gen.get_state()
        _grads(ours, gen)
        gen.set_state(state)
        _grads(theirs, gen)
        monkeypatch.setattr(torch, "_fused_adam_", renamed)
        with caplog.at_level("WARNING", logger="stg_node.avatar.optim"):
            assert not _fused_adam_step(adam_a)
        monkeypatch.setattr(torch, "_fused_adam_", real)  # torch's own Adam.step runs the real op
        adam_a.step()
        adam_b.step()
    assert len(calls) == 1  # tried once, then left alone
    assert sum("refused the call" in r.getMessage() for r in caplog.records) == 1
    for a, b in zip(ours, theirs, strict=True):
        assert torch.equal(a, b)
        assert torch.equal(adam_a.state[a]["step"], adam_b.state[b]["step"])
