"""The observation encoder: one-hot for small integer codes, linear for everything else."""

import numpy as np
import torch
from gymnasium import spaces

from thci.config import TrainConfig
from thci.envs.factory import make_vector_env
from thci.rl.encoders import OneHotLinear, observation_categories
from thci.rl.trainer import build_agent


def test_categories_only_for_small_integer_codes():
    codes = spaces.Box(0, np.array([10, 5, 2, 1]), dtype=np.uint8)
    assert observation_categories(codes) == [11, 6, 3, 2]
    assert observation_categories(spaces.Box(0.0, 1.0, (4,), dtype=np.float32)) is None
    assert observation_categories(spaces.Box(0, 255, (4,), dtype=np.uint8)) is None  # pixels
    assert observation_categories(spaces.Box(0, 1, (4,), dtype=np.int64)) is None  # binary
    assert observation_categories(spaces.Box(-2, 2, (4,), dtype=np.int64)) is None  # shifted
    babyai = make_vector_env("thci/BabyAI-L1-v0", 1)
    categories = observation_categories(babyai.single_observation_space)
    babyai.close()
    assert categories is not None and len(categories) == 151 and max(categories) == 11


def test_one_hot_linear_equals_a_linear_layer_on_the_one_hot_expansion():
    torch.manual_seed(0)
    categories = [3, 2, 4]
    layer = OneHotLinear(categories, 5)
    obs = torch.tensor([[2, 0, 3], [0, 1, 1]], dtype=torch.uint8)
    one_hot = torch.cat(
        [torch.nn.functional.one_hot(obs[:, i].long(), n) for i, n in enumerate(categories)], -1
    ).float()
    expected = one_hot @ layer.embedding.weight + layer.bias
    assert torch.allclose(layer(obs), expected, atol=1e-6)
    # A float copy of the codes (what the rollout feeds the agent) gives the same features.
    assert torch.allclose(layer(obs.float()), expected, atol=1e-6)


def test_trainer_builds_a_one_hot_encoder_for_babyai_and_a_linear_one_for_the_maze():
    for env_id, first_layer in (
        ("thci/BabyAI-L1-v0", OneHotLinear),
        ("thci/PaperMaze-L1-v0", torch.nn.Linear),
    ):
        config = TrainConfig(env=env_id, num_envs=1)
        envs = make_vector_env(env_id, 1)
        agent = build_agent(config, envs)
        obs, _ = envs.reset(seed=0)
        envs.close()
        assert isinstance(agent.encoder[0], first_layer)
        logits, _, _ = agent(
            torch.as_tensor(obs, dtype=torch.float32)[None], agent.initial_state(1)
        )
        assert logits.shape == (1, 1, agent.actor[-1].out_features)
