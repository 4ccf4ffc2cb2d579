"""The auxiliary pretraining losses on the predicted clean layout x0_hat (``overlap_weight``,
``out_of_bound_weight`` of :class:`agents.pretrain.PretrainConfig`), each per scene and only below its noise level."""

from __future__ import annotations

import math
from typing import Callable

import torch

from iarcs_env.geometry import bounds_overlaps, bounds_separations
from iarcs_env.scene import box_corners_xz, decode_geometry
from iarcs_env.schedule import NoiseSchedule
from iarcs_env.stats import DatasetStats


def on_rows(mask: torch.Tensor, per_scene: Callable[..., torch.Tensor], *scenes: torch.Tensor) -> torch.Tensor:
    """``per_scene(*scenes)`` (one value per scene, a batch in each tensor) where ``mask`` is true, 0 elsewhere.
    On the CPU only the masked scenes are computed (the x0-hat losses apply to a few noise levels); on a GPU
    all are, times the mask, since selecting rows would make the host wait for the mask."""
    if mask.device.type != "cpu":
        return per_scene(*scenes) * mask
    rows = mask.nonzero().squeeze(1)
    values = per_scene(*(x[rows] for x in scenes)) if len(rows) else scenes[0].new_zeros(0)
    return scenes[0].new_zeros(mask.shape).index_put((rows,), values.to(scenes[0].dtype))


def excess_overlap_volume(placed: torch.Tensor, data: torch.Tensor) -> torch.Tensor:
    """(B, N, N) relu(A(placed) - A(data)) * H(data) from two :func:`bounds_overlaps` results: each pair's footprint
    overlap area beyond the data's, times the pair's vertical overlap in the data (m^3)."""
    return (placed[..., 0] * placed[..., 2] - data[..., 0] * data[..., 2]).clamp_min(0) * data[..., 1]


def overlap_excess(spec, stats: DatasetStats, extents: torch.Tensor, weight: float = 1.0,
                   max_timestep: int = NoiseSchedule().num_train_timesteps, spare_contact: bool = False,
                   contact_gap: float = 0.0, contact_volume: float = math.inf) -> Callable:
    """The ``x0_penalty`` of :meth:`NoiseSchedule.training_loss` for ``overlap_weight``: per scene with
    t < ``max_timestep``, ``weight`` times the sum over pairs of objects (non-empty slots of x0) of
    relu(A(x0_hat) - A(x0)) * H(x0): A the overlap area of the two footprints' axis-aligned bounds (exact
    for the axis-aligned furniture of the data), H the pair's vertical overlap in the data; 0 for the other
    scenes. The footprints of x0_hat are the data's (sizes and yaws) at x0_hat's floor positions: the loss is
    the overlap volume beyond the data's and moves objects apart on the floor, it cannot be lowered by
    shrinking, turning or lifting them (a lamp above a bed costs nothing). ``spare_contact``: only the pairs
    whose footprints do not overlap in the data are charged; the data's contact (a chair under its table) is left
    to the DDPM loss. ``contact_gap`` (m): pairs whose footprints' bounds come closer than this in the data count
    as contact too (a chair drawn up to its table edge): charged, x0_hat's errors into the table would cost and its
    errors away from it not, so the loss would stand the data's chairs off their tables (docs/design.md).
    ``contact_volume`` (m^3): the spared pairs are charged their excess beyond this volume (inf: nothing)."""

    def overlaps(x, extents):  # (B, N, N, 3) overlap lengths of each pair of boxes' bounds along x, y and z
        return bounds_overlaps(*decode_geometry(x, stats, extents))

    def per_scene(x0_hat, x0, extents):
        objects = x0[..., 8:].argmax(-1) != spec.empty_index
        pairs = (objects[:, :, None] & objects[:, None]).triu(1)
        placed = overlaps(torch.cat([x0_hat[..., :3], x0[..., 3:]], -1), extents)  # predicted positions, data's boxes
        separations = bounds_separations(*decode_geometry(x0, stats, extents))
        excess = excess_overlap_volume(placed, separations.clamp_min(0)) * pairs
        if spare_contact:
            contact = separations[..., 0:3:2].amin(-1) > -contact_gap
            excess = torch.where(contact, (excess - contact_volume).clamp_min(0), excess)
        return excess.flatten(1).sum(1)

    return lambda x0_hat, x0, t: weight * on_rows(t < max_timestep, per_scene, x0_hat, x0, extents)


def out_of_bound_excess(spec, stats: DatasetStats, extents: torch.Tensor, points: torch.Tensor,
                        weight: float = 1.0, max_timestep: int = NoiseSchedule().num_train_timesteps) -> Callable:
    """The ``x0_penalty`` of :meth:`NoiseSchedule.training_loss` for ``out_of_bound_weight``: per scene with
    t < ``max_timestep``, ``weight`` times the sum over the objects (non-empty slots of x0) and the 4 corners
    of their footprints of relu(b(x0_hat) - b(x0)), with b a corner's distance (m) behind the wall nearest to
    it: relu(-(c - p) . n) for the floor's boundary point p nearest to the corner c and that point's inward
    normal n (``points`` (B, P, 4): x, z, nx, nz in metres; the batch carries these, not the polygons). The
    footprints of x0_hat are the data's at x0_hat's floor positions, as in :func:`overlap_excess`; the data's
    own overhangs cost nothing."""

    def behind(x, extents, points):  # (B, N, 4) metres behind the nearest wall, per footprint corner
        trans, half, yaws = decode_geometry(x, stats, extents)
        corners = box_corners_xz(trans[..., 0:3:2], half[..., 0:3:2], yaws)[..., None, :]  # (B, N, 4, 1, 2)
        offset = corners - points[:, None, None, :, :2]  # (B, N, 4, P, 2)
        nearest = offset.square().sum(-1).argmin(-1, keepdim=True)
        along_normal = (offset * points[:, None, None, :, 2:]).sum(-1).gather(-1, nearest).squeeze(-1)
        return (-along_normal).clamp_min(0)

    def per_scene(x0_hat, x0, extents, points):
        objects = x0[..., 8:].argmax(-1) != spec.empty_index
        placed = behind(torch.cat([x0_hat[..., :3], x0[..., 3:]], -1), extents, points)
        excess = (placed - behind(x0, extents, points)).clamp_min(0).sum(-1) * objects
        return excess.sum(1)

    return lambda x0_hat, x0, t: weight * on_rows(t < max_timestep, per_scene, x0_hat, x0, extents, points)
