"""tmrl.custom.utils.nn: copy_shared shares memory without sharing the module object; no_grad."""

from __future__ import annotations

import torch

from tmrl.custom.utils.nn import copy_shared, no_grad


def _net() -> torch.nn.Module:
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4), torch.nn.Linear(4, 2))
    return net


def test_copy_shared_shares_parameter_and_buffer_memory():
    net = _net()
    twin = copy_shared(net)
    assert twin is not net
    for (name, a), (name_b, b) in zip(
        net.state_dict(keep_vars=True).items(), twin.state_dict(keep_vars=True).items()
    ):
        assert name == name_b
        assert a is not b
        assert a.untyped_storage().data_ptr() == b.untyped_storage().data_ptr(), name


def test_in_place_updates_are_seen_by_the_copy_and_back():
    net = _net()
    twin = copy_shared(net)
    opt = torch.optim.SGD(net.parameters(), lr=0.5)
    x = torch.randn(8, 3)
    net(x).square().sum().backward()
    opt.step()
    for a, b in zip(net.parameters(), twin.parameters()):
        assert torch.equal(a, b)
    with torch.no_grad():
        next(twin.parameters()).fill_(3.0)
    assert torch.all(next(net.parameters()) == 3.0)


def test_copy_shared_keeps_its_own_flags_and_mode():
    net = _net()
    twin = no_grad(copy_shared(net))
    twin.eval()
    assert all(p.requires_grad for p in net.parameters())
    assert not any(p.requires_grad for p in twin.parameters())
    assert net.training and not twin.training


def test_no_grad_returns_the_module_and_blocks_gradients():
    net = _net()
    same = no_grad(net)
    assert same is net
    out = net.eval()(torch.randn(2, 3))
    assert not out.requires_grad
