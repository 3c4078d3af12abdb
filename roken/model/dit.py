"""Roken: a diffusion transformer whose tokens are robots (paper: "Model Structure").

    robot token  z_i = phi_tok(CAT[phi_tau(noisy chunk_i), phi_g(goal_i - start_i), phi_mg(m_g,i), phi_mtau(m_tau,i)])
                       + PE(start_i)
    map tokens   ResNet(occupancy, start heat-map, goal heat-map) at half resolution, cut into patches of
                 10 x 10 map cells (14 x 14 = 196 tokens on the 140 canvas), + PE(patch centre)
    decoder      per layer: self-attention among robot tokens (key-padding mask), cross-attention to the map
                 tokens, MLP; AdaLN-Zero conditioning on the diffusion step (DiT). By default the cross-attention
                 output has no zero gate, so map information flows from the first step of training (paper).
    heads        noise (final layer), waypoints (final layer), local occupancy at 1x and 3x (middle layer);
                 the auxiliary heads run only when asked for (training).

Robot tokens carry no slot index, so the network is equivariant to the robot order, and padding tokens are
excluded as attention keys, so they change nothing for the real robots.

Parameter count of the `paper` preset. The paper states 11.9M parameters, 8 layers, 8 heads and "hidden
dimension 512". Standard blocks of width 512 (self + cross attention, MLP 4x, AdaLN) have about 50M. The
reading that gives 11.9M is token width 256 with MLP hidden dimension 512: 8 blocks of 1.32M (self-attention
0.26M, cross-attention 0.26M, MLP 0.26M, AdaLN modulation 0.53M) plus a 2-block ResNet map encoder, the token
embeddings and the heads; tests/test_model.py checks the count within 3 %.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn as nn
import torch.nn.functional as F


@dataclass
class ModelConfig:
    width: int = 256  # robot / map token width
    depth: int = 8  # decoder layers
    heads: int = 8
    mlp_hidden: int = 512  # the paper's "hidden dimension 512" (see the module docstring)
    map_channels: int = 64  # ResNet channels at half resolution
    map_blocks: int = 2  # ResNet basic blocks
    map_patch: int = 10  # map cells per token side (paper: 10 x 10)
    canvas: int = 140
    horizon: int = 16  # chunk length H
    num_waypoints: int = 5
    occ_patch: int = 7
    occ_layer: int = -1  # decoder layer whose output feeds the occupancy heads; -1 = the middle one
    cross_attn_gate: bool = False  # AdaLN-Zero gate on the cross-attention output (paper: off)
    freq_dim: int = 256  # sinusoidal features of the diffusion step
    # Beyond the paper, for laptops (README "A map encoder for laptops"); the defaults are the paper's.
    map_encoder: str = "resnet"  # resnet (paper) | patch: linear 10x10 patch embedding + ConvNeXt mixer blocks
    local_crop: int = 0  # side (cells) of an ego-centric occupancy crop in each robot token, at 1x and 3x; 0 = off
    # Beyond the paper: each robot token also sees its last chunk move (cond["prev_move"]), the inertia the
    # expert's next moves follow; zero-initialised, so a model trained without it starts unchanged.
    prev_move: bool = False
    # Beyond the paper: each robot token also sees its `neighbours` nearest team-mates as offsets from it (m / 5,
    # the distance, a presence flag; README "Team-mates as offsets"): the pairwise geometry the robot-robot
    # constraints depend on, which absolute sinusoidal positions leave to attention to compute. Zero-initialised
    # like prev_move; 0 = off.
    neighbours: int = 0


PRESETS = {
    "paper": ModelConfig(),
    "small": ModelConfig(width=128, depth=4, heads=4, mlp_hidden=256, map_channels=32, map_blocks=1),
    "tiny": ModelConfig(width=64, depth=2, heads=4, mlp_hidden=128, map_channels=16, map_blocks=1),
}


def preset(name: str, **overrides) -> ModelConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown model preset {name!r}; choose one of {sorted(PRESETS)}")
    return replace(PRESETS[name], **overrides)


def sincos_2d(p: torch.Tensor, dim: int) -> torch.Tensor:
    """(..., 2) positions in metres -> (..., dim) sinusoidal features, half for x and half for y."""
    quarter = dim // 4
    omega = 1.0 / 10000 ** (torch.arange(quarter, device=p.device, dtype=torch.float32) / quarter)
    ax, ay = p[..., :1].float() * omega, p[..., 1:].float() * omega
    return torch.cat([ax.sin(), ax.cos(), ay.sin(), ay.cos()], dim=-1)


def check(cfg: ModelConfig) -> None:
    """Shapes that would otherwise fail at the first forward pass, named by their keys."""
    if cfg.map_encoder not in MAP_ENCODERS:
        raise ValueError(f"model.map_encoder must be one of {', '.join(MAP_ENCODERS)}, got {cfg.map_encoder!r}")
    if cfg.local_crop < 0:
        raise ValueError(f"model.local_crop must be >= 0 (0 = off), got {cfg.local_crop}")
    if cfg.neighbours < 0:
        raise ValueError(f"model.neighbours must be >= 0 (0 = off), got {cfg.neighbours}")
    problems = []
    if min(cfg.width, cfg.depth, cfg.heads, cfg.mlp_hidden, cfg.map_patch, cfg.horizon, cfg.freq_dim) < 1:
        problems.append("model.width, depth, heads, mlp_hidden, map_patch, horizon and freq_dim must be >= 1")
    elif cfg.width % cfg.heads:
        problems.append(f"model.width={cfg.width} is not divisible by model.heads={cfg.heads}")
    if cfg.width % 4:
        problems.append(f"model.width={cfg.width} must be a multiple of 4 (2-D sinusoidal position features)")
    if cfg.freq_dim % 2:
        problems.append(f"model.freq_dim={cfg.freq_dim} must be even (cos and sin halves)")
    if cfg.map_patch >= 1 and cfg.canvas % cfg.map_patch:
        problems.append(f"model.map_patch={cfg.map_patch} does not divide model.canvas={cfg.canvas}")
    if cfg.map_encoder == "resnet" and (cfg.map_patch % 2 or cfg.map_channels % 8 or cfg.map_channels < 8):
        problems.append(f"the resnet map encoder needs an even model.map_patch (got {cfg.map_patch}) and "
                        f"model.map_channels a multiple of 8 (GroupNorm of 8 groups; got {cfg.map_channels})")
    if cfg.depth >= 1 and not -1 <= cfg.occ_layer < cfg.depth:
        problems.append(f"model.occ_layer={cfg.occ_layer} must be -1 (the middle layer) or a layer 0..{cfg.depth - 1}")
    if problems:
        raise ValueError("; ".join(problems))


def modulate(x, shift, scale):
    return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1)


class TimestepEmbedder(nn.Module):
    """Diffusion step k -> (B, width), as in DiT."""

    def __init__(self, width: int, freq_dim: int):
        super().__init__()
        self.freq_dim = freq_dim
        self.mlp = nn.Sequential(nn.Linear(freq_dim, width), nn.SiLU(), nn.Linear(width, width))

    def forward(self, k: torch.Tensor) -> torch.Tensor:
        half = self.freq_dim // 2
        freqs = torch.exp(-math.log(10000) * torch.arange(half, device=k.device, dtype=torch.float32) / half)
        args = k.float()[:, None] * freqs[None]
        return self.mlp(torch.cat([args.cos(), args.sin()], dim=-1))


def neighbour_offsets(start: torch.Tensor, robot_mask: torch.Tensor, k: int) -> torch.Tensor:
    """(B, R, 2) positions (m), (B, R) real robots -> (B, R, 4k): each robot's k nearest real team-mates, nearest
    first, as (dx / 5, dy / 5, distance / 5, 1); zeros where fewer than k exist. Sorted by distance, so the
    features do not depend on the robots' order."""
    B, R, _ = start.shape
    off = start[:, None, :, :] - start[:, :, None, :]  # (B, R, R, 2): j relative to i
    d = off.norm(dim=-1)  # (B, R, R)
    valid = robot_mask.bool()[:, None, :] & ~torch.eye(R, dtype=torch.bool, device=start.device)
    kk = min(k, R)
    dist, idx = d.masked_fill(~valid, float("inf")).topk(kk, dim=-1, largest=False)  # (B, R, kk)
    pres = torch.isfinite(dist)
    o = off.gather(2, idx[..., None].expand(B, R, kk, 2))  # (B, R, kk, 2)
    feat = torch.cat([o, dist[..., None], torch.full_like(dist[..., None], 5.0)], -1) / 5.0
    feat = torch.where(pres[..., None], feat, 0.0)  # slots without a team-mate (inf distance) stay 0
    if kk < k:
        feat = torch.cat([feat, feat.new_zeros(B, R, k - kk, 4)], dim=2)
    return feat.reshape(B, R, 4 * k)


def patch_positions(cfg: ModelConfig) -> torch.Tensor:
    """(M, width) sinusoidal embeddings of the map patches' centres (metres), row-major patches."""
    n = cfg.canvas // cfg.map_patch
    centres = (torch.arange(n, dtype=torch.float32) + 0.5) * cfg.map_patch
    grid = torch.stack(torch.meshgrid(centres, centres, indexing="xy"), dim=-1).reshape(-1, 2)  # (M, 2) = (x, y)
    return sincos_2d(grid, cfg.width)


class BasicBlock(nn.Module):
    """ResNet basic block; GroupNorm instead of BatchNorm because a plan's batch is G copies of one map."""

    def __init__(self, c: int):
        super().__init__()
        self.conv1, self.norm1 = nn.Conv2d(c, c, 3, padding=1, bias=False), nn.GroupNorm(8, c)
        self.conv2, self.norm2 = nn.Conv2d(c, c, 3, padding=1, bias=False), nn.GroupNorm(8, c)

    def forward(self, x):
        h = F.silu(self.norm1(self.conv1(x)))
        return F.silu(x + self.norm2(self.conv2(h)))


class MapEncoder(nn.Module):
    """(B, 3, S, S) map tensor -> (B, M, width) patch tokens, M = (S / map_patch)^2."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        c = cfg.map_channels
        self.stem = nn.Sequential(nn.Conv2d(3, c, 3, stride=2, padding=1, bias=False), nn.GroupNorm(8, c), nn.SiLU())
        self.blocks = nn.Sequential(*[BasicBlock(c) for _ in range(cfg.map_blocks)])
        p = cfg.map_patch // 2  # patch side in half-resolution cells
        self.patch = nn.Conv2d(c, cfg.width, p, stride=p)
        self.register_buffer("pos", patch_positions(cfg), persistent=False)  # (M, width)
        self.norm = nn.LayerNorm(cfg.width)

    def forward(self, m: torch.Tensor) -> torch.Tensor:
        # channels_last (NHWC): oneDNN's fast convolution / GroupNorm layout; the encoder is ~95 % of a `small`
        # training step on a CPU, and this layout makes it 27 % faster there (benchmarks/README.md).
        m = m.contiguous(memory_format=torch.channels_last)
        h = self.blocks(self.stem(m))  # (B, C, S/2, S/2)
        h = self.patch(h).flatten(2).transpose(1, 2)  # (B, M, width), row-major patches
        return self.norm(h + self.pos)


class ConvNeXtBlock(nn.Module):
    """Depthwise 7x7 mixing over the patch grid + a pointwise MLP (ConvNeXt), on (B, W, n, n) tokens."""

    def __init__(self, w: int):
        super().__init__()
        self.dw = nn.Conv2d(w, w, 7, padding=3, groups=w)
        self.norm = nn.LayerNorm(w)
        self.mlp = nn.Sequential(nn.Linear(w, 2 * w), nn.GELU(approximate="tanh"), nn.Linear(2 * w, w))

    def forward(self, x):
        h = self.dw(x).permute(0, 2, 3, 1)  # (B, n, n, W)
        return x + self.mlp(self.norm(h)).permute(0, 3, 1, 2)


class PatchMapEncoder(nn.Module):
    """(B, 3, S, S) -> (B, M, width): a linear embedding of each 10 x 10 patch at full resolution, then
    `map_blocks` ConvNeXt blocks over the 14 x 14 grid. About 30x fewer FLOPs than the ResNet at `small`
    widths (benchmarks/README.md), the same token layout and positional embedding."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.patch = nn.Conv2d(3, cfg.width, cfg.map_patch, stride=cfg.map_patch)
        self.blocks = nn.Sequential(*[ConvNeXtBlock(cfg.width) for _ in range(cfg.map_blocks)])
        self.register_buffer("pos", patch_positions(cfg), persistent=False)
        self.norm = nn.LayerNorm(cfg.width)

    def forward(self, m: torch.Tensor) -> torch.Tensor:
        h = self.blocks(self.patch(m))  # (B, W, n, n)
        return self.norm(h.flatten(2).transpose(1, 2) + self.pos)


MAP_ENCODERS = {"resnet": MapEncoder, "patch": PatchMapEncoder}


def local_crops(occ: torch.Tensor, start: torch.Tensor, side: int, scales=(1.0, 3.0)) -> torch.Tensor:
    """Ego-centric occupancy around each robot: occ (Bm, S, S), start (Bm, R, 2) metres -> (Bm, R, len(scales)
    side^2), bilinear at offsets (j - (side-1)/2) * scale metres from the start (outside the canvas: obstacle)."""
    Bm, S = occ.shape[0], occ.shape[-1]
    o = (torch.arange(side, device=occ.device, dtype=torch.float32) - (side - 1) / 2)
    oy, ox = torch.meshgrid(o, o, indexing="ij")
    off = torch.stack([ox, oy], -1).reshape(-1, 2)  # (side^2, 2) = (x, y)
    off = torch.cat([off * s for s in scales])  # (n_s side^2, 2)
    pts = start.float()[:, :, None, :] + off  # (Bm, R, P, 2)
    grid = pts.reshape(Bm, -1, 1, 2) * (2.0 / S) - 1.0
    padded = F.pad(occ[:, None].float(), (1, 1, 1, 1), value=1.0)  # outside counts as obstacle
    grid = grid * (S / (S + 2))  # the same metres on the padded grid
    out = F.grid_sample(padded, grid.to(padded.dtype), mode="bilinear", padding_mode="border", align_corners=False)
    return out.view(Bm, start.shape[1], -1)


class Attention(nn.Module):
    """Multi-head attention with separate query and key/value projections, so the map's keys/values can be
    computed once per plan (`kv`) and reused at every denoising step."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(width, width)
        self.kv_proj = nn.Linear(width, 2 * width)
        self.out = nn.Linear(width, width)

    def kv(self, src: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        B, M, W = src.shape
        k, v = self.kv_proj(src).view(B, M, 2, self.heads, W // self.heads).permute(2, 0, 3, 1, 4)
        return k, v  # (B, heads, M, head_dim) each

    def forward(self, x: torch.Tensor, k: torch.Tensor, v: torch.Tensor, mask: torch.Tensor | None = None):
        # x (B, N, W); k, v (Bk, heads, M, hd) where B = Bk * G: the G candidates of one prompt become extra
        # queries against the same keys, so the map keys/values are never copied per candidate.
        B, N, W = x.shape
        G = B // k.shape[0]
        q = self.q(x).view(k.shape[0], G * N, self.heads, W // self.heads).transpose(1, 2)
        o = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)  # (Bk, heads, G*N, hd)
        return self.out(o.transpose(1, 2).reshape(B, N, W))


class DecoderBlock(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        w = cfg.width
        self.norm1 = nn.LayerNorm(w, elementwise_affine=False, eps=1e-6)
        self.attn = Attention(w, cfg.heads)
        self.norm2 = nn.LayerNorm(w, elementwise_affine=False, eps=1e-6)
        self.cross = Attention(w, cfg.heads)
        self.norm3 = nn.LayerNorm(w, elementwise_affine=False, eps=1e-6)
        self.mlp = nn.Sequential(nn.Linear(w, cfg.mlp_hidden), nn.GELU(approximate="tanh"), nn.Linear(cfg.mlp_hidden, w))
        self.gate_cross = cfg.cross_attn_gate
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(w, (9 if self.gate_cross else 8) * w))

    def forward(self, x, c, map_kv, pad_mask):
        # x (B, N, W) robot tokens, c (B, W) step embedding, map_kv cached keys/values, pad_mask (B, 1, 1, N)
        mods = self.adaLN_modulation(c).chunk(9 if self.gate_cross else 8, dim=-1)
        sh1, sc1, g1, sh2, sc2, sh3, sc3, g3 = mods[:8]
        h = modulate(self.norm1(x), sh1, sc1)
        k, v = self.attn.kv(h)
        x = x + g1.unsqueeze(1) * self.attn(h, k, v, pad_mask)
        h = self.cross(modulate(self.norm2(x), sh2, sc2), *map_kv)
        x = x + (mods[8].unsqueeze(1) * h if self.gate_cross else h)
        return x + g3.unsqueeze(1) * self.mlp(modulate(self.norm3(x), sh3, sc3))


class FinalLayer(nn.Module):
    def __init__(self, width: int, out: int):
        super().__init__()
        self.norm = nn.LayerNorm(width, elementwise_affine=False, eps=1e-6)
        self.linear = nn.Linear(width, out)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(width, 2 * width))

    def forward(self, x, c):
        shift, scale = self.adaLN_modulation(c).chunk(2, dim=-1)
        return self.linear(modulate(self.norm(x), shift, scale))


def mlp_head(width: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.LayerNorm(width), nn.Linear(width, width), nn.GELU(approximate="tanh"), nn.Linear(width, out))


class MapContext:
    """What a plan computes once: the map tokens' keys/values for every decoder layer, and the occupancy
    channel (Bm, S, S) the ego-centric crops are read from."""

    def __init__(self, kv: list[tuple[torch.Tensor, torch.Tensor]], occ: torch.Tensor | None = None):
        self.kv, self.occ = kv, occ

    @property
    def batch(self) -> int:
        return self.kv[0][0].shape[0]


class RokenDiT(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        w, H = cfg.width, cfg.horizon
        self.phi_tau = nn.Linear(2 * H, w)
        self.phi_g = nn.Linear(2, w)
        self.phi_mg = nn.Embedding(2, w)
        self.phi_mtau = nn.Embedding(2, w)
        self.phi_tok = nn.Linear(4 * w, w)
        self.t_embed = TimestepEmbedder(w, cfg.freq_dim)
        check(cfg)
        self.map_encoder = MAP_ENCODERS[cfg.map_encoder](cfg)
        if cfg.local_crop:
            self.phi_crop = nn.Sequential(nn.Linear(2 * cfg.local_crop ** 2, w), nn.SiLU(), nn.Linear(w, w))
        if cfg.prev_move:
            self.phi_prev = nn.Linear(2, w)
        if cfg.neighbours:
            self.phi_nbr = nn.Sequential(nn.Linear(4 * cfg.neighbours, w), nn.SiLU(), nn.Linear(w, w))
        self.blocks = nn.ModuleList([DecoderBlock(cfg) for _ in range(cfg.depth)])
        self.occ_layer = cfg.occ_layer if cfg.occ_layer >= 0 else cfg.depth // 2 - 1
        self.final = FinalLayer(w, 2 * H)
        self.wp_head = mlp_head(w, 2 * cfg.num_waypoints)
        self.occ_head = mlp_head(w, 2 * cfg.occ_patch ** 2)
        self.initialize_weights()

    def initialize_weights(self):
        def basic(m):
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)
            elif isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, nn.Embedding):
                nn.init.normal_(m.weight, std=0.02)
        self.apply(basic)
        self.map_encoder.to(memory_format=torch.channels_last)  # conv weights in the layout of the input
        for lin in (self.t_embed.mlp[0], self.t_embed.mlp[2]):
            nn.init.normal_(lin.weight, std=0.02)
        # AdaLN-Zero: every block starts as the identity on the gated paths, the noise output starts at 0.
        for blk in self.blocks:
            nn.init.zeros_(blk.adaLN_modulation[-1].weight)
            nn.init.zeros_(blk.adaLN_modulation[-1].bias)
        nn.init.zeros_(self.final.adaLN_modulation[-1].weight)
        nn.init.zeros_(self.final.adaLN_modulation[-1].bias)
        nn.init.zeros_(self.final.linear.weight)
        nn.init.zeros_(self.final.linear.bias)
        if self.cfg.prev_move:  # the last move enters at 0: a fine-tune from a model without it starts unchanged
            nn.init.zeros_(self.phi_prev.weight)
            nn.init.zeros_(self.phi_prev.bias)
        if self.cfg.neighbours:  # the same for the team-mates' offsets
            nn.init.zeros_(self.phi_nbr[-1].weight)
            nn.init.zeros_(self.phi_nbr[-1].bias)

    def num_params(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def encode_map(self, map_tensor: torch.Tensor) -> MapContext:
        """(B, 3, S, S) -> the cross-attention keys/values of every layer; once per plan."""
        tokens = self.map_encoder(map_tensor)  # (B, M, W)
        return MapContext([blk.cross.kv(tokens) for blk in self.blocks], map_tensor[:, 0])

    def forward(self, x: torch.Tensor, k: torch.Tensor, cond: dict, ctx: MapContext | None = None,
                aux: bool = False) -> dict[str, torch.Tensor]:
        """x (B, R, H, 2) noisy chunks (conditioned robots hold their clean chunk), k (B,) diffusion steps,
        cond: start (B, R, 2) m, rel_goal (B, R, 2), goal_mask, traj_mask (B, R), robot_mask (B, R) bool,
        prev_move (B, R, 2) (read with model.prev_move),
        map (Bm, 3, S, S) with B = Bm * G (G candidates per map). Returns eps (B, R, H, 2), the denoiser's
        output: the noise, or v or x0 per diffusion.prediction (NoiseSchedule.eps_from reads it as the noise);
        with aux, waypoints (B, R, K, 2), occ_small / occ_large logits (B, R, P, P)."""
        B, R, H, _ = x.shape
        if ctx is None:
            ctx = self.encode_map(cond["map"])
        tok = torch.cat([self.phi_tau(x.reshape(B, R, 2 * H)), self.phi_g(cond["rel_goal"]),
                         self.phi_mg(cond["goal_mask"].long()), self.phi_mtau(cond["traj_mask"].long())], dim=-1)
        z = self.phi_tok(tok) + sincos_2d(cond["start"], self.cfg.width)  # (B, R, W)
        if self.cfg.local_crop:  # one crop per map row, shared by its G candidates / K draws
            Bm = ctx.occ.shape[0]
            crop = local_crops(ctx.occ, cond["start"].view(Bm, B // Bm, R, 2)[:, 0], self.cfg.local_crop)
            z = z + self.phi_crop(crop).repeat_interleave(B // Bm, 0)  # (B, R, W)
        if self.cfg.prev_move:  # absent from the condition: at rest (build_condition's previous=None)
            prev = cond.get("prev_move")
            z = z + self.phi_prev(torch.zeros_like(cond["start"]) if prev is None else prev.to(z.dtype))  # (B, R, W)
        if self.cfg.neighbours:
            nbr = neighbour_offsets(cond["start"].float(), cond["robot_mask"], self.cfg.neighbours)  # (B, R, 4K)
            z = z + self.phi_nbr(nbr.to(z.dtype))  # (B, R, W)
        c = self.t_embed(k)  # (B, W)
        pad_mask = cond["robot_mask"].bool()[:, None, None, :]  # (B, 1, 1, R): True = attend
        out = {}
        for i, blk in enumerate(self.blocks):
            z = blk(z, c, ctx.kv[i], pad_mask)
            if aux and i == self.occ_layer:
                P = self.cfg.occ_patch
                occ = self.occ_head(z).view(B, R, 2, P, P)
                out["occ_small"], out["occ_large"] = occ[:, :, 0], occ[:, :, 1]
        out["eps"] = self.final(z, c).view(B, R, H, 2)
        if aux:
            out["waypoints"] = self.wp_head(z).view(B, R, self.cfg.num_waypoints, 2)
        return out
