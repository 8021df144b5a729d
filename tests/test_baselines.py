"""Baselines and ablations (nm, wmg, sai, hai, oracle): shapes, resets, each module's defining
property, a two-step recall task each memory solves and a memoryless policy cannot, and short
end-to-end runs with every algorithm."""

import json

import pytest
import torch
from test_cli import (
    FAST,
    assert_one_line_error,
    assert_stop_and_resume_matches,
    run_cli,
    train,
)

from thci.causal.taie import observation_weights, taie_of_rollout
from thci.envs.factory import make_vector_env
from thci.memory import NOISE, NeuralMap, make_memory
from thci.memory.wmg import babyai_factors
from thci.rl.agent import ActorCritic
from thci.rl.rollout import RolloutCollector

OBS = 3  # the recall task's observations: cue A, cue B, blank
SMALL = {
    "observation_size": OBS,
    "nm_map_size": 4,
    "nm_channels": 8,
    "wmg_memos": 4,
    "wmg_layers": 1,
    "wmg_heads": 2,
    "wmg_head_size": 8,
    "window": 6,
}
METHODS = ["nm", "wmg", "sai", "hai", "oracle"]


def agent_for(method: str, **options) -> ActorCritic:
    memory = make_memory(method, 16, 16, **{**SMALL, **options})
    return ActorCritic(OBS, 2, memory, 16)


def side_inputs(agent: ActorCritic, obs: torch.Tensor) -> torch.Tensor:
    """Inputs (B, L, OBS + side) for the recall task: position (0, t), label = 'is a cue',
    fresh noise; what the rollout collector would append from info."""
    batch, steps, _ = obs.shape
    columns = [obs]
    for name, width in agent.memory.side_inputs:
        if name == "agent_pos":
            t = torch.arange(steps).float()
            columns.append(torch.stack((torch.zeros(steps), t), -1).expand(batch, -1, -1))
        elif name == "causal":
            columns.append(obs[..., :2].sum(-1, keepdim=True))
        else:
            assert name == NOISE
            columns.append(torch.rand(batch, steps, width))
    return torch.cat(columns, dim=-1)


def recall_batch(agent: ActorCritic, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A cue at step 0, a blank at step 1: the right action at step 1 is the cue."""
    cue = torch.randint(2, (batch,))
    obs = torch.zeros(batch, 2, OBS)
    obs[torch.arange(batch), 0, cue] = 1.0
    obs[:, 1, 2] = 1.0
    return side_inputs(agent, obs), cue


def recall_accuracy(method: str, steps: int = 300) -> float:
    torch.manual_seed(0)
    agent = agent_for(method)
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-2)
    for step in range(steps):
        inputs, cue = recall_batch(agent, 64)
        logits, _, _ = agent(inputs, agent.initial_state(64))
        if step % 25 == 0 and bool((logits[:, 1].argmax(-1) == cue).all()):
            break  # learnt (judged below on fresh data)
        loss = torch.nn.functional.cross_entropy(logits[:, 1], cue)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        inputs, cue = recall_batch(agent, 512)
        logits, _, _ = agent(inputs, agent.initial_state(512))
    return float((logits[:, 1].argmax(-1) == cue).float().mean())


@pytest.mark.parametrize("method", METHODS)
def test_memory_matters_two_step_recall(method):
    assert recall_accuracy(method) >= 0.97


def test_memoryless_policy_cannot_recall():
    assert recall_accuracy("mlp") <= 0.6


@pytest.mark.parametrize("method", METHODS)
def test_shapes_and_sequence_call_equals_step_loop_with_resets(method):
    torch.manual_seed(0)
    agent = agent_for(method)
    obs = torch.rand(3, 7, OBS).round()
    obs[..., :2] *= 3  # positions up to 3 for nm, labels 0/1 for the oracle's side column
    inputs = torch.cat((obs, torch.rand(3, 7, agent.memory.side_size).round()), -1)
    if method == "nm":
        inputs[..., OBS:] = torch.randint(4, (3, 7, 2)).float()
    if method == "oracle":
        inputs[..., OBS:] = 1.0  # every step labelled causal: the memory carries all of them
    starts = torch.zeros(3, 7, dtype=torch.bool)
    starts[:, 0] = True
    starts[1, 4] = True
    state = agent.initial_state(3)
    assert state.shape == (3, agent.memory.state_size)
    step_values = []
    for t in range(7):
        logits, values, state = agent.step(inputs[:, t], state, starts[:, t])
        assert logits.shape == (3, 2) and values.shape == (3,)
        assert state.shape == (3, agent.memory.state_size)
        step_values.append(values)
    step_values = torch.stack(step_values, 1)
    logits, seq_values, final = agent(inputs, agent.initial_state(3))
    assert logits.shape == (3, 7, 2) and seq_values.shape == (3, 7)
    assert final.shape == (3, agent.memory.state_size)
    assert torch.allclose(seq_values[[0, 2]], step_values[[0, 2]], atol=1e-5)
    # env 1's second episode starts from a zero state in the step loop
    _, tail, _ = agent(inputs[1:2, 4:], agent.initial_state(1))
    assert torch.allclose(tail[0], step_values[1, 4:], atol=1e-5)
    assert not torch.allclose(seq_values[1, 4:], step_values[1, 4:], atol=1e-3)


def test_neural_map_writes_only_at_the_agent_position():
    torch.manual_seed(0)
    memory = make_memory("nm", 16, 16, nm_map_size=5, nm_channels=4)
    state = torch.randn(2, memory.state_size)
    position = torch.tensor([[1.0, 3.0], [4.0, 0.0]])
    x = torch.cat((torch.randn(2, 1, 16), position.unsqueeze(1)), dim=-1)
    out, new = memory(x, state)
    assert out.shape == (2, 1, 12)
    changed = (new != state).view(2, 4, 5, 5).any(dim=1)
    expected = torch.zeros(2, 5, 5, dtype=torch.bool)
    expected[0, 1, 3] = expected[1, 4, 0] = True
    assert torch.equal(changed, expected)
    # the written cell is the output's last C values
    assert torch.allclose(new.view(2, 4, 5, 5)[0, :, 1, 3], out[0, 0, 8:])


def test_neural_map_rejects_positions_outside_the_map():
    memory = make_memory("nm", 16, 16, nm_map_size=5, nm_channels=4)
    x = torch.cat((torch.randn(1, 1, 16), torch.tensor([[[2.0, 5.0]]])), dim=-1)
    with pytest.raises(Exception, match="--nm-map-size"):
        memory(x, memory.initial_state(1))


def test_wmg_fifo_evicts_the_oldest_memo_and_ages_shift_by_one():
    torch.manual_seed(0)
    memory = make_memory("wmg", 16, 16, **SMALL)
    memos = memory.memos
    _, state = memory(torch.rand(2, memos + 2, OBS), memory.initial_state(2))  # FIFO full
    old_memos, old_valid = memory.split(state)
    assert bool(old_valid.all())
    _, new_state = memory(torch.rand(2, 1, OBS), state)
    new_memos, new_valid = memory.split(new_state)
    assert bool(new_valid.all())
    assert torch.equal(new_memos[:, 1:], old_memos[:, :-1])  # age k -> k + 1, oldest gone
    assert not torch.allclose(new_memos[:, 0], old_memos[:, 0])
    _, first = memory(torch.rand(2, 1, OBS), memory.initial_state(2))
    assert memory.split(first)[1].sum(dim=1).tolist() == [1, 1]  # one memo after one step


def reference_wmg(memory, x: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """WMG step by step as the paper describes it, with torch's own Transformer layers (the
    memory's weights copied in): every step embeds the Memos with their one-hot ages anew."""
    width = memory.output_size
    layers = []
    for ours in memory.layers:
        layer = torch.nn.TransformerEncoderLayer(
            width, ours.heads, ours.ff_in.out_features, dropout=0.0, batch_first=True
        )
        with torch.no_grad():
            layer.self_attn.in_proj_weight.copy_(ours.qkv.weight)
            layer.self_attn.in_proj_bias.copy_(ours.qkv.bias)
        layer.self_attn.out_proj.load_state_dict(ours.out.state_dict())
        layer.linear1.load_state_dict(ours.ff_in.state_dict())
        layer.linear2.load_state_dict(ours.ff_out.state_dict())
        layer.norm1.load_state_dict(ours.norm_attention.state_dict())
        layer.norm2.load_state_dict(ours.norm_ff.state_dict())
        layers.append(layer)
    memos, valid = memory.split(state)
    outputs = []
    for t in range(x.shape[1]):
        tokens = torch.cat(
            (
                memory.core(x[:, t : t + 1]),
                memory.memo(torch.cat((memos, memory.ages.expand(len(x), -1, -1)), dim=-1)),
            ),
            dim=1,
        )
        mask = ~torch.cat((torch.ones(len(x), 1, dtype=torch.bool), valid), dim=1)
        for layer in layers:
            tokens = layer(tokens, src_key_padding_mask=mask)
        outputs.append(tokens[:, 0])
        memos = torch.cat((torch.tanh(memory.write(tokens[:, :1])), memos[:, :-1]), dim=1)
        valid = torch.cat((torch.ones(len(x), 1, dtype=torch.bool), valid[:, :-1]), dim=1)
    return torch.stack(outputs, dim=1), memos, valid


def test_wmg_computes_what_torch_transformer_layers_compute_step_by_step():
    torch.manual_seed(0)
    memory = make_memory("wmg", 16, 16, **{**SMALL, "wmg_layers": 2})
    _, state = memory(torch.rand(3, 2, OBS), memory.initial_state(3))  # 2 of 4 slots valid
    state = torch.cat((state[:2], memory.initial_state(1)))  # and an episode start
    x = torch.rand(3, 6, OBS)  # longer than the FIFO: the first Memos are evicted
    outputs, new_state = memory(x, state)
    expected, memos, valid = reference_wmg(memory, x, state)
    assert torch.allclose(outputs, expected, atol=1e-5)
    ours_memos, ours_valid = memory.split(new_state)
    assert torch.allclose(ours_memos, memos, atol=1e-5) and torch.equal(ours_valid, valid)
    _, short_state = memory(x[:, :1], state)  # fewer steps than slots: old Memos shift
    _, memos, valid = reference_wmg(memory, x[:, :1], state)
    ours_memos, ours_valid = memory.split(short_state)
    assert torch.allclose(ours_memos, memos, atol=1e-5) and torch.equal(ours_valid, valid)


def test_wmg_babyai_factors_are_the_visible_objects():
    obs = torch.zeros(151)
    view = obs[:147].view(7, 7, 3)  # minigrid's (x, y, channel)
    view[:, :, 0] = 1  # empty
    view[0, :, 0] = 2  # a wall column
    view[3, 5] = torch.tensor([5.0, 4.0, 0.0])  # a key
    view[6, 1] = torch.tensor([4.0, 1.0, 2.0])  # a locked door
    factors, valid = babyai_factors(obs)
    assert factors.shape == (49, 34) and int(valid.sum()) == 2
    key = factors[3 * 7 + 5]
    assert key[5] == 1 and key[11 + 4] == 1 and key[17] == 1  # type, colour, state one-hots
    assert key[20 + 3] == 1 and key[27 + 5] == 1  # view column 3, row 5


def test_sai_attention_sums_to_one_per_head_over_the_window():
    torch.manual_seed(0)
    agent = agent_for("sai")
    inputs = torch.rand(9, 3, OBS)
    starts = torch.zeros(9, 3, dtype=torch.bool)
    starts[0] = starts[5, 1] = True
    weights = observation_weights(agent, inputs, starts)
    assert weights.shape == (9, 3, 4)
    assert bool((weights >= 0).all())
    # env 1's episodes: steps 0-4 and 5-8, each head's weights sum to 1 inside each episode
    for episode in (slice(0, 5), slice(5, 9)):
        assert torch.allclose(weights[episode, 1].sum(0), torch.ones(4), atol=1e-5)
    # env 0's 9 steps exceed the window of 6: the 3 oldest get no attention
    assert bool((weights[:3, 0] == 0).all())
    assert torch.allclose(weights[3:, 0].sum(0), torch.ones(4), atol=1e-5)
    labels = torch.zeros(9, 3, dtype=torch.bool)
    dones = torch.zeros(9, 3, dtype=torch.bool)
    dones[4, 1] = dones[8] = True
    errors = taie_of_rollout(weights, labels, starts, dones)
    assert errors.shape == (4, 4)  # 4 complete episodes x 4 heads


def test_hai_selection_is_binary_and_trained_through_the_relaxation():
    torch.manual_seed(0)
    agent = agent_for("hai")
    inputs = side_inputs(agent, torch.rand(4, 10, OBS))
    weights = observation_weights(agent, inputs.transpose(0, 1))
    assert set(weights.unique().tolist()) == {0.0, 1.0}
    logits, _, _ = agent(inputs, agent.initial_state(4))
    logits.sum().backward()
    selector_grad = agent.memory.selector[0].weight.grad
    assert selector_grad is not None and bool(selector_grad.abs().sum() > 0)


def test_hai_reads_the_max_of_the_selected_values_and_nothing_of_the_others():
    torch.manual_seed(0)
    memory = make_memory("hai", 16, 16, **SMALL)
    features = torch.rand(2, 6, 16)
    selected = torch.tensor([[1, 0, 0, 1, 0, 0], [0, 1, 1, 0, 0, 1]], dtype=torch.bool)
    # logistic noise of +-13.8 decides the selection whatever the selector's small logits
    noise = torch.where(selected, 1 - 1e-6, 1e-6).unsqueeze(-1)
    read, _ = memory(torch.cat((features, noise), -1), memory.initial_state(2))
    values = memory.value(features)  # (2, 6, 16)
    for b in range(2):
        for t in range(6):
            chosen = selected[b, : t + 1].nonzero().flatten()
            expected = values[b, chosen].amax(0) if len(chosen) else torch.zeros(16)
            assert torch.allclose(read[b, t], expected)
    # an unselected step changes nothing that is read
    changed = features.clone()
    changed[~selected] = torch.rand(int((~selected).sum()), 16)
    other, _ = memory(torch.cat((changed, noise), -1), memory.initial_state(2))
    assert torch.equal(other, read)
    # runs from before the max read the mean (--hai-read mean)
    mean = make_memory("hai", 16, 16, **SMALL, hai_read="mean")
    mean.load_state_dict(memory.state_dict())
    read, _ = mean(torch.cat((features, noise), -1), mean.initial_state(2))
    chosen = selected[1, :3].nonzero().flatten()
    assert torch.allclose(read[1, 2], values[1, chosen].mean(0))


def test_oracle_keeps_exactly_the_labelled_observations():
    torch.manual_seed(0)
    agent = agent_for("oracle")
    obs = torch.rand(2, 6, OBS)
    labels = torch.tensor([[1, 0, 0, 1, 0, 0], [0, 1, 0, 0, 0, 1]], dtype=torch.float32)
    inputs = torch.cat((obs, labels.unsqueeze(-1)), dim=-1)
    weights = observation_weights(agent, inputs.transpose(0, 1))
    assert torch.equal(weights, labels.t())  # ν = the labels: the gate is the ground truth
    # changing unlabelled observations changes nothing the memory carries
    other = inputs.clone()
    other[..., :OBS] = torch.where(labels.bool().unsqueeze(-1), obs, torch.rand(2, 6, OBS))
    logits, values, state = agent(inputs, agent.initial_state(2))
    _, _, other_state = agent(other, agent.initial_state(2))
    assert torch.allclose(state, other_state)
    # training passes (no final state) keep the same observations
    train_logits, train_values = agent.evaluate(inputs, agent.initial_state(2))
    assert torch.equal(train_logits, logits) and torch.equal(train_values, values)


def test_collector_appends_the_positions_the_environment_reports():
    envs = make_vector_env("thci/PaperMaze-L1-v0", 4)
    try:
        torch.manual_seed(0)
        agent = ActorCritic(int(envs.single_observation_space.shape[0]), 4, NeuralMap(8, 18, 4), 8)
        collector = RolloutCollector(envs, agent, 40, 0.99, info_keys=("agent_pos",))
        collector.reset(seed=1)
        rollout, _ = collector.collect()
    finally:
        envs.close()
    assert rollout.side.shape == (40, 4, 2)
    assert torch.equal(rollout.inputs, torch.cat((rollout.obs, rollout.side), dim=-1))
    # the position an action reached is the next step's side input, unless the episode ended
    reached = torch.as_tensor(rollout.reached_info["agent_pos"][:-1]).float()
    going_on = ~rollout.dones[:-1]
    assert bool(going_on.any()) and bool(rollout.dones.any())
    assert torch.equal(rollout.side[1:][going_on], reached[going_on])
    assert len(torch.unique(rollout.side.reshape(-1, 2), dim=0)) > 1  # the agent moved


@pytest.mark.parametrize("algo", ["ppo", "a2c", "dmc"])
@pytest.mark.parametrize("method", METHODS)
def test_every_method_trains_with_every_algorithm(tmp_path, method, algo):
    summary = train(
        tmp_path,
        "run",
        "--method",
        method,
        "--algo",
        algo,
        "--total-steps",
        "512",
        "--wmg-layers",
        "1",
        "--wmg-head-size",
        "16",
    )
    assert summary["method"] == method and summary["total_env_steps"] == 512
    assert summary["episodes"] > 0
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert summary["num_parameters"] > 0 and config["method"] == method
    if method == "sai":
        assert len(summary["taie"]) == 4 and all(0 <= v <= 1 for v in summary["taie"])
    elif method == "oracle":
        assert summary["taie"] == 0.0
    elif method == "hai":
        assert 0 <= summary["taie"] <= 1
    else:
        assert summary["taie"] is None


@pytest.mark.parametrize(
    "args",
    [
        # DMC carries unfinished episodes, side inputs included, across checkpoints
        ["--method", "hai", "--algo", "dmc"],
        ["--method", "nm", "--algo", "a2c", "--nm-channels", "4"],
    ],
)
def test_side_inputs_survive_stop_and_resume(tmp_path, args):
    args = [*args, "--seed", "2"]
    reference = train(tmp_path, "reference", "--total-steps", "2048", *args)
    assert_stop_and_resume_matches(tmp_path, reference, args, total=2048)


def test_parameter_count_is_printed_at_the_start(tmp_path, capsys):
    summary = train(tmp_path, "run", "--method", "sai", "--total-steps", "256")
    out = capsys.readouterr()
    assert f"{summary['num_parameters']} parameters" in out.out + out.err


def test_neural_map_on_an_env_without_positions_is_refused(tmp_path, capsys):
    run_dir = tmp_path / "run"
    args = ["--env", "CartPole-v1", "--method", "nm", "--run-dir", str(run_dir), *FAST]
    code = run_cli(["train", *args])
    assert_one_line_error(capsys, code, "agent_pos", "--method nm", "grid position")
    assert not run_dir.exists()
