"""Ship a trained model: a checkpoint's EMA weights in half precision, its config.json and a model card.

    roken export runs/mixed models/roken-small-mixed --which best
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from safetensors.torch import load_file

from . import checkpoint as ckpt
from .validation import CHUNK_METRICS


def export(source: str | Path, out: str | Path, which: str = "latest", notes: str = "") -> Path:
    src = ckpt.find(source, which)
    loaded = ckpt.load(src)  # fails here, naming the file, on anything the planner could not load
    cfg = loaded.config
    dest = Path(out)
    if dest.resolve() == src.resolve() or dest.resolve() in src.resolve().parents:
        raise ValueError(f"roken export {source} {out}: the output is the source checkpoint (or holds it); export "
                         f"into another folder")
    if dest.exists() and not (dest / ckpt.CONFIG).is_file():
        raise ValueError(f"{dest} exists and is not a checkpoint directory; choose another output folder")
    tmp = dest.parent / f".tmp-{dest.name}"
    shutil.rmtree(tmp, ignore_errors=True)
    ckpt.write(tmp, load_file(str(src / ckpt.WEIGHTS)), cfg, half=True)
    card = model_card(cfg, src, loaded.model.num_params(), notes)
    (tmp / "MODEL_CARD.md").write_text(keep_sections(card, src / "MODEL_CARD.md"))
    if dest.exists():  # replace a shipped model, not add one beside it
        shutil.rmtree(dest)
    tmp.rename(dest)
    return dest


def keep_sections(card: str, old_card: Path) -> str:
    """The new card plus every `## ` section of the source's card that the new one does not have (a card is
    never shortened by re-exporting: "How it was made", validation histories, ...)."""
    if not old_card.is_file():
        return card
    have = {line.strip() for line in card.splitlines() if line.startswith("## ")}
    extra, keep = [], False
    for line in old_card.read_text().splitlines():
        if line.startswith("## "):
            keep = line.strip() not in have
        if keep:
            extra.append(line)
    return card.rstrip() + ("\n\n" + "\n".join(extra).strip() + "\n" if extra else "\n")


def model_card(cfg: dict, src: Path, params: int, notes: str) -> str:
    m, t, d, v = cfg["model"], cfg["train"], cfg.get("dataset", {}), cfg.get("validation", {})
    rows = []
    for name in ("model", "still", "expert"):
        if f"val/{name}/obs_frac" in v:
            rows.append(f"| {name} | " + " | ".join(f"{v[f'val/{name}/{k}']:.3f}" for k in CHUNK_METRICS) + " |")
    table = "\n".join([f"| chunk | {' | '.join(CHUNK_METRICS)} |", "|" + " --- |" * (len(CHUNK_METRICS) + 1), *rows])
    keys_cl = ("success", "reach", "obstacle_collision", "inter_collision", "connectivity")
    closed = ("| " + " | ".join(keys_cl) + " |\n|" + " --- |" * len(keys_cl) + "\n| "
              + " | ".join(f"{v[f'closed_loop/{k}']:.3f}" for k in keys_cl) + " |") \
        if "closed_loop/success" in v else "(none recorded)"
    code = cfg.get("code_version", {})
    keys = ("condition_prob", "subteam_prob", "final_goal_prob", "team_size_weights")
    samples = json.dumps({k: cfg["samples"][k] for k in keys})
    parts = d.get("datasets") or [d]  # a data mix (DAgger, --data A,B) lists each of its datasets
    data = "; ".join(f"`{x.get('location')}` (fingerprint {x.get('fingerprint')}, {x.get('episodes')} episodes on "
                     f"{x.get('maps')} maps)" for x in parts)
    return f"""# Roken DiT checkpoint

- Architecture: width {m['width']}, {m['depth']} decoder layers, {m['heads']} heads, MLP {m['mlp_hidden']},
  map encoder `{m.get('map_encoder', 'resnet')}` ({m['map_channels']} channels x {m['map_blocks']} blocks), ego-centric
  crop {m.get('local_crop', 0) or 'off'}: {params:,} parameters; weights in fp16
  (EMA of the training weights), loaded in fp32 by `roken.train.checkpoint.load`.
- Trained from `{src}` at step {cfg['step']}: global batch {t['batch_size']}, AdamW lr {t['lr']}, {t['schedule']}
  schedule, EMA {t['ema_decay']}, seed {t['seed']}, {t.get('noise_draws', 1)} noise draw(s) per encoded sample;
  loss {json.dumps(cfg['loss'])}.
- Samples: {samples}.
- Data: {data}.
- Code: roken {code.get('roken')}, git {code.get('git')}.

## Closed-loop validation (the checkpoint's own, {int(v.get('closed_loop/episodes') or 0)} `val` tasks, {t.get('closed_loop_robots', 4)} robots, plain Roken)

{closed}

## Open-loop validation (held-out prompts, DDIM-{t.get('ddim_steps', 10)}, one chunk each)

First-move cosine with the expert: leader {v.get('val/first_move_cos_leader', float('nan')):.3f}, follower {v.get('val/first_move_cos_follower', float('nan')):.3f}; L2 over the executed moves {v.get('val/l2_executed_m', float('nan')):.3f} m.

Held-out loss: total {v.get('val/losses/total', float('nan')):.4f}, L_traj {v.get('val/losses/traj', float('nan')):.4f}.

{table}

{notes}
"""
