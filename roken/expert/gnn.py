"""GNN (Tang et al. 2024, decentralized communication-maintained coordination), the paper's second baseline.

No public code exists; this follows the paper's description: each robot builds candidate graphs from its
discrete candidate positions and the others' positions, a graph neural network scores them for connectivity
and collision avoidance, and the robots' next positions are chosen one after another by the scores; the leader
follows its A* reference. The decision loop is SGG's (roken.expert.sgg: the same candidates, leader rule and
breadth-first order over the team's spanning tree) with the discrete choice made by the scorer and no
continuous refinement.

The scorer (plain torch message passing; no graph library is needed for graphs of <= 10 nodes, which batch as
dense (M, N, N) tensors):
  nodes  [x, y relative to the robot's candidate / R, clearance / 5 (capped at 1), self, leader, placed]
  edges  [d / R, d <= R, d < d_coll_min + margin]
  h = MLP(node); `layers` x { m_ij = MLP([h_i, h_j, e_ij]); h_i += MLP(sum_j m_ij) }; logit = MLP([h_self, mean h])
Labels come from our simulator (`make_dataset`, `graph_labels`): 0 when the robot at its candidate breaks
clearance or spacing (with the margins), else a sigmoid of how far the graph's bottleneck link is inside R
(> 0.5 exactly when connected). Graphs are cut from states of the
Laplacian expert's episodes on `train` maps, every robot and every candidate.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..configtools import from_dict
from ..world.geometry import clearance
from ..world.graph import minimum_spanning_tree
from ..world.tasks import TaskConfig
from .laplacian import ExpertConfig
from .sgg import SGGConfig, SGGPlanner

NODE_F, EDGE_F = 6, 3


@dataclass
class GNNConfig:
    checkpoint: str = "models/gnn-scorer"  # the trained scorer (`roken train-gnn`)
    motion_weight: float = 0.02  # a candidate's utility: score - motion_weight x its step (in full steps)
    cohesion: float = 0.1  # ... - cohesion x metres beyond sgg.comfort from its parent
    hidden: int = 64
    layers: int = 3


class GraphScorer(nn.Module):
    """Scores M candidate graphs: nodes (M, N, NODE_F), edges (M, N, N, EDGE_F), mask (M, N), self index (M,)."""

    def __init__(self, hidden: int = 64, layers: int = 3):
        super().__init__()
        mlp = lambda i, o: nn.Sequential(nn.Linear(i, hidden), nn.SiLU(), nn.Linear(hidden, o))  # noqa: E731
        self.embed = mlp(NODE_F, hidden)
        self.msg = nn.ModuleList([mlp(2 * hidden + EDGE_F, hidden) for _ in range(layers)])
        self.upd = nn.ModuleList([mlp(hidden, hidden) for _ in range(layers)])
        self.head = mlp(2 * hidden, 1)

    def forward(self, nodes, edges, mask, me):
        M, N, _ = nodes.shape
        h = self.embed(nodes)  # (M, N, h)
        pair = (mask[:, :, None] & mask[:, None] & ~torch.eye(N, dtype=torch.bool, device=nodes.device)).float()
        for msg, upd in zip(self.msg, self.upd):
            hi = h[:, :, None].expand(M, N, N, h.shape[-1])
            hj = h[:, None].expand(M, N, N, h.shape[-1])
            m = msg(torch.cat([hi, hj, edges], -1)) * pair[..., None]  # (M, N, N, h): j -> i
            h = h + upd(m.sum(2))
        w = mask.float()[..., None]
        pooled = (h * w).sum(1) / w.sum(1).clamp(min=1)
        return self.head(torch.cat([h[torch.arange(M), me], pooled], -1))[:, 0]  # (M,) logits


def featurize(cand, others, placed, leader_node, clr_cand, clr_others, tc: TaskConfig, margin: float):
    """Candidate graphs of one robot: cand (M, 2) its candidate positions, others (M, N, 2) every robot's
    position in the graph (the robot's own row replaced by the candidate), placed (M, N), leader_node (M,),
    clr_* clearances. Returns nodes, edges, mask, self index (the robot is node `me`)."""
    M, N, _ = others.shape
    R = tc.comm_radius
    rel = (others - cand[:, None]) / R
    clr = np.minimum(clr_others / 5.0, 1.0)
    me = np.argmin(np.linalg.norm(others - cand[:, None], axis=-1), axis=1)  # the candidate's own node
    clr[np.arange(M), me] = np.minimum(clr_cand / 5.0, 1.0)
    onehot = lambda i: (np.arange(N)[None] == i[:, None]).astype(np.float32)  # noqa: E731
    nodes = np.concatenate([rel, clr[..., None], onehot(me)[..., None], onehot(leader_node)[..., None],
                            placed[..., None].astype(np.float32)], -1)
    d = np.linalg.norm(others[:, :, None] - others[:, None], axis=-1)
    edges = np.stack([d / R, d <= R, d < tc.d_coll_min + margin], -1).astype(np.float32)
    return nodes.astype(np.float32), edges, np.ones((M, N), bool), me


def graph_labels(others, me, clr_cand, tc: TaskConfig, margin_obs: float, margin_coll: float,
                 softness: float = 1.5) -> np.ndarray:
    """The simulator's verdict on each candidate graph, in [0, 1]: 0 when the robot at its candidate breaks
    clearance or spacing (with the margins), else sigmoid((R - b) / softness) of the graph's bottleneck b (the
    longest edge of its minimum spanning tree): > 0.5 exactly when the team is connected, and graded, so that
    among candidates of a stretched or split team the ones that close the gap score higher."""
    M, N, _ = others.shape
    d = np.linalg.norm(others - others[np.arange(M), me][:, None], axis=-1)
    d[np.arange(M), me] = np.inf
    dd = np.linalg.norm(others[:, :, None] - others[:, None], axis=-1)
    tree = minimum_spanning_tree(np.where(np.eye(N, dtype=bool)[None], np.inf, dd))
    bottleneck = np.where(tree, dd, 0).max((1, 2))
    safe = (clr_cand >= tc.d_obs_min + margin_obs) & (d >= tc.d_coll_min + margin_coll).all(1)
    return (safe / (1 + np.exp(-(tc.comm_radius - bottleneck) / softness))).astype(np.float32)


class GNNPlanner(SGGPlanner):
    """SGG's decision loop with the discrete choice made by a trained GraphScorer."""

    def __init__(self, cfg: GNNConfig, sgg_cfg: SGGConfig, task_cfg: TaskConfig, expert_cfg: ExpertConfig | None,
                 scorer: GraphScorer):
        super().__init__(replace(sgg_cfg, refine=False), task_cfg, expert_cfg)
        self.gcfg, self.scorer = cfg, scorer.eval()

    @classmethod
    def load(cls, cfg: GNNConfig, sgg_cfg: SGGConfig, task_cfg: TaskConfig, expert_cfg=None) -> "GNNPlanner":
        return cls(cfg, sgg_cfg, task_cfg, expert_cfg, load_scorer(cfg.checkpoint))

    @torch.no_grad()
    def _place(self, q, lead_next, parents, order, padded, clr_now, d_now):
        cfg, g, tc = self.cfg, self.gcfg, self.tc
        S, N, _ = q.shape
        sl = np.arange(S)
        K = len(self.offsets)
        nxt, placed = q.copy(), np.zeros((S, N), bool)
        leader = order[:, 0]
        nxt[sl, leader], placed[sl, leader] = lead_next, True
        ok_team = np.ones(S, bool)
        step = self.step_len / tc.max_step
        for k in range(1, N):
            r = order[:, k]
            cand = q[sl, r][:, None] + self.offsets[None]  # (S, K, 2)
            graphs = np.repeat(nxt[:, None], K, 1)  # (S, K, N, 2)
            graphs[sl, :, r] = cand
            flat = graphs.reshape(S * K, N, 2)
            idx = np.repeat(sl, K)
            clr_c = clearance(padded, cand, np.broadcast_to(sl[:, None], (S, K))).reshape(-1)
            clr_o = clearance(padded, flat, np.broadcast_to(idx[:, None], (S * K, N)))
            pl = np.repeat(placed, K, 0)
            nodes, edges, mask, me = featurize(cand.reshape(-1, 2), flat, pl, np.repeat(leader, K), clr_c, clr_o,
                                               tc, cfg.margin_coll)
            score = torch.sigmoid(self.scorer(torch.from_numpy(nodes), torch.from_numpy(edges),
                                              torch.from_numpy(mask), torch.from_numpy(me))).numpy().reshape(S, K)
            par = np.where(parents[sl, r] >= 0, parents[sl, r], leader)
            link = np.linalg.norm(cand - nxt[sl, par][:, None], axis=-1)
            util = score - g.motion_weight * step[None] - g.cohesion * np.maximum(link - cfg.comfort, 0)
            pick = util.argmax(1)
            ok_team &= score[sl, pick] > 0.5
            nxt[sl, r], placed[sl, r] = cand[sl, pick], True
        return nxt, ok_team


# ---------------------------------------------------------------------- training
def make_dataset(cfg, tasks: int, states_per_episode: int, seed: int = 0, jitter: float = 2.5
                 ) -> dict[str, np.ndarray]:
    """Candidate graphs and labels from expert states on `train` maps: every robot of each sampled state, its
    candidates, the others where they are (placed: a random half, as the breadth-first order puts them)."""
    from ..eval.harness import make_tasks
    from ..world.maps import generate_map
    from .laplacian import LaplacianExpert

    n = cfg.eval.robots[0]
    ec = replace(cfg.eval, episodes=tasks, seed=seed)
    maps = [generate_map(cfg.map, "train", i) for i in range(tasks)]
    task_list, _ = make_tasks(replace(cfg, eval=ec), maps, n)
    by_id = {m.map_id: m for m in maps}
    offsets = SGGPlanner(cfg.sgg, cfg.task, cfg.expert).offsets
    rng = np.random.default_rng(seed)
    out = {k: [] for k in ("nodes", "edges", "mask", "me", "label")}
    tc, sc = cfg.task, cfg.sgg
    for i, ep in LaplacianExpert(cfg.expert, tc).run([t for _, t in task_list], by_id):
        task, gm = task_list[i][1], by_id[task_list[i][1].map_id]
        for t in rng.integers(0, len(ep.positions), states_per_episode):
            # the expert's state with its shape stretched (x 0.7-2.5 about the centroid) and jittered (sigma
            # `jitter` m per robot): candidates then lie on both sides of the clearance, spacing and range
            # limits, which the expert alone seldom approaches
            q = ep.positions[t].astype(np.float64)
            c = q.mean(0)
            q = c + (q - c) * rng.uniform(0.7, 2.5) + rng.normal(0, jitter, (n, 2))
            for r in range(n):
                cand = q[r][None] + offsets  # (K, 2)
                K = len(cand)
                graphs = np.repeat(q[None], K, 0)
                graphs[:, r] = cand
                placed = np.repeat((rng.random(n) < 0.5)[None], K, 0)
                clr_c = clearance(gm.padded, cand)
                clr_o = clearance(gm.padded, graphs)
                nodes, edges, mask, me = featurize(cand, graphs, placed, np.full(K, task.leader), clr_c, clr_o, tc,
                                                   sc.margin_coll)
                lab = graph_labels(graphs, me, clr_c, tc, sc.margin_obs, sc.margin_coll)
                for k, v in zip(out, (nodes, edges, mask, me, lab)):
                    out[k].append(v)
    return {k: np.concatenate(v) for k, v in out.items()}


def train_scorer(cfg, out: str, tasks: int = 256, states: int = 8, steps: int = 3000, batch: int = 512,
                 lr: float = 1e-3, seed: int = 0, log=print) -> dict:
    """Train a GraphScorer on simulator labels; writes OUT/model.safetensors, config.json, summary.json."""
    from safetensors.torch import save_file

    from ..data.store import atomic_write_json

    torch.manual_seed(seed)
    t0 = time.time()
    data = make_dataset(cfg, tasks, states, seed)
    val = make_dataset(cfg, max(tasks // 8, 8), states, seed + 1)  # other tasks (other maps' episodes)
    log(f"[train-gnn] {len(data['label'])} graphs ({(data['label'] > 0.5).mean():.2f} good), "
        f"{len(val['label'])} held out, "
        f"{time.time() - t0:.0f} s")
    T = {k: torch.from_numpy(v) for k, v in data.items()}
    V = {k: torch.from_numpy(v) for k, v in val.items()}
    model = GraphScorer(cfg.gnn.hidden, cfg.gnn.layers)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1 - s / steps)  # linear decay: a settled last step
    g = torch.Generator().manual_seed(seed)
    bce = nn.BCEWithLogitsLoss()

    def accuracy(D):
        with torch.no_grad():
            p = torch.cat([model(D["nodes"][i:i + 4096], D["edges"][i:i + 4096], D["mask"][i:i + 4096],
                                 D["me"][i:i + 4096]) for i in range(0, len(D["label"]), 4096)])
        return float(((p > 0) == (D["label"] > 0.5)).float().mean())

    for s in range(1, steps + 1):
        b = torch.randint(0, len(T["label"]), (batch,), generator=g)
        loss = bce(model(T["nodes"][b], T["edges"][b], T["mask"][b], T["me"][b]), T["label"][b])
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if s % 500 == 0 or s == steps:
            log(f"[train-gnn] step {s}/{steps} loss {loss.item():.4f} held-out accuracy {accuracy(V):.4f}")
    summary = {"graphs": int(len(data["label"])), "good_fraction": float((data["label"] > 0.5).mean()),
               "train_accuracy": accuracy(T), "heldout_accuracy": accuracy(V), "steps": steps,
               "seconds": round(time.time() - t0, 1), "team_size": int(cfg.eval.robots[0])}
    o = Path(out)
    o.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(o / "model.safetensors.tmp"))
    (o / "model.safetensors.tmp").replace(o / "model.safetensors")
    atomic_write_json({"gnn": asdict(cfg.gnn), "task": asdict(cfg.task), "sgg": asdict(cfg.sgg)}, o / "config.json")
    atomic_write_json(summary, o / "summary.json")
    card = f"""# GNN baseline scorer ({o.name})

The graph scorer of the paper's GNN baseline (Tang et al. 2024; `roken/expert/gnn.py`): plain torch message
passing, {cfg.gnn.layers} layers of width {cfg.gnn.hidden}, {sum(p.numel() for p in model.parameters())} parameters. It
scores a robot's candidate next position by the graph it makes with the team: > 0.5 when the robot keeps
clearance and spacing (with the SGG margins) and the team stays connected within R = {cfg.task.comm_radius:g} m.

Trained on simulator labels (`graph_labels`): {summary['graphs']} candidate graphs ({summary['good_fraction']:.2f}
good) from states of {tasks} Laplacian-expert episodes on `train` maps ({states} states each, the team's shape
stretched and jittered), {cfg.eval.robots[0]} robots, {steps} AdamW steps of {batch} graphs (lr {lr:g}, linear
decay), {summary['seconds']:.0f} s on this machine's CPU.

| | accuracy (score > 0.5 vs label > 0.5) |
| --- | --- |
| training graphs | {summary['train_accuracy']:.4f} |
| held-out graphs (other maps' episodes) | {summary['heldout_accuracy']:.4f} |

Re-train: `python -m roken train-gnn --out {out} --tasks {tasks} --states {states} --steps {steps} --robots
{cfg.eval.robots[0]} --seed {seed}`. Use: `pipelines/evaluate.py --planner gnn` (`gnn.checkpoint`).
"""
    fs_tmp = o / "MODEL_CARD.md.tmp"
    fs_tmp.write_text(card)
    fs_tmp.replace(o / "MODEL_CARD.md")
    return summary


def scorer_bytes(path: str) -> dict:
    """A trained scorer as bytes (config + weights), shipped once to every evaluation worker."""
    import hashlib

    d = Path(path)
    if not (d / "model.safetensors").is_file() or not (d / "config.json").is_file():
        raise FileNotFoundError(f"gnn.checkpoint {d}: no trained GNN scorer there (model.safetensors, config.json); "
                                f"train one with `python -m roken train-gnn --out {d}`, or pass "
                                f"--set gnn.checkpoint=DIR")
    w = (d / "model.safetensors").read_bytes()
    return {"path": str(d), "config": json.loads((d / "config.json").read_text()), "weights": w,
            "sha256": hashlib.sha256(w).hexdigest()[:16]}


def scorer_from_bytes(blob: dict) -> GraphScorer:
    from safetensors.torch import load

    c = from_dict(GNNConfig, blob["config"]["gnn"], "gnn.")
    m = GraphScorer(c.hidden, c.layers)
    m.load_state_dict(load(blob["weights"]))
    return m.eval()


def load_scorer(path: str) -> GraphScorer:
    return scorer_from_bytes(scorer_bytes(path))
