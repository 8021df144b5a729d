"""The observation encoder: one-hot for small integer codes, linear for everything else."""

import numpy as np
import pytest
import torch
from gymnasium import spaces

from thci.config import TrainConfig
from thci.envs.factory import make_vector_env
from thci.errors import ThciError
from thci.rl.encoders import CellEncoder, GridEncoder, OneHotLinear, observation_categories
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


def test_ci_settings_do_not_change_the_initial_weights_of_a_method_without_ci():
    # A gate built and thrown away would draw from torch's RNG, so the same seed would start an
    # LSTM run elsewhere whenever a CI setting changed the gate (it did, with cell-set codes).
    envs = make_vector_env("thci/BabyAI-L1-v0", 1)
    weights = []
    for discretizer in ("exact", "cell-set"):
        torch.manual_seed(0)
        config = TrainConfig(env="thci/BabyAI-L1-v0", method="lstm", discretizer=discretizer)
        agent = build_agent(config, envs)
        assert agent.gate is None
        weights.append(agent.state_dict())
    envs.close()
    assert weights[0].keys() == weights[1].keys()
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


def test_grid_encoder_reads_a_cell_by_its_value_and_place_and_keeps_the_rest():
    torch.manual_seed(0)
    layout, categories = (2, 9, 2), [2, 2] + [4, 3] * 9  # two leading entries, 3x3 cells
    encoder = GridEncoder(20, layout, categories, out_size=8)
    obs = torch.zeros(5, 20)
    obs[:, 2:] = torch.randint(0, 3, (5, 18)).float()
    batched = encoder(obs.view(5, 1, 20))
    assert batched.shape == (5, 1, 8)
    assert torch.allclose(batched[:, 0], torch.stack([encoder(o) for o in obs]), atol=1e-6)
    moved = obs.clone()
    moved[:, 2:4], moved[:, 4:6] = obs[:, 4:6], obs[:, 2:4]  # swap two cells: another image
    assert not torch.allclose(encoder(moved), encoder(obs))
    other_rest = obs.clone()
    other_rest[:, 0] = 1  # the entries before the cells reach the features too
    assert not torch.allclose(encoder(other_rest), encoder(obs))


@pytest.mark.parametrize(("kind", "first_layer"), [("grid", GridEncoder), ("cells", CellEncoder)])
def test_trainer_builds_a_cell_encoder_on_request_and_refuses_it_where_cells_are_missing(
    kind, first_layer
):
    config = TrainConfig(env="thci/BabyAI-L1-v0", num_envs=1, encoder=kind)
    envs = make_vector_env(config.env, 1)
    agent = build_agent(config, envs)
    obs, _ = envs.reset(seed=0)
    envs.close()
    assert isinstance(agent.encoder[0], first_layer)
    logits, _, _ = agent(torch.as_tensor(obs, dtype=torch.float32)[None], agent.initial_state(1))
    assert logits.shape == (1, 1, 6) and torch.isfinite(logits).all()
    maze = make_vector_env("thci/PaperMaze-L1-v0", 1)
    with pytest.raises(ThciError, match=f"--encoder {kind}"):
        build_agent(TrainConfig(env="thci/PaperMaze-L1-v0", num_envs=1, encoder=kind), maze)
    maze.close()


def _cell_values(pairs: list[tuple[int, int]]) -> torch.Tensor:
    """Observations of one leading entry (1) and two cells of (object, colour, state)."""
    return torch.tensor([[1, obj, colour, 0, 1, 0, 0] for obj, colour in pairs])


def test_cell_encoder_reads_entries_by_place_and_whole_cells_pooled_over_places():
    torch.manual_seed(0)
    layout, categories = (1, 2, 3), [3] + [5, 4, 2] * 2  # a leading entry, two cells
    encoder = CellEncoder(7, layout, categories, out_size=6)
    obs = torch.tensor([[2, 4, 3, 1, 0, 0, 0], [0, 1, 2, 0, 3, 1, 1]])
    # Category of a cell: (object * 4 + colour) * 2 + state.
    joint = torch.tensor([[4 * 8 + 3 * 2 + 1, 0], [1 * 8 + 2 * 2, 3 * 8 + 1 * 2 + 1]])
    assert torch.equal(encoder.cell_categories(obs.float()), joint)
    # By place: a linear layer on the one-hot of every entry, as the flat encoder reads it.
    one_hot = torch.cat(
        [torch.nn.functional.one_hot(obs[:, i], n) for i, n in enumerate(categories)], -1
    ).float()
    by_place = one_hot @ encoder.by_place.embedding.weight + encoder.by_place.bias
    # Pooled: the max over cells of ReLU(one shared embedding), the same wherever a cell is.
    pooled = torch.relu(encoder.cell_embedding.weight[joint]).amax(dim=1)
    assert torch.allclose(encoder.pooled(obs), pooled)
    swapped = obs[:, [0, 4, 5, 6, 1, 2, 3]]
    assert torch.allclose(encoder.pooled(swapped), pooled)
    assert not torch.allclose(encoder(swapped), encoder(obs))  # the by-place branch differs
    expected = by_place + encoder.pooled_out(pooled)
    assert torch.allclose(encoder(obs.float()), expected, atol=1e-6)


def test_cell_encoder_pooling_has_the_gradient_of_relu_then_max_over_looked_up_cells():
    torch.manual_seed(0)
    categories = [3] + [5, 4, 2] * 4  # a leading entry, four cells
    encoder = CellEncoder(13, (1, 4, 3), categories, out_size=8)
    # (2, 3) leading dims; repeated cell values in a view, and views sharing values.
    obs = torch.stack([torch.randint(0, n, (2, 3)) for n in categories], dim=-1).float()
    obs[0, 0, 4:7] = obs[0, 0, 1:4]
    weights = torch.randn(2, 3, 8)
    (encoder.pooled(obs) * weights).sum().backward()
    fast = encoder.cell_embedding.weight.grad.clone()
    encoder.zero_grad()
    looked_up = encoder.cell_embedding(encoder.cell_categories(obs))  # (2, 3, 4 cells, 8)
    explicit = torch.relu(looked_up).amax(dim=-2)
    (explicit * weights).sum().backward()
    assert encoder.pooled(obs).shape == (2, 3, 8)
    assert torch.allclose(encoder.pooled(obs), explicit)
    assert fast.abs().sum() > 0 and torch.allclose(fast, encoder.cell_embedding.weight.grad)


def test_cell_encoder_tells_a_green_wall_from_a_green_door_where_per_entry_one_hot_cannot():
    # A per-channel one-hot layer is additive in object and colour: the change from blue to
    # green is the same vector for a wall and for a door, so no linear readout can single out
    # "green wall" (an XOR of the two channels). The cell's whole value can.
    torch.manual_seed(0)
    layout, categories = (1, 2, 3), [3] + [5, 4, 2] * 2
    wall, door, green, blue = 2, 4, 1, 2
    obs = _cell_values([(wall, green), (wall, blue), (door, green), (door, blue)])
    per_channel = OneHotLinear(categories, 8)(obs)
    assert torch.allclose(per_channel[0] - per_channel[1], per_channel[2] - per_channel[3])
    cells = CellEncoder(7, layout, categories, 8)(obs)
    assert not torch.allclose(cells[0] - cells[1], cells[2] - cells[3], atol=1e-3)
    # A linear readout of the cell features fits "is a green wall" exactly.
    target = torch.tensor([1.0, 0.0, 0.0, 0.0])
    design = torch.cat((cells, torch.ones(4, 1)), 1).detach()
    fit = design @ torch.linalg.lstsq(design, target[:, None]).solution
    assert torch.allclose(fit.squeeze(1), target, atol=1e-4)


def test_cell_encoder_refuses_a_layout_beyond_the_observation_or_too_many_values():
    for encoder in (CellEncoder, GridEncoder):  # the layout's own check, shared by both
        with pytest.raises(ThciError, match="needs 151 entries"):
            encoder(100, (4, 49, 3), [11, 6, 3] * 50, 8)
    with pytest.raises(ThciError, match="--encoder cells would embed 125000 cell values"):
        CellEncoder(151, (0, 49, 3), [50] * 151, 8)
    with pytest.raises(ThciError, match="square"):
        GridEncoder(151, (0, 50, 3), [3] * 151, 8)


@pytest.mark.parametrize("method", ["lstm", "t-hci", "wmg", "sai"])
def test_padding_skips_the_encoder_and_gate_and_leaves_the_real_steps_unchanged(method):
    config = TrainConfig(env="thci/BabyAI-L1-v0", num_envs=2, encoder="cells", method=method)
    envs = make_vector_env(config.env, 2)
    agent = build_agent(config, envs)
    obs, _ = envs.reset(seed=0)
    steps = [obs]
    for _ in range(5):
        obs, *_ = envs.step(np.array([2, 1]))
        steps.append(obs)
    envs.close()
    inputs = torch.as_tensor(np.stack(steps, axis=1), dtype=torch.float32)  # (2, 6, D)
    side = torch.zeros(2, 6, agent.input_size - agent.observation_size)
    inputs = torch.cat((inputs, side), dim=-1)
    valid = torch.tensor([[True] * 6, [True] * 3 + [False] * 3])  # row 1: 3 steps, padded
    inputs[1, 3:] = 0.0
    calls, gate_calls = [], []
    agent.encoder.register_forward_hook(lambda _m, args, _out: calls.append(args[0].shape[0]))
    if agent.gate is not None:  # an active gate: its keep mask shapes the memory's input
        agent.gate.active.fill_(True)
        agent.gate.register_forward_hook(
            lambda _m, args, _out: gate_calls.append(args[0].shape[:-1].numel())
        )
    full_logits, full_values = agent.evaluate(inputs, agent.initial_state(2))
    logits, values = agent.evaluate(inputs, agent.initial_state(2), valid)
    assert calls[-1] == 9  # the encoder ran on the 9 real steps only
    assert gate_calls == ([] if agent.gate is None else [12, 9])  # the gate too
    assert torch.allclose(logits[valid], full_logits[valid], atol=1e-6)
    assert torch.allclose(values[valid], full_values[valid], atol=1e-6)
