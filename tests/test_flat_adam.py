"""FlatAdam is torch's Adam, bit for bit, in fewer operations."""

import pytest
import torch
from torch import nn

from thci.causal.flat_adam import FlatAdam


def _parameters(seed: int) -> list[nn.Parameter]:
    torch.manual_seed(seed)
    shapes = [(4, 15, 16), (4, 14, 16), (4, 1, 64), (4, 84, 64), (4, 64, 1), (3,)]
    return [nn.Parameter(torch.randn(shape)) for shape in shapes]


def _loss(params: list[nn.Parameter], step: int) -> torch.Tensor:
    """A loss whose gradients vary in scale and sign from step to step (and are exactly 0 for
    some entries, as for the embedding rows of codes a batch does not hold)."""
    generator = torch.Generator().manual_seed(step)
    total = torch.zeros(())
    for p in params:
        target = torch.randn(p.shape, generator=generator) * (step % 3 + 1)
        keep = torch.rand(p.shape, generator=generator) < 0.8
        total = total + ((p - target).pow(2) * keep).sum() * 10.0 ** (step % 4 - 2)
    return total


def _fit(params: list[nn.Parameter], optimizer, steps: range) -> None:
    for step in steps:
        optimizer.zero_grad()
        _loss(params, step).backward()
        optimizer.step()


@pytest.mark.parametrize("lr", [3e-3, 1e-1])
@pytest.mark.parametrize("foreach", [True, False])
def test_flat_adam_gives_torch_adams_parameters_bit_for_bit(lr, foreach):
    """Against both of torch's implementations: multi-tensor, and per tensor (its default on
    the CPU)."""
    ours, theirs = _parameters(0), _parameters(0)
    _fit(ours, FlatAdam(ours, lr=lr), range(60))
    _fit(theirs, torch.optim.Adam(theirs, lr=lr, foreach=foreach), range(60))
    for a, b in zip(ours, theirs, strict=True):
        assert torch.equal(a, b)
    assert not torch.equal(ours[0], _parameters(0)[0])  # it did move them


def test_flat_adam_continues_from_torch_adams_state_and_from_its_own():
    """A fit continued from torch's Adam state, then from FlatAdam's, gives what torch's Adam
    alone gives."""
    reference = _parameters(1)
    _fit(reference, torch.optim.Adam(reference, lr=1e-2, foreach=True), range(30))

    mixed = _parameters(1)
    first = torch.optim.Adam(mixed, lr=1e-2, foreach=True)
    _fit(mixed, first, range(10))
    second = FlatAdam(mixed, lr=1e-2)
    second.load_state_dict(first.state_dict())
    _fit(mixed, second, range(10, 20))
    third = FlatAdam(mixed, lr=1e-2)
    third.load_state_dict(second.state_dict())
    _fit(mixed, third, range(20, 30))
    for a, b in zip(mixed, reference, strict=True):
        assert torch.equal(a, b)


def test_flat_adam_refuses_a_parameter_without_gradient():
    params = _parameters(2)
    optimizer = FlatAdam(params, lr=1e-3)
    params[0].sum().backward()
    with pytest.raises(RuntimeError, match="gradient for every parameter"):
        optimizer.step()
