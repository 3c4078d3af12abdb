"""The `rl` config section: GRPO post-training (paper appendix, "Trajectory-Level Reinforcement Learning").

Defaults are the appendix tables (run settings and reward weights); the numerics below them were chosen by
measurement on the shipped model (README, "Post-training with GRPO").
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class RLConfig:
    # --- run (appendix table "RL post-training hyperparameters")
    iterations: int = 200  # rollout -> learn rounds
    prompts_per_iteration: int = 500  # P prompts per on-policy buffer (500 x 32 candidates)
    group_size: int = 32  # G candidates per prompt, independent noise
    clip: float = 0.1  # PPO ratio clip eps_clip
    kl_beta: float = 0.2  # beta of the analytic KL to the frozen reference
    lr: float = 1e-6
    weight_decay: float = 0.01
    grad_clip: float = 0.5
    epochs: int = 1  # passes over one buffer before it is discarded
    minibatch_prompts: int = 4  # prompts per optimizer step (their G candidates together: one map encoding)
    overlap: bool = False  # sample the next buffer (with the current weights) while the learner learns: the
    #                        learner stops waiting for rollouts; groups arrive one weight version behind
    # --- numerics (README: measured on the shipped model)
    train_transitions: int = 10  # denoising transitions per candidate that enter the loss
    transitions: str = "random"  # "random": a random subset of the chain per group (the early, high-noise steps
    #                              decide a chunk's shape); "last": the ones nearest the clean chunk (DPPO)
    skip_final: bool = True  # leave out k = 0 (its sigma is the floored posterior sigma; Flow-GRPO drops it)
    min_std: float = 1e-3  # a group whose reward std is below this gets zero advantages
    adv_eps: float = 1e-6
    # --- prompts
    min_future: int = 64  # expert steps that must remain after the prompt's time t (a chunk's 16 x 4)
    hard_prompt_prob: float = 0.25  # share of prompts drawn from the hard-prompt store once it has some
    hard_store_size: int = 4096  # prompts kept in the store (oldest replaced)
    hard_temperature: float = 1.0  # sampling weight ~ difficulty ** (1 / temperature)
    team_sizes: str = ""  # e.g. "4" or "2,3,4": the episodes prompts come from (empty: every team size)
    # --- reward (appendix table "Reward cost function parameters")
    w_obs: float = 30.0  # per robot-step within the obstacle soft margin
    w_inter: float = 30.0  # per pair-step within the inter-robot soft margin
    w_conn: float = 30.0  # per disconnected step
    w_goal: float = 30.0  # leader's geodesic distance to the goal at the chunk's end (normalised, below)
    w_wp: float = 50.0  # leader's deviation from the optimal path's waypoints
    reach_bonus: float = 50.0
    c_max: float = 10000.0  # the clip of the total cost
    hard_cost: float = 10000.0  # added for any hard violation (paper: c_max, so every violator scores -c_max / s;
    #                             lower, violators still rank by their violation counts: a denser signal for a
    #                             weak model whose groups are mostly violators)
    reward_scale: float = 20.0  # r = -min(C, c_max) / s
    obs_margin: float = 0.5  # soft margin (m) beyond task.d_obs_min
    inter_margin: float = 1.0  # soft margin (m) beyond task.d_coll_min
    wp_scale: float = 2.0  # metres of deviation that cost w_wp (one full-speed chunk move)
    # --- bookkeeping
    seed: int = 0
    checkpoint_every: int = 10  # iterations
    keep_checkpoints: int = 3
    eval_episodes: int = 0  # before/after evaluation on this many evaluation tasks at the end (0 = none)
    eval_team_size: int = 4
    eval_planners: str = "roken"  # the rows of the before/after table, e.g. roken,roken+guided+safe (same tasks)
    device: str = "auto"  # the learner's device (auto: cuda where available)
    rollout_device: str = "auto"  # each rollout worker's device


def check(rc: RLConfig) -> None:
    """Settings that cannot work, named before anything runs."""
    if rc.group_size < 2:
        raise ValueError(f"rl.group_size={rc.group_size}: GRPO compares candidates within a group; use >= 2")
    for name in ("iterations", "prompts_per_iteration", "minibatch_prompts", "epochs", "train_transitions"):
        if getattr(rc, name) < 1:
            raise ValueError(f"rl.{name}={getattr(rc, name)}: must be >= 1")
    if rc.transitions not in ("last", "random"):
        raise ValueError(f"rl.transitions={rc.transitions!r}: choose last or random")
    if not 0 <= rc.hard_prompt_prob <= 1:
        raise ValueError(f"rl.hard_prompt_prob={rc.hard_prompt_prob}: a probability in [0, 1]")
    if rc.clip <= 0 or rc.kl_beta < 0 or rc.lr <= 0 or rc.reward_scale <= 0:
        raise ValueError("rl.clip, rl.lr and rl.reward_scale must be > 0 and rl.kl_beta >= 0")


def team_sizes(rc: RLConfig) -> list[int]:
    return [int(v) for v in str(rc.team_sizes).replace(" ", "").split(",") if v]
