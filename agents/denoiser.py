"""The scene denoiser (MiDiffusion-style, iARCS appendix A) and :class:`ScenePrior`, which bundles it with
the noise schedule, the dataset statistics and the room type, samples scenes and saves / loads checkpoints.

Network, for x_t of shape (B, N, 8 + K) (N object slots; geometry 8 = translation 3, half size 3,
[cos, sin] yaw; K class logits mapped to {-1, +1}):

* slot embedding: geometry through a 2-layer MLP plus a linear map of the class part (a learnable class
  embedding weighted by the noisy one-hot), summed; no positional encoding, so the network is
  permutation-equivariant over slots; with ``slot_embedding`` a learned embedding of the slot's index is added
  (slot identity, for rooms in a canonical slot order: ``PretrainConfig.canonical_order``);
* floor encoder: a PointNet over the 256 boundary points with inward normals (x, z, nx, nz): per-point
  MLP 4 -> 64 -> 64 -> 512, max-pool over points, then 512 -> 64 (widths [4, 64, 64, 512, 64]); the 64-d
  global floor feature is mapped to ``floor_tokens`` context tokens, and ``floor_point_tokens`` boundary
  points, subsampled evenly along the boundary, keep their 512-d per-point features as more tokens (projected
  to width d, plus a projection of the global feature), so cross-attention sees where the walls are;
* slot translations (x, z) are in the room frame of :class:`iarcs_env.stats.DatasetStats` (each centre over
  its free half-range in the floor's bounding box, +-1 = touching a wall), which made placement against walls
  precise (docs/results/prior_bedroom_small.md);
* wall features: each slot's noisy (x, z) against the subsampled boundary points, in the floor's
  bounding-box frame: offset to the nearest point, its inward normal and signed distance, the same for the
  nearest point of another wall, the floor's half-extents and both footprint-to-wall gaps in metres
  (:meth:`SceneDenoiser.wall_features`; 14 numbers through an MLP added to the slot embedding);
* timestep: sinusoidal embedding -> MLP, plus a linear map of the global floor feature; it drives the
  shift / scale / gate of every sub-layer's adaptive layer norm (zero-initialised as in DiT's adaLN-Zero);
* ``num_layers`` blocks of self-attention over the slots, cross-attention to the floor tokens and a GELU
  feed-forward; attention uses explicit ``q_proj``, ``k_proj``, ``v_proj``, ``out_proj`` ``nn.Linear``
  layers (LoRA targets exactly these; ``nn.MultiheadAttention`` would bypass LoRA on its fast path);
* output: epsilon (or x0, or v: the schedule's ``prediction_type``) of shape (B, N, 8 + K).

:meth:`SceneDenoiser.encode_floor` returns one tensor (B, rows, d): row 0 is the floor's adaLN vector, then
the cross-attention tokens, then the subsampled raw boundary points and the floor's half-extents packed into
rows of width d; one tensor, so that it can be cached over a rollout and concatenated for classifier-free
guidance.

Unconditional predictions (classifier-free guidance, condition dropout in training) use an all-zero floor
input, which no real floor produces (its normals are unit vectors).

This is the one design (every shipped checkpoint's). The switches of earlier designs (:data:`RETIRED_FIELDS`)
are gone; a saved config may still name them with the values of this design, any other value is refused.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from iarcs_env.floorplan import FloorPlan
from iarcs_env.rooms import RoomSpec, get_room
from iarcs_env.scene import MIN_FREE_RANGE, SceneBatch, floor_features, footprint_reach
from iarcs_env.schedule import NoiseSchedule, ScheduleConfig, guided_model_fn, standard_normal
from iarcs_env.stats import DatasetStats

from .pointnet import PointNetEncoder

GEOMETRY_DIM = 8
CHECKPOINT_FORMAT = "iarcs-scene-prior"
CHECKPOINT_VERSION = 1  # DenoiserConfig fields of earlier designs: drop_retired_fields
CHECKPOINT_DIR = Path(__file__).resolve().parent / "checkpoints"
MAX_SLOTS = 32  # rows of the slot-index embedding (DenoiserConfig.slot_embedding); the first N are used


@dataclass
class DenoiserConfig:
    """Size of the denoiser. Presets: :meth:`paper` and :meth:`small` (see :data:`PRESETS`)."""

    num_layers: int = 8
    """Transformer blocks (self-attention, cross-attention, feed-forward)."""
    width: int = 512
    """Token width d of the slot embeddings and attention."""
    num_heads: int = 4
    """Attention heads (width must be divisible by it)."""
    ff_dim: int = 2048
    """Hidden width of the GELU feed-forward."""
    dropout: float = 0.1
    """Dropout in attention and feed-forward (training only)."""
    pointnet: tuple = (4, 64, 64, 512, 64)
    """PointNet widths: per-point MLP up to the second-to-last width, max-pool, then a linear map to the
    last width (the floor feature)."""
    floor_tokens: int = 4
    """Context tokens the global floor feature is mapped to for cross-attention, beside the point tokens."""
    floor_point_tokens: int = 64
    """Boundary points, subsampled evenly along the boundary, whose per-point PointNet features are
    cross-attention tokens and against which the wall features measure each slot (> 0)."""
    slot_embedding: bool = False
    """Add a learned embedding of each slot's index to its token (a table of ``MAX_SLOTS`` rows, the first N
    used), as DiffuScene's instance embedding: slots get an identity and the network is no longer
    permutation-equivariant; meant for rooms in a canonical slot order (``PretrainConfig.canonical_order``).
    False: exchangeable slots (the original design)."""

    def __post_init__(self):
        self.pointnet = tuple(int(v) for v in self.pointnet)
        if self.width % self.num_heads:
            raise ValueError(f"width {self.width} is not divisible by num_heads {self.num_heads}")
        if self.floor_point_tokens < 1:
            raise ValueError(f"floor_point_tokens must be > 0 (the boundary points the wall features measure); "
                             f"got {self.floor_point_tokens}")
        if self.floor_tokens < 0:
            raise ValueError(f"floor_tokens must be >= 0; got {self.floor_tokens}")
        if len(self.pointnet) < 3 or self.pointnet[0] != 4:
            raise ValueError(f"pointnet widths must start with 4 (x, z, nx, nz) and have >= 3 entries; "
                             f"got {list(self.pointnet)}")

    @classmethod
    def paper(cls) -> "DenoiserConfig":
        """iARCS / MiDiffusion size: 8 layers, width 512, 4 heads, feed-forward 2048, dropout 0.1, PointNet
        [4, 64, 64, 512, 64], 64 boundary-point tokens (the dataclass defaults)."""
        return cls()

    @classmethod
    def small(cls) -> "DenoiserConfig":
        """CPU default: a 20-step DDIM rollout of 32 bedrooms in about a second on 2 cores."""
        return cls(num_layers=6, width=128, num_heads=4, ff_dim=512, dropout=0.0)

    @classmethod
    def tiny(cls) -> "DenoiserConfig":
        """For tests only."""
        return cls(num_layers=1, width=32, num_heads=2, ff_dim=64, dropout=0.0, pointnet=(4, 16, 32, 16),
                   floor_tokens=2, floor_point_tokens=8)

    @classmethod
    def from_preset(cls, name: str, **overrides) -> "DenoiserConfig":
        if name not in PRESETS:
            raise ValueError(f"unknown model preset {name!r}; choose one of: {', '.join(PRESETS)}")
        base = asdict(PRESETS[name]())
        overrides = drop_retired_fields(overrides, "model settings")
        unknown = sorted(set(overrides) - set(base))
        if unknown:
            raise ValueError(f"unknown denoiser field(s) {', '.join(unknown)}; known: {', '.join(base)}")
        return cls(**{**base, **overrides})


PRESETS = {"paper": DenoiserConfig.paper, "small": DenoiserConfig.small, "tiny": DenoiserConfig.tiny}

#: Switches of earlier designs and the value every shipped checkpoint has (the one design now); a saved config
#: (checkpoint, a run's ``model`` settings) may still carry them at these values.
RETIRED_FIELDS = {"floor_adaln": True, "floor_slot_features": True, "room_frame": True, "pair_bias": False}


def drop_retired_fields(values: dict, where: str = "denoiser config") -> dict:
    """``values`` (DenoiserConfig fields) without :data:`RETIRED_FIELDS`; a ValueError where one of them, or
    ``floor_point_tokens`` (0 was "none"), asks for a design this version no longer runs. Every saved or
    configured denoiser config is read through this."""
    bad = [(k, values[k]) for k, kept in RETIRED_FIELDS.items() if k in values and values[k] != kept]
    if "floor_point_tokens" in values and values["floor_point_tokens"] == 0:
        bad.append(("floor_point_tokens", 0))
    if bad:
        key, value = bad[0]
        raise ValueError(f"{where}: made by an earlier design of the denoiser ({key}={value!r}) that this version "
                         "of iARCS no longer runs; use the iARCS version that made it")
    return {k: v for k, v in values.items() if k not in RETIRED_FIELDS}


# --- building blocks -----------------------------------------------------------------------------------
class Attention(nn.Module):
    """Multi-head attention with explicit q/k/v/out projections (LoRA-ready; never nn.MultiheadAttention)."""

    def __init__(self, dim: int, num_heads: int, context_dim: int | None = None, dropout: float = 0.0):
        super().__init__()
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.dropout = dropout
        kv = context_dim or dim
        self.q_proj = nn.Linear(dim, dim)
        self.k_proj = nn.Linear(kv, dim)
        self.v_proj = nn.Linear(kv, dim)
        self.out_proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        """Attention of ``x`` (B, N, dim) to itself, or to ``context`` (B, M, context_dim): cross-attention to
        the many floor tokens (M > N) without projecting them (:meth:`forward_context_absorbed`) where the key and
        value projections are plain layers, not LoRA-wrapped."""
        if (context is not None and context.shape[1] > x.shape[1]
                and type(self.k_proj) is nn.Linear and type(self.v_proj) is nn.Linear):
            return self.forward_context_absorbed(x, context)
        return self.forward_reference(x, context)

    def forward_reference(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        """softmax(q k^T / sqrt(d_head)) v per head, with k and v the projections of every context token."""
        ctx = x if context is None else context
        b, n, d = x.shape
        m = ctx.shape[1]
        q = self.q_proj(x).view(b, n, self.num_heads, self.head_dim).transpose(1, 2)
        k = self.k_proj(ctx).view(b, m, self.num_heads, self.head_dim).transpose(1, 2)
        v = self.v_proj(ctx).view(b, m, self.num_heads, self.head_dim).transpose(1, 2)
        o = _attend(q, k, v, self.dropout if self.training else 0.0)
        return self.out_proj(o.transpose(1, 2).reshape(b, n, d))

    def forward_context_absorbed(self, x: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        """The same attention with the key and value projections moved onto the N queries: per head h,
        q_h (c W_k,h + b_k,h)^T = (q_h W_k,h) c^T + a constant per query, which the softmax drops, and
        softmax(.) (c W_v,h + b_v,h) = (softmax(.) c) W_v,h^T + b_v,h. All heads then attend to the raw context c
        as one head over N x heads queries; the (B, M, dim) keys and values are never formed. Equal to
        :meth:`forward_reference` up to float rounding; cheaper when M >> N (68 floor tokens, 12 slots)."""
        b, n, d = x.shape
        h, hd = self.num_heads, self.head_dim
        q = self.q_proj(x).view(b * n, h, hd).transpose(0, 1)  # (h, B N, hd)
        q = torch.bmm(q, self.k_proj.weight.view(h, hd, -1).to(q.dtype))  # (h, B N, context_dim)
        q = q.view(h, b, n, -1).transpose(0, 1).reshape(b, h * n, -1)
        context = context.to(q.dtype)
        scores = torch.bmm(q, context.transpose(1, 2)) * hd ** -0.5  # (B, h N, M)
        weights = torch.softmax(scores, -1, dtype=torch.promote_types(scores.dtype, torch.float32))
        weights = F.dropout(weights, self.dropout, self.training).to(q.dtype)
        mixed = torch.bmm(weights, context)  # (B, h N, context_dim)
        mixed = mixed.view(b, h, n, -1).transpose(0, 1).reshape(h, b * n, -1)
        o = torch.bmm(mixed, self.v_proj.weight.view(h, hd, -1).transpose(1, 2).to(mixed.dtype))  # (h, B N, hd)
        o = (o + self.v_proj.bias.view(h, 1, hd)).transpose(0, 1).reshape(b, n, d)
        return self.out_proj(o)


def _attend(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, dropout: float):
    """``F.scaled_dot_product_attention``; in float32 on the CPU, where its bfloat16 backward is ten times slower
    than the float32 one (docs/results/benchmarks.md, "Pretraining")."""
    if q.device.type != "cpu" or torch.bfloat16 not in (q.dtype, k.dtype, v.dtype):
        return F.scaled_dot_product_attention(q, k, v, dropout_p=dropout)
    with torch.autocast("cpu", enabled=False):
        return F.scaled_dot_product_attention(q.float(), k.float(), v.float(), dropout_p=dropout).to(q.dtype)


def modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return x * (1 + scale[:, None]) + shift[:, None]


class DenoiserBlock(nn.Module):
    """adaLN-Zero block: self-attention over slots, cross-attention to the floor, GELU feed-forward."""

    def __init__(self, cfg: DenoiserConfig):
        super().__init__()
        d = cfg.width
        self.norm1 = nn.LayerNorm(d, elementwise_affine=False, eps=1e-6)
        self.self_attn = Attention(d, cfg.num_heads, dropout=cfg.dropout)
        self.norm2 = nn.LayerNorm(d, elementwise_affine=False, eps=1e-6)
        self.cross_attn = Attention(d, cfg.num_heads, dropout=cfg.dropout)
        self.norm3 = nn.LayerNorm(d, elementwise_affine=False, eps=1e-6)
        self.ff = nn.Sequential(nn.Linear(d, cfg.ff_dim), nn.GELU(), nn.Dropout(cfg.dropout),
                                nn.Linear(cfg.ff_dim, d), nn.Dropout(cfg.dropout))
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(d, 9 * d))
        nn.init.zeros_(self.ada[1].weight)
        nn.init.zeros_(self.ada[1].bias)

    def forward(self, x: torch.Tensor, temb: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        s1, c1, g1, s2, c2, g2, s3, c3, g3 = self.ada(temb).chunk(9, dim=-1)
        x = x + g1[:, None] * self.self_attn(modulate(self.norm1(x), s1, c1))
        x = x + g2[:, None] * self.cross_attn(modulate(self.norm2(x), s2, c2), context)
        x = x + g3[:, None] * self.ff(modulate(self.norm3(x), s3, c3))
        return x


# SceneDenoiser.wall_features: (offset 2, normal 2, signed distance 1) x 2 walls, the floor's half-extents (x, z)
# and the footprint-to-wall gaps of both walls
WALL_FEATURES = 14
PACKED_EXTENTS = 2  # the floor's half-extents, packed after the raw boundary points


def point_subset(num_points: int, k: int, device=None) -> torch.Tensor:
    """Indices of ``k`` points spread evenly over ``num_points`` boundary points (every
    num_points / k-th; points repeat when there are fewer than ``k``)."""
    return torch.arange(k, device=device) * num_points // k


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal embedding (B, dim) of (possibly fractional) timesteps."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = F.pad(emb, (0, 1))
    return emb


class SceneDenoiser(nn.Module):
    """eps_theta(x_t, t, floor): (B, N, 8 + K) -> (B, N, 8 + K)."""

    def __init__(self, config: DenoiserConfig, feature_dim: int):
        super().__init__()
        if feature_dim <= GEOMETRY_DIM:
            raise ValueError(f"feature_dim must exceed {GEOMETRY_DIM} (8 + K); got {feature_dim}")
        self.config = config
        self.feature_dim = feature_dim
        d = config.width
        k = feature_dim - GEOMETRY_DIM
        self.geometry_embed = nn.Sequential(nn.Linear(GEOMETRY_DIM, d), nn.GELU(), nn.Linear(d, d))
        self.class_embed = nn.Linear(k, d, bias=False)  # = learnable class embeddings weighted by the one-hot
        if config.slot_embedding:
            self.slot_embed = nn.Parameter(torch.randn(MAX_SLOTS, d) * 0.02)
        self.time_embed = nn.Sequential(nn.Linear(d, d), nn.SiLU(), nn.Linear(d, d))
        self.floor_encoder = PointNetEncoder(config.pointnet)
        g = config.pointnet[-1]
        self.floor_proj = nn.Linear(g, config.floor_tokens * d) if config.floor_tokens else None
        self.floor_point_proj = nn.Linear(config.pointnet[-2], d)
        self.floor_point_global = nn.Linear(g, d)
        self.floor_norm = nn.LayerNorm(d)
        self.floor_adaln = nn.Linear(g, d)
        self.wall_embed = nn.Sequential(nn.Linear(WALL_FEATURES, d), nn.GELU(), nn.Linear(d, d))
        # translation (lo x, lo z, hi x, hi z), then the same of the half sizes
        self.register_buffer("metric_bounds", torch.tensor([-1.0, -1.0, 1.0, 1.0] * 2), persistent=False)
        self.blocks = nn.ModuleList(DenoiserBlock(config) for _ in range(config.num_layers))
        self.final_norm = nn.LayerNorm(d, elementwise_affine=False, eps=1e-6)
        self.final_ada = nn.Sequential(nn.SiLU(), nn.Linear(d, 2 * d))
        self.out = nn.Linear(d, feature_dim)
        for lin in (self.final_ada[1], self.out):
            nn.init.zeros_(lin.weight)
            nn.init.zeros_(lin.bias)

    def _packed_floor_size(self) -> int:
        """Numbers of the raw floor packed at the end of the context: the (x, z, nx, nz) of the point
        subset, plus the floor's half-extents."""
        return 4 * self.config.floor_point_tokens + PACKED_EXTENTS

    def set_metric_scale(self, stats: DatasetStats) -> None:
        """Take the feature scaling of ``stats`` (translation and size bounds), with which the room-frame
        wall features measure footprint-to-wall gaps in metres. Not saved with the weights: the prior's
        statistics carry it (:class:`ScenePrior` sets it); until set, features are taken as metres."""
        self.metric_bounds.copy_(torch.tensor([stats.bounds_translations[i] for i in (0, 2, 3, 5)]
                                              + [stats.bounds_sizes[i] for i in (0, 2, 3, 5)]))

    def encode_floor(self, floor: torch.Tensor) -> torch.Tensor:
        """Floor condition (B, P, 4) -> context (B, 1 + floor_tokens + point tokens + packed rows, width): row 0
        is the floor's adaLN vector, then the cross-attention tokens, then the raw (x, z, nx, nz) of the point
        subset and the floor's half-extents, packed into rows of width d. Zeros = unconditional."""
        cfg = self.config
        b, p = floor.shape[:2]
        subset = point_subset(p, cfg.floor_point_tokens, floor.device)
        f, per_point = self.floor_encoder.encode(floor, subset)
        tokens = []
        if self.floor_proj is not None:
            tokens.append(self.floor_proj(f).view(b, cfg.floor_tokens, cfg.width))
        tokens.append(self.floor_point_proj(per_point) + self.floor_point_global(f)[:, None])
        ctx = torch.cat([self.floor_adaln(f)[:, None], self.floor_norm(torch.cat(tokens, 1))], 1)
        # the raw (x, z, nx, nz) of the subset and the half-extents of the scaled floor, over all its points
        # (centred floors), packed into rows of width d
        raw = torch.cat([floor[:, subset].reshape(b, -1), floor[..., :2].abs().amax(1)], 1)
        rows = -(-raw.shape[1] // cfg.width)
        return torch.cat([ctx, F.pad(raw, (0, rows * cfg.width - raw.shape[1])).view(b, rows, cfg.width)], 1)

    def wall_features(self, x: torch.Tensor, points: torch.Tensor, extents: torch.Tensor) -> torch.Tensor:
        """(B, N, WALL_FEATURES): each slot's (x, z) relative to the nearest boundary point q1 (offset, q1's
        inward normal, signed distance along it) and to the nearest point q2 whose normal differs from q1's by
        more than 60 degrees (another wall; q1 again when there is none), slots and points measured in the
        floor's bounding-box frame (its walls at +-1; ``extents`` (B, 2) are the scaled floor's half-extents);
        then the extents and, for q1 and q2, the gap in metres between the slot's oriented footprint and the
        wall (signed distance of the centre minus the footprint's half-extent along the normal)."""
        q, n = points[..., :2], points[..., 2:]
        centre, ext, u_x, u_z, half = self._slot_geometry(x, extents)
        p = centre / ext.clamp_min(1e-2)  # (an all-zero, unconditional floor has no extent)
        q = q / extents.clamp_min(1e-2)[:, None]
        d2 = (p[:, :, None] - q[:, None]).pow(2).sum(-1)  # (B, N, K)
        j1 = d2.argmin(-1)
        n1 = torch.gather(n, 1, j1[..., None].expand(-1, -1, 2))
        other = (n1[:, :, None] * n[:, None]).sum(-1) < 0.5
        j2 = torch.where(other.any(-1), d2.masked_fill(~other, float("inf")).argmin(-1), j1)
        feats = []
        for j in (j1, j2):
            qj = torch.gather(q, 1, j[..., None].expand(-1, -1, 2))
            nj = torch.gather(n, 1, j[..., None].expand(-1, -1, 2))
            off = p - qj
            feats += [off, nj, (off * nj).sum(-1, keepdim=True)]
        feats.append(extents[:, None].expand(-1, p.shape[1], -1))
        q_m = self._metres(points[..., :2], 0)
        gaps = []  # footprint-to-wall gaps in metres, for the same two walls
        for j in (j1, j2):
            qj = torch.gather(q_m, 1, j[..., None].expand(-1, -1, 2))
            nj = torch.gather(n, 1, j[..., None].expand(-1, -1, 2))
            reach = half[..., 0] * (nj * u_x).sum(-1).abs() + half[..., 1] * (nj * u_z).sum(-1).abs()
            gaps.append(((centre - qj) * nj).sum(-1) - reach)
        feats.append(torch.stack(gaps, -1).clamp(-2, 2))
        return torch.cat(feats, -1)

    def _metres(self, v: torch.Tensor, which: int) -> torch.Tensor:
        """Scaled (x, z) features -> metres: ``which`` 0 for translations, 1 for half sizes."""
        lo, hi = self.metric_bounds.view(2, 2, 2)[which]
        return (v.clamp(-1, 1) + 1) / 2 * (hi - lo) + lo

    def _slot_geometry(self, x: torch.Tensor, extents: torch.Tensor):
        """Metric geometry of noisy room-frame slots (see :func:`iarcs_env.scene.translation_scale`): centre
        (B, N, 2), the floor's half-extents (B, 1, 2), the object's local x and z axes in (x, z), half size."""
        ext = self._metres(extents, 0)[:, None]
        half = self._metres(x[..., 3:6:2], 1).clamp_min(0)
        yaw = F.normalize(x[..., 6:8], dim=-1, eps=1e-3)  # (cos, sin)
        free = (ext - footprint_reach(half, yaw[..., 0], yaw[..., 1])).clamp_min(MIN_FREE_RANGE)
        centre = x[..., 0:3:2].clamp(-1, 1) * free
        u_x = torch.stack([yaw[..., 0], -yaw[..., 1]], -1)
        u_z = torch.stack([yaw[..., 1], yaw[..., 0]], -1)
        return centre, ext, u_x, u_z, half

    def forward(self, x: torch.Tensor, t: torch.Tensor, floor: torch.Tensor | None = None,
                floor_context: torch.Tensor | None = None) -> torch.Tensor:
        """``x`` (B, N, 8+K) noisy features, ``t`` (B,) or scalar timesteps, and either ``floor`` (B, P, 4)
        or precomputed ``floor_context`` from :meth:`encode_floor` (reuse it across the steps of a
        rollout). ``floor=None`` and no context means unconditional (an all-zero floor)."""
        b = x.shape[0]
        t = torch.as_tensor(t, device=x.device)
        if t.ndim == 0:
            t = t.expand(b)
        if floor_context is None:
            if floor is None:  # an all-zero floor (every subset of its points is the same)
                floor = x.new_zeros(b, 1, 4)
            floor_context = self.encode_floor(floor)
        h = self.geometry_embed(x[..., :GEOMETRY_DIM]) + self.class_embed(x[..., GEOMETRY_DIM:])
        if self.config.slot_embedding:
            if x.shape[1] > MAX_SLOTS:
                raise ValueError(f"slot_embedding has {MAX_SLOTS} slots; got {x.shape[1]}")
            h = h + self.slot_embed[:x.shape[1]]
        temb = self.time_embed(timestep_embedding(t, self.config.width)) + floor_context[:, 0]
        k = self.config.floor_point_tokens
        rows = -(-self._packed_floor_size() // self.config.width)
        raw = floor_context[:, -rows:].reshape(b, -1)
        points = raw[:, :4 * k].view(b, k, 4)
        extents = raw[:, 4 * k:4 * k + PACKED_EXTENTS]
        floor_context = floor_context[:, 1:-rows]
        h = h + self.wall_embed(self.wall_features(x, points, extents))
        for block in self.blocks:
            h = block(h, temb, floor_context)
        shift, scale = self.final_ada(temb).chunk(2, dim=-1)
        return self.out(modulate(self.final_norm(h), shift, scale))

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def flops_per_scene(self, num_slots: int, num_points: int = 256, include_floor: bool = False) -> int:
        """Multiply-adds x 2 of one forward pass per scene (linear layers and attention products), without
        the floor encoder unless ``include_floor`` (a rollout encodes the floor once)."""
        c = self.config
        d, n, k = c.width, num_slots, self.feature_dim
        m = c.floor_tokens + min(c.floor_point_tokens, num_points)
        macs = n * (GEOMETRY_DIM * d + d * d + (k - GEOMETRY_DIM) * d)  # slot embedding
        macs += 2 * d * d  # time MLP
        per_block = (
            9 * d * d  # adaLN
            + 4 * n * d * d + 2 * n * n * d  # self-attention
            + 2 * n * d * d + 2 * m * d * d + 2 * n * m * d  # cross-attention (k/v over context tokens)
            + 2 * n * d * c.ff_dim  # feed-forward
        )
        macs += c.num_layers * per_block + 2 * d * d + n * d * k
        macs += n * (WALL_FEATURES * d + d * d)  # wall features
        if include_floor:
            w = list(c.pointnet)
            macs += num_points * sum(a * b for a, b in zip(w[:-2], w[1:-1])) + w[-2] * w[-1]
            macs += w[-1] * c.floor_tokens * d + min(c.floor_point_tokens, num_points) * (w[-2] + w[-1]) * d
            macs += w[-1] * d  # the floor's adaLN vector
        return 2 * macs


# --- the prior ------------------------------------------------------------------------------------------
def centre_floor(floor: FloorPlan) -> FloorPlan:
    """The floor moved so its bounding-box centre is the origin (the scene frame)."""
    c = floor.centre
    return floor if np.allclose(c, 0.0, atol=1e-9) else floor.translated(-c)


class ScenePrior:
    """Denoiser + noise schedule + dataset statistics + room type: a floor-conditioned scene sampler.

    ``sample(floors)`` returns a :class:`SceneBatch` (scene frame: floors centred on their bounding box).
    ``save(path)`` writes one ``.pt`` with configs, statistics and weights; ``load(path)`` reads it back;
    ``load_default(room)`` loads the prior shipped in ``agents/checkpoints``.
    """

    def __init__(self, denoiser: SceneDenoiser, stats: DatasetStats, schedule: NoiseSchedule | None = None,
                 meta: dict | None = None):
        self.denoiser = denoiser
        self.stats = stats
        self.spec: RoomSpec = get_room(stats.room_type)
        if denoiser.feature_dim != self.spec.feature_dim:
            raise ValueError(f"denoiser has {denoiser.feature_dim} features per slot but {self.spec.name} "
                             f"needs {self.spec.feature_dim}")
        if stats.translation_frame != "room":
            raise ValueError(f"the denoiser takes translations in the room frame but the statistics say "
                             f"{stats.translation_frame!r}: set DatasetStats.translation_frame to 'room' "
                             "(ScenePrior.create does this)")
        denoiser.set_metric_scale(stats)
        self.schedule = schedule or NoiseSchedule()
        self.meta = dict(meta or {})

    @classmethod
    def create(cls, room: str | RoomSpec, stats: DatasetStats, preset: str | DenoiserConfig = "small",
               schedule: NoiseSchedule | None = None, **overrides) -> "ScenePrior":
        """A new (untrained) prior; the statistics take the room frame (the denoiser's)."""
        spec = get_room(room)
        cfg = preset if isinstance(preset, DenoiserConfig) else DenoiserConfig.from_preset(preset, **overrides)
        stats = replace(stats, translation_frame="room")
        return cls(SceneDenoiser(cfg, spec.feature_dim), stats, schedule)

    @property
    def device(self) -> torch.device:
        return next(self.denoiser.parameters()).device

    @property
    def num_slots(self) -> int:
        return self.spec.max_objects

    def to(self, device) -> "ScenePrior":
        self.denoiser.to(device)
        return self

    # --- conditioning -------------------------------------------------------------------------------
    def floor_condition(self, floors: Sequence[FloorPlan]) -> torch.Tensor:
        """(B, 256, 4) floor features of (centred) floors, on the model's device."""
        return floor_features([centre_floor(f) for f in floors], self.stats).to(self.device)

    def model_fn(self, floor_cond: torch.Tensor, guidance_scale: float = 1.0, eps_fn=None):
        """``f(x_t, t) -> eps`` for a batch of floor conditions, the floor encoded once. ``eps_fn(x_t, t,
        floor_context=...)`` replaces the denoiser's own call (a policy that mixes adapted and prior features)."""
        net = self.denoiser
        call = eps_fn or net
        ctx = net.encode_floor(floor_cond)
        unc = net.encode_floor(torch.zeros_like(floor_cond)) if guidance_scale != 1.0 else None
        return guided_model_fn(lambda x, t, c: call(x, t, floor_context=c), ctx, guidance_scale, unc)

    # --- sampling ---------------------------------------------------------------------------------------
    def class_features(self, classes: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """The class part (B, N, K) of clean features: the one-hot of ``classes`` (B, N) mapped to +-1."""
        return 2 * F.one_hot(classes.to(like.device), self.spec.num_classes).to(like.dtype) - 1

    def with_clean_classes(self, x: torch.Tensor, classes: torch.Tensor) -> torch.Tensor:
        """Features ``x`` with their class part the clean one-hot (+-1) of ``classes`` (B, N)."""
        return torch.cat([x[..., :GEOMETRY_DIM], self.class_features(classes, x)], -1)

    def with_classes(self, x_t: torch.Tensor, t: torch.Tensor, classes: torch.Tensor,
                     generator: torch.Generator | None = None) -> torch.Tensor:
        """x_t with its class part given by ``classes`` (B, N) class indices (``empty_index``: an empty slot): their
        one-hot (+-1) as it is for a prior trained with ``PretrainConfig.classes_given``, else noised to t,
        q(x_t | classes) with fresh noise at every call (RePaint's rule for the known part of an image), so the
        network sees what it was trained on and samples the geometry of those classes
        (``iarcs_env.required_objects``)."""
        if self.meta.get("classes_given"):
            return self.with_clean_classes(x_t, classes)
        given = self.class_features(classes, x_t)
        given = self.schedule.q_sample(given, t, standard_normal(given.shape, generator, x_t.device, x_t.dtype))
        return torch.cat([x_t[..., :GEOMETRY_DIM], given], -1)

    @torch.no_grad()
    def sample_features(self, floors: Sequence[FloorPlan], num_steps: int = 20, eta: float = 1.0,
                        generator: torch.Generator | None = None, guidance_scale: float = 1.0,
                        return_trajectory: bool = False, eps_fn=None, classes: torch.Tensor | None = None):
        """DDIM rollout; returns x_0 (B, N, 8+K) (and the trajectory, see NoiseSchedule.sample). ``classes``
        (B, N) class indices: the network sees them as the class part of x_t at every step
        (:meth:`with_classes`), and x_0 has them (not with ``return_trajectory``)."""
        was_training = self.denoiser.training
        self.denoiser.eval()
        try:
            cond = self.floor_condition(floors)
            shape = (len(floors), self.num_slots, self.spec.feature_dim)
            x_T = standard_normal(shape, generator, self.device)
            if classes is not None and eps_fn is not None:  # a policy's: its slots given empty follow its reference
                given = classes.to(self.device).repeat(1 if guidance_scale == 1.0 else 2, 1)  # guidance: cond + uncond
                eps_fn = functools.partial(eps_fn, classes=given)
            fn = self.model_fn(cond, guidance_scale, eps_fn)
            if classes is None:
                return self.schedule.sample(fn, shape, num_steps=num_steps, eta=eta, generator=generator, x_T=x_T,
                                            return_trajectory=return_trajectory)
            if return_trajectory:
                raise ValueError("sampling with given classes returns no trajectory")
            x0 = self.schedule.sample(lambda x, t: fn(self.with_classes(x, t, classes, generator), t), shape,
                                      num_steps=num_steps, eta=eta, generator=generator, x_T=x_T)
            return self.with_clean_classes(x0, classes)
        finally:
            self.denoiser.train(was_training)

    def sample(self, floors: Sequence[FloorPlan], num_steps: int = 20, eta: float = 1.0,
               generator: torch.Generator | None = None, guidance_scale: float = 1.0,
               batch_size: int | None = None, ids: Sequence[str] | None = None, eps_fn=None,
               classes: torch.Tensor | None = None) -> SceneBatch:
        """Scenes for the given floor plans (any frame; returned centred). ``batch_size`` splits big requests
        into chunks run one after another (the random stream is then consumed chunk by chunk). ``eps_fn``: see
        :meth:`model_fn`; ``classes``: see :meth:`sample_features`."""
        floors = [centre_floor(f) for f in floors]
        if not floors:
            raise ValueError("sample needs at least one floor plan")
        bs = batch_size or len(floors)
        xs = [self.sample_features(floors[i:i + bs], num_steps, eta, generator, guidance_scale, eps_fn=eps_fn,
                                   classes=None if classes is None else classes[i:i + bs])
              for i in range(0, len(floors), bs)]
        x0 = torch.cat(xs).cpu()
        return SceneBatch.decode(x0, self.stats, floors, list(ids) if ids else
                                 [f"{self.spec.name}_{i:05d}" for i in range(len(floors))])

    # --- checkpoints --------------------------------------------------------------------------------------
    def state(self, half: bool = False) -> dict:
        """Checkpoint contents; ``half`` stores floating-point weights as float16 (loaded back as float32)."""
        weights = {k: v.detach().cpu().clone() for k, v in self.denoiser.state_dict().items()}
        if half:
            weights = {k: v.half() if v.is_floating_point() else v for k, v in weights.items()}
        return {
            "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "room_type": self.spec.name,
            "denoiser_config": asdict(self.denoiser.config), "feature_dim": self.denoiser.feature_dim,
            "schedule_config": asdict(self.schedule.config), "stats": self.stats.to_json(), "meta": self.meta,
            "state_dict": weights,
        }

    def save(self, path: str | Path, half: bool = False) -> Path:
        """Write the checkpoint atomically (a temporary file renamed into place); see :meth:`state`."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_torch_save(self.state(half), path)
        return path

    @classmethod
    def from_state(cls, state: dict, where: str = "checkpoint") -> "ScenePrior":
        if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"{where} is not an iARCS scene-prior checkpoint (no format {CHECKPOINT_FORMAT!r}); "
                             "a pretraining state (train_state.pt) is exported with agents.pretrain.export_prior")
        if state.get("version", 0) > CHECKPOINT_VERSION:
            raise ValueError(f"{where} has checkpoint version {state['version']}; this iARCS reads up to "
                             f"{CHECKPOINT_VERSION}: upgrade iARCS")
        known = {f.name for f in fields(DenoiserConfig)}
        saved = drop_retired_fields(state["denoiser_config"], where if where == "checkpoint" else f"checkpoint {where}")
        cfg = DenoiserConfig(**{k: v for k, v in saved.items() if k in known})
        stats = DatasetStats.from_json(state["stats"], state["room_type"])
        net = SceneDenoiser(cfg, int(state["feature_dim"]))
        try:
            net.load_state_dict(state["state_dict"])
        except RuntimeError as err:
            raise ValueError(f"{where}: its weights do not fit the denoiser its denoiser_config describes "
                             f"({cfg}); it was written by an incompatible version of iARCS: retrain it, or "
                             f"load it with the iARCS version that wrote it ({err})") from None
        net.eval()
        sched = NoiseSchedule(ScheduleConfig(**state.get("schedule_config", {})))
        return cls(net, stats, sched, state.get("meta"))

    @classmethod
    def load(cls, path: str | Path, map_location="cpu") -> "ScenePrior":
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"no scene-prior checkpoint at {path}")
        try:
            state = torch.load(path, map_location=map_location, weights_only=True)
        except Exception as err:  # noqa: BLE001 - report any unreadable file the same way
            raise ValueError(f"{path} is not a readable PyTorch checkpoint ({err})") from None
        return cls.from_state(state, str(path))

    @classmethod
    def default_path(cls, room: str = "bedroom") -> Path:
        return CHECKPOINT_DIR / f"{get_room(room).name}_small.pt"

    @classmethod
    def load_default(cls, room: str = "bedroom") -> "ScenePrior":
        """The small prior shipped with the package (``agents/checkpoints/<room>_small.pt``)."""
        path = cls.default_path(room)
        if not path.exists():
            shipped = sorted(p.stem.replace("_small", "") for p in CHECKPOINT_DIR.glob("*_small.pt"))
            raise FileNotFoundError(
                f"no shipped prior for {get_room(room).name} (shipped: {', '.join(shipped) or 'none'}); train one "
                f"with `iarcs pretrain --config experiments/pretrain_{get_room(room).name}.yaml` and pass its "
                "prior.pt as --checkpoint")
        return cls.load(path)


def atomic_torch_save(obj, path: str | Path) -> None:
    """torch.save to a temporary file in the same folder, then rename over ``path`` (never half-written)."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")  # created with the usual permissions (umask)
    try:
        torch.save(obj, tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


__all__ = ["Attention", "DenoiserConfig", "PRESETS", "PointNetEncoder", "RETIRED_FIELDS", "SceneDenoiser",
           "ScenePrior", "atomic_torch_save", "drop_retired_fields", "timestep_embedding"]
