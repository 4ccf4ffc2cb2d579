"""Scenes: one room as a :class:`Layout` (NumPy, for files), a batch as a :class:`SceneBatch` (torch,
for the model and the rewards), and the model features of MiDiffusion.

Conventions (ATISS / ThreedFront): y is up, the floor is the x-z plane, ``yaw`` rotates about +y with
``R_y = [[c, 0, s], [0, 1, 0], [-s, 0, c]]``, ``half_sizes`` are half extents along the object's own
axes, and in a :class:`SceneBatch` translations are relative to the floor plan's bounding-box centre.

Model features per slot (8 + K numbers): translation (3) and half size (3) scaled to [-1, 1],
``[cos(yaw), sin(yaw)]``, and the class one-hot over ``classes + [empty]`` mapped to {-1, +1}. Unused
slots are class ``empty`` with geometry 0 in scaled space. Sizes and the height use the dataset bounds;
the floor-plane translations (x, z) use, in the default ``"room"`` frame of :class:`DatasetStats`, each
object's free half-range in its floor's bounding box (+-1 = the footprint touches a wall; see
:func:`translation_scale`), or the dataset bounds in the ``"dataset"`` frame of ATISS / MiDiffusion.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from .floorplan import FloorPlan, rotate_xz
from .rooms import RoomSpec, get_room

if TYPE_CHECKING:
    from .stats import DatasetStats


def wrap_angle(a):
    """Wrap angles to [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


@dataclass
class Layout:
    """One room: its floor polygon and objects, in one metric frame (not necessarily centred)."""

    room_type: str
    floor: FloorPlan
    labels: list[str]
    translations: np.ndarray  # (n, 3) box centres
    half_sizes: np.ndarray  # (n, 3)
    yaws: np.ndarray  # (n,)
    id: str = ""
    ceiling_height: float = 2.6
    extras: list[dict] = field(default_factory=list)  # per-object fields kept from the source (jid, ...)

    def __post_init__(self):
        n = len(self.labels)
        self.translations = np.asarray(self.translations, dtype=np.float64).reshape(n, 3)
        self.half_sizes = np.asarray(self.half_sizes, dtype=np.float64).reshape(n, 3)
        self.yaws = np.asarray(self.yaws, dtype=np.float64).reshape(n)
        if not self.extras:
            self.extras = [{} for _ in range(n)]

    def __len__(self) -> int:
        return len(self.labels)

    @property
    def spec(self) -> RoomSpec:
        return get_room(self.room_type)

    def centred(self) -> "Layout":
        """The same room moved so that the floor's bounding-box centre is the origin."""
        c = self.floor.centre
        t = self.translations.copy()
        t[:, 0] -= c[0]
        t[:, 2] -= c[1]
        return replace(self, floor=self.floor.translated(-c), translations=t)

    def rotated(self, yaw: float) -> "Layout":
        """The room rotated about the origin by ``yaw`` about +y (floor, positions and orientations)."""
        t = self.translations.copy()
        t[:, [0, 2]] = rotate_xz(t[:, [0, 2]], yaw)
        return replace(self, floor=self.floor.rotated(yaw), translations=t, yaws=wrap_angle(self.yaws + yaw))

    def footprints(self) -> np.ndarray:
        """Footprint corners ``(n, 4, 2)`` in (x, z)."""
        return box_corners_xz(self.translations[:, [0, 2]], self.half_sizes[:, [0, 2]], self.yaws)


def box_corners_xz(centres, half_xz, yaw):
    """Footprint corners of oriented boxes, ``(..., 4, 2)``, counter-clockwise in (x, z).

    A corner at local (lx, lz) lands at ``(x + c*lx + s*lz, z - s*lx + c*lz)``. Works on NumPy arrays
    and on torch tensors.
    """
    lib = torch if isinstance(centres, torch.Tensor) else np
    signs = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
    lx = lib.stack([half_xz[..., 0] * a for a, _ in signs], -1)
    lz = lib.stack([half_xz[..., 1] * b for _, b in signs], -1)
    c, s = lib.cos(yaw)[..., None], lib.sin(yaw)[..., None]
    x = centres[..., 0:1] + c * lx + s * lz
    z = centres[..., 1:2] - s * lx + c * lz
    return lib.stack([x, z], -1)


@dataclass
class SceneBatch:
    """B scenes of N object slots as tensors; ``labels == spec.empty_index`` marks unused slots.

    Translations are relative to each floor plan's bounding-box centre; ``floors`` are the floor plans
    in that same centred frame.
    """

    spec: RoomSpec
    labels: torch.Tensor  # (B, N) long
    translations: torch.Tensor  # (B, N, 3)
    half_sizes: torch.Tensor  # (B, N, 3)
    yaws: torch.Tensor  # (B, N)
    floors: list[FloorPlan]
    ids: list[str] = field(default_factory=list)

    @property
    def mask(self) -> torch.Tensor:
        """(B, N) True for slots holding an object."""
        return self.labels != self.spec.empty_index

    @property
    def ground_mask(self) -> torch.Tensor:
        """(B, N) True for ground objects (all but ceiling and pendant lamps, and empty slots)."""
        ground = torch.tensor(self.spec.ground_mask(), dtype=torch.bool, device=self.labels.device)
        return ground[self.labels]

    @property
    def batch_size(self) -> int:
        return self.labels.shape[0]

    @property
    def num_slots(self) -> int:
        return self.labels.shape[1]

    def __len__(self) -> int:
        return self.batch_size

    def footprints(self) -> torch.Tensor:
        """(B, N, 4, 2) footprint corners in (x, z)."""
        return box_corners_xz(self.translations[..., 0:3:2], self.half_sizes[..., 0:3:2], self.yaws)

    def __getitem__(self, index) -> "SceneBatch":
        """Scenes ``index`` (a slice, a sequence of indices or a boolean mask) as a new batch."""
        rows = np.arange(self.batch_size)[np.asarray(index) if not isinstance(index, slice) else index]
        rows = np.atleast_1d(rows)
        idx = torch.as_tensor(rows, dtype=torch.long)
        return SceneBatch(self.spec, self.labels[idx], self.translations[idx], self.half_sizes[idx], self.yaws[idx],
                          [self.floors[i] for i in rows], [self.ids[i] for i in rows] if self.ids else [])

    # --- conversion to and from files -----------------------------------------------------------------
    @classmethod
    def from_layouts(cls, layouts: Sequence[Layout], spec: RoomSpec | str | None = None,
                     num_slots: int | None = None) -> "SceneBatch":
        """Stack layouts (centring each on its floor plan). ``num_slots`` defaults to the largest room;
        a room with more objects than ``num_slots`` raises (filter or raise ``num_slots`` first)."""
        if not layouts:
            raise ValueError("cannot build a scene batch from no layouts")
        spec = get_room(spec or layouts[0].room_type)
        n = num_slots if num_slots is not None else max(1, max(len(l) for l in layouts))
        b = len(layouts)
        labels = np.full((b, n), spec.empty_index, dtype=np.int64)
        trans = np.zeros((b, n, 3))
        half = np.zeros((b, n, 3))
        yaws = np.zeros((b, n))
        floors = []
        for i, lay in enumerate(layouts):
            if len(lay) > n:
                raise ValueError(
                    f"scene {lay.id or i} has {len(lay)} objects but the batch has {n} slots; "
                    f"drop rooms with more than {n} objects or raise num_slots"
                )
            c = lay.centred()
            k = len(c)
            labels[i, :k] = [spec.class_index(lbl) for lbl in c.labels]
            trans[i, :k], half[i, :k], yaws[i, :k] = c.translations, c.half_sizes, c.yaws
            floors.append(c.floor)
        f = torch.float32
        return cls(spec, torch.from_numpy(labels), torch.tensor(trans, dtype=f), torch.tensor(half, dtype=f),
                   torch.tensor(yaws, dtype=f), floors, [l.id for l in layouts])

    def to_layouts(self) -> list[Layout]:
        """One :class:`Layout` per scene (centred frame), empty slots dropped."""
        out = []
        labels = self.labels.cpu().numpy()
        trans = self.translations.detach().cpu().double().numpy()
        half = self.half_sizes.detach().cpu().double().numpy()
        yaws = self.yaws.detach().cpu().double().numpy()
        for i in range(self.batch_size):
            keep = labels[i] != self.spec.empty_index
            out.append(Layout(
                self.spec.name, self.floors[i], [self.spec.vocabulary[j] for j in labels[i][keep]],
                trans[i][keep], half[i][keep], wrap_angle(yaws[i][keep]),
                id=self.ids[i] if self.ids else f"scene_{i:05d}",
            ))
        return out

    # --- model features --------------------------------------------------------------------------------
    def encode(self, stats: "DatasetStats", extents: torch.Tensor | None = None) -> torch.Tensor:
        """Model features ``x_0`` of shape (B, N, 8 + K); geometry is clipped to [-1, 1]. ``extents`` (B, 2)
        are the floors' half-extents (default: from ``floors``; see :func:`floor_half_extents`)."""
        if extents is None and stats.translation_frame == "room" and len(self.floors) == self.batch_size:
            extents = floor_half_extents(self.floors)
        t_lo, t_hi = translation_scale(stats, self.translations, extents, self.half_sizes, self.yaws)
        s_lo, s_hi = stats.size_bounds(self.half_sizes)
        t = (2 * (self.translations - t_lo) / (t_hi - t_lo) - 1).clamp(-1, 1)
        s = (2 * (self.half_sizes - s_lo) / (s_hi - s_lo) - 1).clamp(-1, 1)
        ang = torch.stack([torch.cos(self.yaws), torch.sin(self.yaws)], -1)
        onehot = 2 * torch.nn.functional.one_hot(self.labels, self.spec.num_classes).to(t.dtype) - 1
        geom = torch.cat([t, s, ang], -1) * self.mask[..., None]
        return torch.cat([geom, onehot], -1)

    @classmethod
    def decode(cls, x: torch.Tensor, stats: "DatasetStats", floors: list[FloorPlan],
               ids: list[str] | None = None, keep_graph: bool = False) -> "SceneBatch":
        """Scene batch from model features (B, N, 8 + K): class by arg-max, geometry de-scaled; with
        ``keep_graph`` the geometry stays differentiable in ``x`` (a reward's gradient chained to the model)."""
        spec = get_room(stats.room_type)
        if x.shape[-1] != spec.feature_dim:
            raise ValueError(f"{spec.name} features have {spec.feature_dim} numbers per slot; got {x.shape[-1]}")
        if len(floors) != x.shape[0]:
            raise ValueError(f"decoding {x.shape[0]} scenes needs as many floor plans; got {len(floors)}")
        x = x.float() if keep_graph else x.detach().float()
        extents = floor_half_extents(floors) if stats.translation_frame == "room" else None
        trans, half, yaws = decode_geometry(x, stats, extents)
        labels = x[..., 8:].argmax(-1)
        empty = labels == spec.empty_index
        trans, half, yaws = trans.masked_fill(empty[..., None], 0), half.masked_fill(empty[..., None], 0), yaws.masked_fill(empty, 0)
        return cls(spec, labels, trans, half, yaws, list(floors), list(ids or []))


def decode_geometry(x: torch.Tensor, stats: "DatasetStats", extents: torch.Tensor | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(translations, half sizes, yaws) in metres of model features ``x`` (B, N, 8 + K), differentiable
    where the scaled geometry lies in [-1, 1]; ``extents`` as for :func:`translation_scale`."""
    s_lo, s_hi = stats.size_bounds(x)
    g = x[..., :6].clamp(-1, 1)
    half = ((g[..., 3:6] + 1) / 2 * (s_hi - s_lo) + s_lo).clamp_min(1e-3)
    yaws = torch.atan2(x[..., 7], x[..., 6])
    t_lo, t_hi = translation_scale(stats, x, extents, half, yaws)  # room frame: needs the footprint
    trans = (g[..., 0:3] + 1) / 2 * (t_hi - t_lo) + t_lo
    return trans, half, yaws


def floor_half_extents(floors: Sequence[FloorPlan]) -> torch.Tensor:
    """(B, 2) half width (x) and half depth (z) of each floor's bounding box, in metres (a floor centred on
    its bounding box spans [-e, e] on each axis): the ``extents`` of :func:`translation_scale`."""
    b = np.array([f.bounds for f in floors], dtype=np.float64).reshape(-1, 4)
    return torch.tensor(np.maximum((b[:, 2:] - b[:, :2]) / 2, 1e-3), dtype=torch.float32)


#: The smallest free half-range (metres) of the room frame, for objects as wide as the room or wider.
MIN_FREE_RANGE = 0.05


def footprint_reach(half_xz: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """(..., 2) half-extents along x and z of footprints with half sizes ``half_xz`` (..., 2) turned by the
    yaw of (cos, sin): ``|c| hx + |s| hz`` and ``|s| hx + |c| hz`` (the axis-aligned box of the footprint)."""
    c, s = cos.abs(), sin.abs()
    return torch.stack([c * half_xz[..., 0] + s * half_xz[..., 1], s * half_xz[..., 0] + c * half_xz[..., 1]], -1)


def translation_scale(stats: "DatasetStats", like: torch.Tensor, extents: torch.Tensor | None = None,
                      half_sizes: torch.Tensor | None = None, yaws: torch.Tensor | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """(lo, hi) that map translations linearly onto [-1, 1]: the dataset bounds (3,), or in the ``"room"``
    frame per-object bounds (B, N, 3) whose x and z are -+ the free half-range ``e - r`` of the object's
    centre in its floor's bounding box: ``e`` the floor's half-extent (``extents`` (B, 2)), ``r`` the
    footprint's half-extent along that axis (:func:`footprint_reach` of ``half_sizes`` and ``yaws``), at
    least :data:`MIN_FREE_RANGE`. So +-1 is an object touching a wall of the bounding box."""
    lo, hi = stats.translation_bounds(like)
    if stats.translation_frame == "dataset":
        return lo, hi
    if extents is None:
        raise ValueError("room-frame features need the floors' half-extents: build the SceneBatch with its "
                         "floor plans, or pass extents=floor_half_extents(floors)")
    e = extents.to(device=like.device, dtype=like.dtype)[:, None]  # (B, 1, 2)
    free = (e - footprint_reach(half_sizes[..., 0:3:2], torch.cos(yaws), torch.sin(yaws))).clamp_min(MIN_FREE_RANGE)
    lo = torch.stack([-free[..., 0], lo[1].expand(free.shape[:-1]), -free[..., 1]], -1)
    hi = torch.stack([free[..., 0], hi[1].expand(free.shape[:-1]), free[..., 1]], -1)
    return lo, hi


def floor_features(floors: Sequence[FloorPlan], stats: "DatasetStats", n_points: int = 256) -> torch.Tensor:
    """Floor condition (B, n_points, 4) of centred floors: boundary points and their unit inward normals,
    see :func:`scale_floor_points`."""
    pts = torch.tensor(np.stack([f.boundary_points(n_points) for f in floors]), dtype=torch.float32)
    return scale_floor_points(pts, stats)


def scale_floor_points(pts: torch.Tensor, stats: "DatasetStats") -> torch.Tensor:
    """Metric boundary points (B, P, 4) as (x, z, nx, nz) -> floor condition: (x, z) scaled with the
    dataset's translation bounds in either translation frame (so the condition carries the room's size),
    normals unchanged."""
    lo, hi = stats.translation_bounds(pts)
    xz_lo, xz_hi = lo[0:3:2], hi[0:3:2]  # slices, not a list index: no host-to-device copy on CUDA
    xz = 2 * (pts[..., :2] - xz_lo) / (xz_hi - xz_lo) - 1
    return torch.cat([xz, pts[..., 2:]], -1)
