"""The floor encoder's PointNet (iARCS appendix A: per-point MLP 4 -> 64 -> 64 -> 512, max-pool, 512 -> 64) and
:class:`PointMaxPool`, its widest layer and max-pool as one autograd function that never stores the
(B, P, F) activation."""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn


class PointMaxPool(torch.autograd.Function):
    """relu(h W^T + b) for every point, max-pooled over the points, and the same features at the points
    ``subset``: PointNet's widest layer without its (B, P, F) activation. The forward pass computes it a few
    rooms at a time; the backward pass uses that a max-pool's gradient reaches one point per room and
    feature, so the (B, P, F) gradient and its two large matrix products are never formed. The values and
    gradients are those of the plain layers (``tests/test_denoiser.py``)."""

    CHUNK_ELEMENTS = 1 << 19  # activations per chunk on a CPU: 2 MB in float32, about one core's L2 cache
    GPU_CHUNK_ELEMENTS = 1 << 28  # on a GPU: large chunks (0.5 GB in bfloat16), few kernel launches

    @staticmethod
    def forward(ctx, h, weight, bias, subset):
        b, p, _ = h.shape
        w = weight.to(h.dtype)
        rows, f = PointMaxPool.rows_per_chunk(h, weight), weight.shape[0]
        pooled, sub = h.new_empty(b, f), h.new_empty(b, len(subset), f)
        arg = torch.empty(b, f, dtype=torch.long, device=h.device)
        for i in range(0, b, rows):
            # (rows, F, P), points last: the max runs along contiguous memory. The bias is the same at every
            # point: added after the max.
            z = torch.matmul(w, h[i:i + rows].transpose(1, 2))
            torch.max(z, dim=2, out=(pooled[i:i + rows], arg[i:i + rows]))
        torch.matmul(h[:, subset], w.t(), out=sub)
        c = bias.to(h.dtype)
        pooled.add_(c).relu_()
        sub.add_(c).relu_()
        ctx.save_for_backward(h, weight, subset, pooled, arg, sub)
        return pooled, sub

    @staticmethod
    def backward(ctx, g_pooled, g_sub):
        h, weight, subset, pooled, arg, sub = ctx.saved_tensors
        b, p, k = h.shape
        w = weight.to(h.dtype)
        # through the relu (its own backward kernel: one pass) to the arg-max points (B, F) and the subset (B, K, F)
        g_pooled = torch.ops.aten.threshold_backward(g_pooled, pooled, 0).to(h.dtype)
        g_sub = torch.ops.aten.threshold_backward(g_sub, sub, 0).to(h.dtype)
        g_weight = g_sub.reshape(-1, g_sub.shape[-1]).t() @ h[:, subset].reshape(-1, k)
        g_h = torch.zeros_like(h)
        rows = PointMaxPool.rows_per_chunk(h, weight)
        for i in range(0, b, rows):  # each feature's gradient goes to its arg-max point
            at = arg[i:i + rows, :, None].expand(-1, -1, k)
            g = g_pooled[i:i + rows, :, None]
            g_weight += (g * h[i:i + rows].gather(1, at)).sum(0)
            g_h[i:i + rows].scatter_add_(1, at, g * w)
        g_h.index_add_(1, subset, g_sub @ w)
        g_bias = g_pooled.sum(0) + g_sub.sum((0, 1))
        return g_h, g_weight.to(weight.dtype), g_bias.to(weight.dtype), None

    @staticmethod
    def rows_per_chunk(h: torch.Tensor, weight: torch.Tensor) -> int:
        size = PointMaxPool.CHUNK_ELEMENTS if h.device.type == "cpu" else PointMaxPool.GPU_CHUNK_ELEMENTS
        return max(1, size // (h.shape[1] * weight.shape[0]))


class PointNetEncoder(nn.Module):
    """PointNet over (B, P, 4) boundary points: per-point MLP (ReLU after every layer), max-pool, linear ->
    (B, widths[-1]). :meth:`encode` also returns the per-point features (widths[-2]) of a subset of points."""

    def __init__(self, widths: Sequence[int]):
        super().__init__()
        widths = list(widths)
        layers: list[nn.Module] = []
        for a, b in zip(widths[:-2], widths[1:-1]):
            layers += [nn.Linear(a, b), nn.ReLU()]
        self.point_mlp = nn.Sequential(*layers)
        self.head = nn.Linear(widths[-2], widths[-1])

    def encode(self, points: torch.Tensor, subset: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(global feature (B, widths[-1]), per-point features of the points ``subset`` (B, len(subset),
        widths[-2]))."""
        h = self.point_mlp[:-2](points)
        last = self.point_mlp[-2]
        pooled, per_point = PointMaxPool.apply(h, last.weight, last.bias, subset)
        return self.head(pooled), per_point

    def encode_reference(self, points: torch.Tensor, subset: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`encode` as plain layers, the (B, P, F) activation formed: what the fast path is tested against,
        and the model FLOPs of a training step are counted on (``benchmarks/bench_pretrain.py``)."""
        per_point = self.point_mlp(points)
        return self.head(per_point.max(dim=1).values), per_point[:, subset]

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.encode(points, points.new_zeros(0, dtype=torch.long))[0]
