"""Training samples for the Roken DiT, cut from expert episodes (paper: "Dataset Collection", appendix tables).

One sample is one episode at one time t, padded to `max_robots` robot tokens (R):

  chunk      (R, H, 2)  the next H = 16 moves of every robot, one every `interval` = 4 expert steps. Relative
                        representation (paper): each move divided by interval * max_step = 2 m, so a full-speed
                        move has norm 1. Absolute (ablation): the positions themselves scaled to [-1, 1].
  start      (R, 2)     positions at t in metres: the token's PE(p_0) and the origin of the relative chunk
  rel_goal   (R, 2)     (goal - start) / (canvas / 2) for the leader, 0 for followers
  goal_mask  (R,)       1 for the leader (the robot given the goal)
  traj_mask  (R,)       1 for robots whose chunk is a fixed condition (masked training), 0 = generated
  robot_mask (R,)       True for real robots, False for padding (the attention key-padding mask)
  waypoints  (R, K, 2)  5 points every 8 m along each robot's future path (the end point once it is
                        shorter, for the leader the goal), relative to start / (K * 8 m)
  occ_small  (R, 7, 7)  occupancy around each robot's cell; occ_large (R, 7, 7): 21 x 21 max-pooled by 3
  map        (3, S, S)  occupancy, start heat-map, goal heat-map (Gaussian kernels), S = canvas = 140
  sdf        (S, S)     signed distance (metres) at cell centres, for the SDF loss
  prev_move  (R, 2)     each robot's last chunk move, (p_t - p_{t-interval}) / (interval * max_step) (condition.py)

The goal is sampled along the leader's future trajectory: with `final_goal_prob` the task's goal, otherwise
the leader's position at a random later step t_g, and then the sample is the sub-episode that ends at t_g
(every robot holds its t_g position afterwards), so chunk, waypoints and goal stay consistent.

Augmentation: a random element of the dihedral group (the 4 exact 90-degree turns, each with or without a
mirror flip) applied to the map, the SDF and every position; these keep every clearance exactly, so expert
trajectories stay collision-free. Beyond the paper we also shuffle the robot order (the model must not learn
anything from token slots); arbitrary-angle rotations are not used because resampling the grid is not exact.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa

from ..world.geometry import signed_distance_field
from . import shards
from .condition import build_condition, decode_chunk, encode_chunk, heatmap  # noqa: F401  (re-exported)

SAMPLE_KEYS = ("chunk", "start", "rel_goal", "goal", "goal_mask", "traj_mask", "robot_mask", "waypoints",
               "occ_small", "occ_large", "map", "sdf", "num_robots", "prev_move")


@dataclass
class SampleConfig:
    horizon: int = 16  # action chunk length H (paper)
    interval: int = 4  # expert steps per chunk move (paper: trajectory sampling interval)
    max_step: float = 0.5  # metres per expert step (paper); a chunk move is normalised by interval * max_step
    representation: str = "relative"  # "relative" (paper) or "absolute" (the paper's ablation)
    max_robots: int = 10  # robot tokens per sample (paper: 10)
    canvas: int = 140  # map side in cells (paper)
    num_waypoints: int = 5  # K (paper)
    waypoint_spacing: float = 8.0  # metres (paper)
    patch: int = 7  # local occupancy patch side (paper)
    large_scale: int = 3  # the large patch covers patch * large_scale cells, max-pooled back to patch
    heatmap_sigma: float = 2.0  # Gaussian kernel of the start / goal heat-maps, metres
    final_goal_prob: float = 0.5  # chance the goal is the task's goal rather than a point along the way
    condition_prob: float = 0.3  # chance a team of 2+ gets a random proper subset of robots as conditions
    augment: bool = True  # random dihedral transform of map and trajectories
    shuffle_robots: bool = True  # random robot order
    team_size_weights: dict[int, float] = field(default_factory=dict)  # resample episodes by team size; {} = as stored
    # Sub-teams for clustered rollout (appendix "Masked Training and Clustered Rollout"): with subteam_prob a
    # connected cluster of 2..subteam_max robots is cut from the team at t, rooted at the leader or (half the
    # time) at another robot; a cluster without the leader has no goal and >= 1 robot given as a condition.
    subteam_prob: float = 0.0
    subteam_max: int = 4
    comm_radius: float = 15.0  # R: robots within it are neighbours when a cluster is grown
    # std of Gaussian noise on prev_move (chunk units, 1 = a full-speed move) of training samples: a model that
    # reads its last move (model.prev_move) must not trust it blindly, since in closed loop it is its own move
    prev_noise: float = 0.0
    # with early_prob, the chunk's time t is drawn in the episode's first early_steps steps instead of uniformly:
    # every closed-loop episode starts at rest in a tight formation, a phase uniform t shows in ~6 % of samples
    early_prob: float = 0.0
    early_steps: int = 40

    @property
    def step_scale(self) -> float:
        return self.interval * self.max_step

    @property
    def waypoint_scale(self) -> float:
        return self.num_waypoints * self.waypoint_spacing

    @property
    def pos_scale(self) -> float:
        return self.canvas / 2.0


def check(cfg: SampleConfig) -> None:
    if cfg.representation not in ("relative", "absolute"):
        raise ValueError(f"samples.representation must be 'relative' or 'absolute', got {cfg.representation!r}")
    if cfg.horizon < 1 or cfg.interval < 1 or cfg.max_robots < 1 or cfg.num_waypoints < 1:
        raise ValueError("samples.horizon, interval, max_robots and num_waypoints must be >= 1")
    if cfg.patch % 2 == 0:
        raise ValueError(f"samples.patch must be odd (a patch centred on the robot's cell), got {cfg.patch}")
    if not all(0 <= p <= 1 for p in (cfg.condition_prob, cfg.final_goal_prob, cfg.subteam_prob)):
        raise ValueError("samples.condition_prob, final_goal_prob and subteam_prob are probabilities in [0, 1]")
    if not 0 <= cfg.early_prob <= 1 or cfg.early_steps < 1:
        raise ValueError(f"samples.early_prob must be in [0, 1] and samples.early_steps >= 1, got {cfg.early_prob}, "
                         f"{cfg.early_steps}")
    if cfg.prev_noise < 0:
        raise ValueError(f"samples.prev_noise must be >= 0 (0 = none), got {cfg.prev_noise}")
    if cfg.subteam_max < 2:
        raise ValueError(f"samples.subteam_max must be >= 2 (a cluster holds a condition and a generated robot), "
                         f"got {cfg.subteam_max}")


# ---------------------------------------------------------------------------------------------------------
# Exact dihedral transforms of a square S x S grid and of (x, y) points on it (ARCHITECTURE.md conventions).
# np.rot90 maps old cell (r, c) to new cell (S-1-c, r), i.e. the point (x, y) to (y, S - x); a left-right
# flip maps (x, y) to (S - x, y).

def transform_grid(a: np.ndarray, element: int) -> np.ndarray:
    """Apply dihedral element 0..7 (element % 4 quarter turns, then a flip if element >= 4) to (..., S, S)."""
    a = np.rot90(a, element % 4, axes=(-2, -1))
    return a[..., :, ::-1] if element >= 4 else a


def transform_points(p: np.ndarray, element: int, size: int) -> np.ndarray:
    """The same transform for points (..., 2) = (x, y) in metres."""
    x, y = p[..., 0], p[..., 1]
    for _ in range(element % 4):
        x, y = y, size - x
    if element >= 4:
        x = size - x
    return np.stack([x, y], axis=-1).astype(p.dtype, copy=False)


# ---------------------------------------------------------------------------------------------------------

class MapStore:
    """The maps of a dataset decoded once onto the canvas: (M, S, S) uint8 occupancy, a map-id index and the
    SDF of each map computed on first use and kept (the Ray batch function holds one for all its batches)."""

    def __init__(self, maps: pa.Table, canvas: int = 140):
        self.map_ids = maps.column("map_id").to_pylist()
        self.lookup = {m: k for k, m in enumerate(self.map_ids)}
        self.occupancy = np.ones((len(self.map_ids), canvas, canvas), dtype=np.uint8)
        for k, (h, w, b) in enumerate(zip(maps.column("height").to_pylist(), maps.column("width").to_pylist(),
                                          maps.column("occupancy").to_pylist())):
            if h > canvas or w > canvas:
                raise ValueError(f"map {self.map_ids[k]} is {h} x {w}, larger than the {canvas} x {canvas} canvas; "
                                 f"set samples.canvas to the canvas the dataset was generated on")
            self.occupancy[k, :h, :w] = np.frombuffer(b, dtype=np.uint8).reshape(h, w)
        self._sdf: dict[int, np.ndarray] = {}

    def index(self, map_ids: list[str]) -> np.ndarray:
        missing = sorted(set(map_ids) - self.lookup.keys())
        if missing:
            raise ValueError(f"episodes refer to maps not in the maps table: {missing[:5]}; "
                             f"read the maps/ shards of the same dataset folder")
        return np.asarray([self.lookup[m] for m in map_ids], dtype=np.int64)

    def sdf(self, m: int) -> np.ndarray:
        if m not in self._sdf:
            self._sdf[m] = signed_distance_field(self.occupancy[m])
        return self._sdf[m]


EPISODE_COLUMNS = ["episode_id", "map_id", "num_robots", "leader", "num_steps", "goal", "positions"]
WINDOW_COLUMNS = ("sample_until", "sample_from")  # where chunks may start (DAgger, Markov-label, DART episodes)


def episode_columns(location: str) -> list[str]:
    """The episode columns a bank reads from a dataset: EPISODE_COLUMNS and the chunk windows it has."""
    names = shards.open_dataset(location, "episodes").schema.names
    return EPISODE_COLUMNS + [c for c in WINDOW_COLUMNS if c in names]


class EpisodeBank:
    """Episodes as flat numpy arrays (zero-copy from Arrow) over a MapStore, indexable by episode.

    positions of episode i: flat[offsets[i]:offsets[i+1]].reshape(T+1, N, 2); its map: maps.occupancy[map_index[i]].
    """

    def __init__(self, flat: np.ndarray, offsets: np.ndarray, num_robots: np.ndarray, num_steps: np.ndarray,
                 leader: np.ndarray, goal: np.ndarray, map_ids: list[str], episode_ids: list[str], maps: MapStore):
        self.flat, self.offsets = flat, offsets
        self.num_robots, self.num_steps, self.leader, self.goal = num_robots, num_steps, leader, goal
        self.maps, self.map_index, self.episode_ids = maps, maps.index(map_ids), episode_ids
        self.occupancy, self.map_ids, self.sdf = maps.occupancy, maps.map_ids, maps.sdf
        self.sample_until: np.ndarray | None = None  # per episode: chunks start before this step (DAgger)
        self.sample_from: np.ndarray | None = None  # per episode: ... and at or after it (a history prefix before)
        expected = (num_steps.astype(np.int64) + 1) * num_robots * 2
        bad = np.flatnonzero(np.diff(offsets) != expected)
        if len(bad):
            raise ValueError(f"episode {episode_ids[bad[0]]}: positions hold {np.diff(offsets)[bad[0]]} values, "
                             f"expected (num_steps + 1) * num_robots * 2 = {expected[bad[0]]}")

    def __len__(self) -> int:
        return len(self.num_robots)

    @classmethod
    def from_arrow(cls, episodes: pa.Table, maps: pa.Table | MapStore, canvas: int = 140) -> "EpisodeBank":
        maps = maps if isinstance(maps, MapStore) else MapStore(maps, canvas)
        pos = episodes.column("positions").combine_chunks()
        bank = cls(pos.values.to_numpy(zero_copy_only=False), pos.offsets.to_numpy(),
                   episodes.column("num_robots").to_numpy(), episodes.column("num_steps").to_numpy(),
                   episodes.column("leader").to_numpy(),
                   np.asarray(episodes.column("goal").to_pylist(), dtype=np.float32).reshape(-1, 2),
                   episodes.column("map_id").to_pylist(), episodes.column("episode_id").to_pylist(), maps)
        if "sample_until" in episodes.column_names:  # relabelled episodes: learn the moves near their start
            until = episodes.column("sample_until").to_numpy(zero_copy_only=False)
            bank.sample_until = np.where(until > 0, until, bank.num_steps).astype(np.int64)
        if "sample_from" in episodes.column_names:  # relabelled episodes led by the learner's own last moves
            bank.sample_from = episodes.column("sample_from").to_numpy(zero_copy_only=False).astype(np.int64)
        return bank

    @classmethod
    def from_columns(cls, batch: dict[str, np.ndarray], maps: MapStore) -> "EpisodeBank":
        """A numpy batch of episode rows (as Ray Data hands them: `positions` an array of arrays)."""
        positions = [np.asarray(p, dtype=np.float32).reshape(-1) for p in batch["positions"]]
        offsets = np.concatenate([[0], np.cumsum([len(p) for p in positions])]).astype(np.int64)
        return cls(np.concatenate(positions), offsets, np.asarray(batch["num_robots"]),
                   np.asarray(batch["num_steps"]), np.asarray(batch["leader"]),
                   np.stack([np.asarray(g, dtype=np.float32) for g in batch["goal"]]),
                   [str(m) for m in batch["map_id"]], [str(e) for e in batch["episode_id"]], maps)

    @classmethod
    def from_folder(cls, location: str, canvas: int = 140, successful_only: bool = True) -> "EpisodeBank":
        """A dataset folder or URI written by pipelines/generate.py, with its episodes' chunk windows
        (`sample_until` / `sample_from` of Markov-label, DART and DAgger episodes) where it has them, as training
        reads it (roken.train.data)."""
        episodes = shards.read_table(location, "episodes", columns=episode_columns(location),
                                     successful_only=successful_only)
        if episodes.num_rows == 0:
            raise ValueError(f"{location}: no {'successful ' if successful_only else ''}episodes to train on")
        return cls.from_arrow(episodes, shards.read_table(location, "maps"), canvas)

    def positions(self, i: int) -> np.ndarray:
        T, N = int(self.num_steps[i]), int(self.num_robots[i])
        return self.flat[self.offsets[i]:self.offsets[i + 1]].reshape(T + 1, N, 2)

    def episode_weights(self, team_size_weights: dict[int, float]) -> np.ndarray | None:
        """Sampling probabilities that give team size n the share team_size_weights[n] (None = uniform)."""
        if not team_size_weights:
            return None
        w = np.zeros(len(self))
        for n, share in team_size_weights.items():
            sel = self.num_robots == int(n)
            if sel.any():
                w[sel] = float(share) / sel.sum()
        if w.sum() <= 0:
            raise ValueError(f"samples.team_size_weights {team_size_weights} selects no episode; "
                             f"team sizes present: {sorted(set(self.num_robots.tolist()))}")
        return w / w.sum()


def _future_points(path: np.ndarray, spacing: float, count: int) -> np.ndarray:
    """Points every `spacing` metres of arc length along path (L, 2); the end point once it runs out."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    targets = spacing * np.arange(1, count + 1)
    return np.stack([np.interp(targets, s, path[:, 0]), np.interp(targets, s, path[:, 1])], axis=-1)




def local_patches(occupancy: np.ndarray, points: np.ndarray, patch: int, scale: int) -> tuple[np.ndarray, np.ndarray]:
    """Occupancy patch x patch around the cell of each point, and the (patch*scale)^2 patch max-pooled by scale.
    Cells outside the map count as obstacle."""
    half_large = patch * scale // 2
    padded = np.pad(occupancy, half_large, constant_values=1)
    r = np.floor(points[:, 1]).astype(np.int64) + half_large
    c = np.floor(points[:, 0]).astype(np.int64) + half_large
    small = np.arange(patch) - patch // 2
    large = np.arange(patch * scale) - half_large
    occ_s = padded[(r[:, None] + small)[:, :, None], (c[:, None] + small)[:, None, :]]
    occ_l = padded[(r[:, None] + large)[:, :, None], (c[:, None] + large)[:, None, :]]
    n = len(points)
    occ_l = occ_l.reshape(n, patch, scale, patch, scale).max(axis=(2, 4))
    return occ_s.astype(np.float32), occ_l.astype(np.float32)






def _subteam(start: np.ndarray, leader: int, rng: np.random.Generator, cfg: SampleConfig) -> tuple[np.ndarray, int]:
    """A connected cluster of the team at positions start (N, 2), grown breadth-first over the communication
    graph from its root; returns the member indices (root first) and the leader's index among them (-1 if out)."""
    N = len(start)
    size = int(rng.integers(2, min(N, cfg.subteam_max) + 1))
    root = leader if rng.random() < 0.5 else int(rng.integers(0, N))
    near = np.linalg.norm(start[:, None] - start[None], axis=-1) <= cfg.comm_radius
    members, frontier = [root], [root]
    while frontier and len(members) < size:
        node = frontier.pop(0)
        for j in rng.permutation(np.flatnonzero(near[node])):
            if j not in members and len(members) < size:
                members.append(int(j))
                frontier.append(int(j))
    members = np.asarray(members)
    hit = np.flatnonzero(members == leader)
    return members, int(hit[0]) if len(hit) else -1


def sample_shapes(cfg: SampleConfig) -> dict[str, tuple[tuple[int, ...], type]]:
    """Shape and dtype of every array of one sample (SAMPLE_KEYS)."""
    R, H, K, P, S = cfg.max_robots, cfg.horizon, cfg.num_waypoints, cfg.patch, cfg.canvas
    f = np.float32
    return {"chunk": ((R, H, 2), f), "start": ((R, 2), f), "rel_goal": ((R, 2), f), "goal": ((2,), f),
            "goal_mask": ((R,), f), "traj_mask": ((R,), f), "robot_mask": ((R,), bool), "waypoints": ((R, K, 2), f),
            "occ_small": ((R, P, P), f), "occ_large": ((R, P, P), f), "map": ((3, S, S), f), "sdf": ((S, S), f),
            "num_robots": ((), np.int64), "prev_move": ((R, 2), f)}


def make_sample(bank: EpisodeBank, i: int, rng: np.random.Generator, cfg: SampleConfig) -> dict[str, np.ndarray]:
    """One training sample from episode i; all randomness comes from rng."""
    P = bank.positions(i)
    T, N, leader = P.shape[0] - 1, P.shape[1], int(bank.leader[i])
    R, H, K, S = cfg.max_robots, cfg.horizon, cfg.num_waypoints, cfg.canvas
    if N > R:
        raise ValueError(f"episode {bank.episode_ids[i]} has {N} robots, more than samples.max_robots={R}; "
                         f"raise it with --set samples.max_robots={N} (the model's token count follows)")
    if T < 1:
        raise ValueError(f"episode {bank.episode_ids[i]} has no steps; drop it from the dataset")
    # The chunk first (any step with a future), then the goal along the leader's future (paper: "we randomly
    # sample a fixed-length multi-robot action chunk and a goal position along the future trajectory of the
    # leader"). Drawing the goal time first and the chunk before it made 67 % of goals lie within 32 m of the
    # start, while evaluation goals are >= 50 m away.
    # (an episode with sample_until, DAgger's, starts its chunks near the learner's state; the future is whole)
    # (and one with sample_from after the learner's last moves that led there: the history a last-move model reads)
    lo = 0 if bank.sample_from is None else min(int(bank.sample_from[i]), T - 1)
    hi = T if bank.sample_until is None else max(lo + 1, min(T, int(bank.sample_until[i])))
    if cfg.early_prob > 0 and rng.random() < cfg.early_prob:
        hi = max(lo + 1, min(hi, cfg.early_steps))
    t = int(rng.integers(lo, hi))
    final = rng.random() < cfg.final_goal_prob
    t_g = T if final else int(rng.integers(t + 1, T + 1))
    goal = bank.goal[i].astype(np.float32) if final else P[t_g, leader].astype(np.float32)
    if N >= 2 and rng.random() < cfg.subteam_prob:
        members, leader = _subteam(P[t], leader, rng, cfg)
        P, N = P[:, members], len(members)
    idx = np.minimum(t + cfg.interval * np.arange(H + 1), t_g)
    points = P[idx]  # (H+1, N, 2)
    before = P[max(0, t - cfg.interval)]  # (N, 2): one chunk move earlier (at rest at the episode's start)
    future = P[t:t_g + 1]  # (L, N, 2)
    wps = np.stack([_future_points(future[:, j], cfg.waypoint_spacing, K) for j in range(N)])  # (N, K, 2)
    if leader >= 0:
        length = np.linalg.norm(np.diff(future[:, leader], axis=0), axis=1).sum()
        wps[leader, cfg.waypoint_spacing * np.arange(1, K + 1) > length] = goal  # "filled with the goal"

    m = int(bank.map_index[i])
    occ, sdf = bank.occupancy[m], bank.sdf(m)
    if cfg.augment:
        e = int(rng.integers(0, 8))
        occ, sdf = transform_grid(occ, e), transform_grid(sdf, e)
        points, wps = transform_points(points, e, S), transform_points(wps, e, S)
        goal, before = transform_points(goal, e, S), transform_points(before, e, S)
    order = rng.permutation(N) if cfg.shuffle_robots else np.arange(N)
    points, wps, before = points[:, order], wps[order], before[order]
    leader = int(np.flatnonzero(order == leader)[0]) if leader >= 0 else -1

    start = points[0]  # (N, 2)
    occ_s, occ_l = local_patches(occ, start, cfg.patch, cfg.large_scale)
    traj_mask = np.zeros(N, dtype=np.float32)
    # A sub-team without the leader is a later cluster of clustered rollout: it always has >= 1 given robot.
    if N >= 2 and (leader < 0 or rng.random() < cfg.condition_prob):
        traj_mask[rng.choice(N, size=int(rng.integers(1, N)), replace=False)] = 1.0

    out = {k: np.zeros(shape, dtype) for k, (shape, dtype) in sample_shapes(cfg).items()}
    # the inputs through the one condition builder (the planner and GRPO call it too); the given chunks of
    # conditioned robots are the target chunk itself, so only the targets are filled in here
    out.update(build_condition(occ, start, leader, goal, cfg, fixed=None, previous=before))
    out["traj_mask"][:N] = traj_mask
    if cfg.prev_noise > 0:
        out["prev_move"][:N] += rng.normal(0.0, cfg.prev_noise, (N, 2)).astype(np.float32)
    out["num_robots"] = np.int64(N)
    out["chunk"][:N] = encode_chunk(points, cfg)
    out["waypoints"][:N] = (wps - start[:, None, :]) / cfg.waypoint_scale
    out["occ_small"][:N], out["occ_large"][:N] = occ_s, occ_l
    out["sdf"][:] = sdf
    return out
