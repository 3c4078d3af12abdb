"""model.neighbours: each robot token sees its nearest team-mates as offsets (README "Team-mates as offsets").
Starting a run with it from a checkpoint without it: tests/test_prev_move.py."""
import pytest
import torch

from roken.model.dit import RokenDiT, neighbour_offsets, preset


def test_offsets_are_nearest_first_real_robots_only_and_independent_of_order():
    start = torch.tensor([[[0.0, 0.0], [3.0, 4.0], [1.0, 0.0], [50.0, 50.0]]])  # (1, 4, 2)
    mask = torch.tensor([[True, True, True, False]])  # robot 3 is padding
    f = neighbour_offsets(start, mask, 3).view(1, 4, 3, 4)
    torch.testing.assert_close(f[0, 0, 0], torch.tensor([0.2, 0.0, 0.2, 1.0]))  # robot 2: 1 m east
    torch.testing.assert_close(f[0, 0, 1], torch.tensor([0.6, 0.8, 1.0, 1.0]))  # robot 1: 5 m away
    assert not f[0, 0, 2].any(), "padding is not a team-mate: the third slot stays empty"
    perm = torch.tensor([2, 0, 1, 3])
    torch.testing.assert_close(neighbour_offsets(start[:, perm], mask[:, perm], 3), f.view(1, 4, 12)[:, perm])
    assert neighbour_offsets(start[:, :1], mask[:, :1], 2).abs().sum() == 0  # a robot alone has no neighbours


def test_the_input_enters_at_zero_and_then_reads_the_team_geometry():
    torch.manual_seed(0)
    off, on = RokenDiT(preset("tiny")).eval(), RokenDiT(preset("tiny", neighbours=2)).eval()
    torch.nn.init.normal_(off.final.linear.weight, std=0.1)
    on.load_state_dict(off.state_dict(), strict=False)
    B, R = 2, 3
    x, k = torch.randn(B, R, 16, 2), torch.tensor([3, 40])
    cond = {"start": torch.rand(B, R, 2) * 40 + 50, "rel_goal": torch.randn(B, R, 2), "goal_mask": torch.ones(B, R),
            "traj_mask": torch.zeros(B, R), "robot_mask": torch.ones(B, R, dtype=torch.bool),
            "map": torch.zeros(B, 3, 140, 140)}
    with torch.no_grad():
        torch.testing.assert_close(on(x, k, cond)["eps"], off(x, k, cond)["eps"])  # the same function at first
        torch.nn.init.normal_(on.phi_nbr[-1].weight, std=0.5)
        moved = cond | {"start": cond["start"] + torch.tensor([[[0.0, 0.0], [2.0, 0.0], [0.0, 0.0]]])}
        shifted = cond | {"start": cond["start"] + 1.5}  # the whole team moved: the offsets are the same
        a = on(x, k, cond)["eps"]
        assert not torch.allclose(a, on(x, k, moved)["eps"])
        torch.testing.assert_close(on.phi_nbr(neighbour_offsets(shifted["start"], cond["robot_mask"], 2)),
                                   on.phi_nbr(neighbour_offsets(cond["start"], cond["robot_mask"], 2)))


def test_a_negative_count_is_named():
    with pytest.raises(ValueError, match="model.neighbours"):
        RokenDiT(preset("tiny", neighbours=-1))
