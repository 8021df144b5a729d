"""Episode segmentation of rollouts: every step lands in exactly one whole segment, in order."""

import torch

from thci.rl.sequences import cut_into_segments


def random_starts(num_steps: int, num_envs: int, p: float, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(num_steps, num_envs, generator=generator) < p


def test_segments_cover_every_step_once_in_time_order():
    starts = random_starts(37, 5, 0.2, 0)
    segments = cut_into_segments(starts)
    positions = segments.index[segments.valid]
    assert sorted(positions.tolist()) == list(range(37 * 5))
    for s in range(len(segments.column)):
        steps = segments.index[s][segments.valid[s]]
        times, columns = steps // 5, steps % 5
        assert (columns == segments.column[s]).all()
        assert (times.diff() == 1).all(), "a segment is a contiguous run of one column"
        assert not starts[times[1:], columns[1:]].any(), "no episode starts inside a segment"
        first = int(times[0])
        assert first == 0 or bool(starts[first, columns[0]])


def test_continues_only_for_segments_that_carry_an_episode_over():
    starts = torch.tensor([[True, False], [False, False], [False, True], [True, False]])
    segments = cut_into_segments(starts)
    # column 0: [0..2], [3]; column 1: [0..1], [2..3]
    assert segments.lengths.tolist() == [3, 1, 2, 2]
    assert segments.column.tolist() == [0, 0, 1, 1]
    assert segments.continues.tolist() == [False, False, True, False]


def test_gather_matches_manual_indexing():
    starts = random_starts(10, 3, 0.3, 1)
    x = torch.arange(30).reshape(10, 3)
    segments = cut_into_segments(starts)
    gathered = segments.gather(x)
    for s in range(len(segments.column)):
        valid = segments.valid[s]
        expected = x[:, int(segments.column[s])]
        times = segments.index[s][valid] // 3
        assert torch.equal(gathered[s][valid], expected[times])


def test_minibatches_partition_segments_with_balanced_steps():
    segments = cut_into_segments(random_starts(64, 16, 0.05, 2))
    groups = segments.minibatches(4, torch.Generator().manual_seed(0))
    assert len(groups) == 4
    assert sorted(torch.cat(groups).tolist()) == list(range(len(segments.column)))
    steps = [int(segments.lengths[g].sum()) for g in groups]
    assert max(steps) - min(steps) <= 2 * int(segments.lengths.max())
    picked = segments.select(groups[0])
    assert picked.index.shape[1] == int(segments.lengths[groups[0]].max())
