"""The project's Adam against torch.optim.Adam (the reference implementation): the same parameters bit for
bit as its fused update, step by step, with groups, changed rates, frozen parameters and a state handed
across; within rounding of its unfused updates."""

import pytest
import torch

from delta.optim import Adam


def problem(seed: int):
    """Parameters of several shapes and a loss with curvature, one of them frozen at some steps."""
    g = torch.Generator().manual_seed(seed)
    params = [torch.randn(7, 3, generator=g).requires_grad_(), torch.randn(5, generator=g).requires_grad_(),
              torch.randn(2, 2, 4, generator=g).requires_grad_(), torch.randn(3, generator=g).requires_grad_()]  # fmt: skip
    targets = [torch.randn(p.shape, generator=g) for p in params]

    def loss():
        return sum(((p - t) ** 2 * (1 + i)).sum() + p.sin().sum() for i, (p, t) in enumerate(zip(params, targets)))

    return params, loss


def groups(params):
    return [{"params": params[:2], "lr": 0.05, "name": "a"}, {"params": params[2:], "lr": 0.01, "name": "b"}]


def run(opt_cls, seed: int, steps: int, **kw):
    params, loss = problem(seed)
    opt = opt_cls(groups(params), eps=1e-12, **kw)
    for step in range(steps):
        params[3].requires_grad_(step % 3 != 1)  # frozen at some steps: no gradient, not stepped
        opt.zero_grad(set_to_none=True)
        loss().backward()
        opt.step()
        for gr in opt.param_groups:
            gr["lr"] *= 0.97
    return params, opt


def test_every_step_matches_torch_bit_for_bit():
    ours, _ = run(Adam, 0, 40)
    ref, _ = run(torch.optim.Adam, 0, 40, fused=True)
    for a, b in zip(ours, ref):
        assert torch.equal(a, b)
    moved = problem(0)[0]
    assert all(not torch.equal(a, m) for a, m in zip(ours, moved))  # it did optimise


@pytest.mark.parametrize("foreach", [False, True])
def test_the_unfused_updates_agree_within_rounding(foreach):
    ours, _ = run(Adam, 0, 40)
    ref, _ = run(torch.optim.Adam, 0, 40, foreach=foreach)
    for a, b in zip(ours, ref):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_float64_parameters_and_a_group_of_two_dtypes():
    """The kernel takes one dtype a call: a group that mixes them is stepped in one call per dtype."""
    a = torch.tensor([1.0, -2.0], dtype=torch.float64, requires_grad=True)
    b = torch.tensor([0.5], requires_grad=True)
    ref = [a.detach().clone().requires_grad_(), b.detach().clone().requires_grad_()]
    ours, theirs = Adam([a, b], lr=0.1), torch.optim.Adam(ref, lr=0.1, fused=True)
    for _ in range(5):
        for opt, (x, y) in ((ours, (a, b)), (theirs, ref)):
            opt.zero_grad()
            ((x - 3) ** 2).sum().add((y + 1).square().sum()).backward()
            opt.step()
    assert a.dtype == torch.float64 and torch.equal(a, ref[0]) and torch.equal(b, ref[1])
    assert float(a.detach()[0]) > 1.0 and float(b.detach()[0]) < 0.5  # moved toward 3 and -1


def test_a_state_saved_by_either_resumes_in_the_other():
    whole, _ = run(Adam, 1, 30)
    for first, second in ((torch.optim.Adam, Adam), (Adam, torch.optim.Adam), (Adam, Adam)):
        params, opt = run(first, 1, 12, **({"fused": True} if first is torch.optim.Adam else {}))
        saved = {k: v for k, v in opt.state_dict().items()}
        params2, loss = problem(1)
        with torch.no_grad():
            for p, q in zip(params2, params):
                p.copy_(q)
        opt2 = second(groups(params2), eps=1e-12, **({"fused": True} if second is torch.optim.Adam else {}))
        opt2.load_state_dict(saved)
        for step in range(12, 30):
            params2[3].requires_grad_(step % 3 != 1)
            opt2.zero_grad(set_to_none=True)
            loss().backward()
            opt2.step()
            for gr in opt2.param_groups:
                gr["lr"] *= 0.97
        assert all(torch.equal(a, b) for a, b in zip(params2, whole)), (first, second)
        assert [g["name"] for g in opt2.param_groups] == ["a", "b"]


def test_a_state_of_other_groups_is_refused():
    params, opt = run(Adam, 2, 3)
    other = Adam([{"params": params, "lr": 0.1}])
    with pytest.raises(ValueError, match="other groups"):
        other.load_state_dict(opt.state_dict())
    decayed = torch.optim.Adam(groups(params), weight_decay=0.01).state_dict()
    with pytest.raises(ValueError, match="weight_decay"):
        Adam(groups(params)).load_state_dict(decayed)
    with pytest.raises(ValueError, match="no parameters"):
        Adam([])


def test_a_first_step_imports_no_compiler():
    """What the class is for: a process that optimises does not pay for ``torch._dynamo`` (~2 s)."""
    import subprocess
    import sys

    code = ("import sys, torch\nfrom delta.optim import Adam\np = torch.zeros(3, requires_grad=True)\n"
            "o = Adam([p], lr=0.1)\n(p - 1).square().sum().backward()\no.step()\n"
            "print('torch._dynamo' in sys.modules, p.detach().tolist())")  # fmt: skip
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    imported, values = res.stdout.split(" ", 1)
    assert imported == "False"
    # Adam's first step is the rate against the gradient's sign
    assert all(abs(float(v) - 0.1) < 1e-6 for v in values.strip(" []\n").split(","))
