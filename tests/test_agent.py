"""The actor-critic's heads: concat and FiLM (``--heads``)."""

import torch

from thci.memory import make_memory
from thci.rl.agent import ActorCritic


def _agents() -> tuple[ActorCritic, ActorCritic]:
    torch.manual_seed(0)
    concat = ActorCritic(5, 3, make_memory("lstm", 8, 8), 8)
    film = ActorCritic(5, 3, make_memory("lstm", 8, 8), 8, film=True)
    missing, unexpected = film.load_state_dict(concat.state_dict(), strict=False)
    assert sorted(missing) == ["film.bias", "film.weight"] and not unexpected
    return concat, film


def test_film_heads_start_as_the_concat_heads():
    concat, film = _agents()
    inputs = torch.randn(2, 6, 5)
    state = concat.initial_state(2)
    for a, b in zip(concat(inputs, state), film(inputs, state), strict=True):
        torch.testing.assert_close(a, b)


def test_film_is_trained_by_the_policy_loss_and_then_conditions_on_memory():
    _, film = _agents()
    assert {id(p) for p in film.film.parameters()} <= {id(p) for p in film.policy_parameters()}
    inputs = torch.randn(4, 6, 5)
    logits, values, _ = film(inputs, film.initial_state(4))
    (logits.square().sum() + values.sum()).backward()
    assert film.film.weight.grad.abs().sum() > 0
    # with a scale of -1 everywhere the heads see no observation features, only the memory
    with torch.no_grad():
        film.film.bias[:8] = -1.0
        film.film.weight.zero_()
    out = torch.randn(3, 8)
    features = torch.randn(3, 8)
    a, _ = film._heads(out, features)
    b, _ = film._heads(out, torch.randn(3, 8))
    torch.testing.assert_close(a, b)
    c, _ = film._heads(torch.randn(3, 8), features)
    assert not torch.allclose(a, c)
