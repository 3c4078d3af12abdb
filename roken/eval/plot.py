"""PNG of a map with a team's trajectories, starts, goal and communication edges at a few instants."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_episode(occupancy: np.ndarray, positions: np.ndarray, goal: np.ndarray, leader: int,
                 out: str | Path, comm_radius: float = 15.0, instants: int = 4, title: str = "",
                 crop: bool = True) -> Path:
    """Draw one episode; positions (T+1, N, 2). Returns the written path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = np.asarray(positions, dtype=np.float64)
    T1, N, _ = p.shape
    fig, ax = plt.subplots(figsize=(9, 7), dpi=110)
    H, W = occupancy.shape
    ax.imshow(occupancy, cmap="Greys", vmin=0, vmax=1.6, origin="upper", extent=(0, W, H, 0),
              interpolation="nearest")
    colors = plt.cm.tab10(np.arange(N) % 10)
    ts = np.unique(np.linspace(0, T1 - 1, instants).round().astype(int))
    for k, t in enumerate(ts):  # communication edges at a few instants, fading in with time
        shade = 0.25 + 0.6 * k / max(len(ts) - 1, 1)
        for i in range(N):
            for j in range(i + 1, N):
                if np.linalg.norm(p[t, i] - p[t, j]) <= comm_radius:
                    ax.plot(p[t, [i, j], 0], p[t, [i, j], 1], "-", color=(0.2, 0.6, 0.2, shade), lw=1.0)
        ax.scatter(p[t, :, 0], p[t, :, 1], s=14, c=colors, alpha=shade, zorder=3)
    labels: list[tuple[np.ndarray, list[int]]] = []  # instants whose leader positions coincide share one label
    for t in ts:
        near = [lab for lab in labels if np.linalg.norm(lab[0] - p[t, leader]) < 3.0]
        (near[0][1].append(t) if near else labels.append((p[t, leader], [t])))
    for xy, group in labels:
        ax.annotate("t=" + ",".join(map(str, group)), xy, textcoords="offset points", xytext=(4, 4), fontsize=7,
                    zorder=6)
    for i in range(N):
        lw = 2.2 if i == leader else 1.2
        name = f"robot {i}" + (" (leader)" if i == leader else "")
        ax.plot(p[:, i, 0], p[:, i, 1], "-", color=colors[i], lw=lw, label=name)
        ax.scatter(*p[0, i], marker="o", s=60, facecolors="none", edgecolors=[colors[i]], lw=1.5, zorder=4)
    ax.scatter(*goal, marker="*", s=260, c="red", edgecolors="k", zorder=5, label="goal")
    ax.add_patch(plt.Circle(goal, 1.0, fill=False, color="red", lw=1))
    if crop:
        pts = np.concatenate([p.reshape(-1, 2), np.asarray(goal)[None]])
        lo = np.maximum(pts.min(0) - 12, 0)
        hi = np.minimum(pts.max(0) + 12, [W, H])
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(hi[1], lo[1])
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"{N} robots, {T1 - 1} steps")
    from matplotlib.lines import Line2D

    extra = [Line2D([], [], marker="o", ls="", mfc="none", mec="k", label="start"),
             Line2D([], [], marker=".", ls="", color="grey", label=f"positions at the instants t (step)"),
             Line2D([], [], color=(0.2, 0.6, 0.2), label=f"communication edge (<= {comm_radius:g} m) at t")]
    handles, _ = ax.get_legend_handles_labels()
    ax.legend(handles=handles + extra, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=7, framealpha=0.8)
    out = Path(out)
    if not out.parent.is_dir():
        raise ValueError(f"--out {out}: folder {out.parent} does not exist; create it first")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out


def animate_episode(occupancy: np.ndarray, positions: np.ndarray, goal: np.ndarray, leader: int, out: str | Path,
                    plans: np.ndarray | None = None, plan_steps: list[int] | None = None, comm_radius: float = 15.0,
                    every: int = 4, fps: int = 8, title: str = "") -> Path:
    """Animated GIF of an episode: the team, its communication edges and trails, and (Roken episodes) the chunk
    planned at the latest re-plan. positions (T+1, N, 2); plans (P, N, H, 2) planned at steps plan_steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

    out = Path(out)
    if not out.parent.is_dir():
        raise ValueError(f"--out {out}: folder {out.parent} does not exist; create it first")
    p = np.asarray(positions, dtype=np.float64)
    T1, N, _ = p.shape
    H, W = occupancy.shape
    frames = list(range(0, T1, max(1, every))) + ([T1 - 1] if (T1 - 1) % max(1, every) else [])
    fig, ax = plt.subplots(figsize=(6, 6), dpi=80)
    colors = plt.cm.tab10(np.arange(N) % 10)
    pts = np.concatenate([p.reshape(-1, 2), np.asarray(goal)[None]])
    lo, hi = np.maximum(pts.min(0) - 12, 0), np.minimum(pts.max(0) + 12, [W, H])
    steps = np.asarray(plan_steps if plan_steps is not None else [], dtype=int)

    def draw(t):
        ax.clear()
        ax.imshow(occupancy, cmap="Greys", vmin=0, vmax=1.6, origin="upper", extent=(0, W, H, 0),
                  interpolation="nearest")
        for i in range(N):
            for j in range(i + 1, N):
                if np.linalg.norm(p[t, i] - p[t, j]) <= comm_radius:
                    ax.plot(p[t, [i, j], 0], p[t, [i, j], 1], "-", color=(0.2, 0.6, 0.2), lw=1.0)
        if plans is not None and len(steps):
            k = int(np.searchsorted(steps, t, side="right")) - 1
            if k >= 0:
                for i in range(N):
                    ax.plot(plans[k, i, :, 0], plans[k, i, :, 1], ":", marker=".", ms=3, color=colors[i], lw=1)
        for i in range(N):
            ax.plot(p[:t + 1, i, 0], p[:t + 1, i, 1], "-", color=colors[i], lw=2.0 if i == leader else 1.0, alpha=0.7)
        ax.scatter(p[t, :, 0], p[t, :, 1], s=40, c=colors, edgecolors="k", zorder=4)
        ax.scatter(*goal, marker="*", s=220, c="red", edgecolors="k", zorder=5)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(hi[1], lo[1])
        ax.set_title(f"{title}\nstep {t}/{T1 - 1}  (dotted: the planned chunk; green: links <= {comm_radius:g} m)",
                     fontsize=8)

    anim = FuncAnimation(fig, draw, frames=frames)
    anim.save(out, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return out
