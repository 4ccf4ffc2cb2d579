"""The scene API of reward programs (paper section 3.4): what ``def reward(scene)`` receives.

A reward program is Python source defining ``def reward(scene):`` that returns a float tensor of shape
``(B,)`` (one value per scene, higher is better, roughly in [0, 1] or [-1, 1]: it is added to the universal
rewards of that scale). It may ``import math`` and ``import torch`` (both are also pre-bound); everything
else it needs is on ``scene``, a batch of B scenes with N object slots.

Example (every support surface at most 1.0 m high, smoothly)::

    def reward(scene):
        support = scene.objects("support_surface")
        return scene.all_of(scene.below(scene.top_height, 1.0), support)

The geometry lives in :mod:`iarcs_env.relations` (shared with the hand-written task checkers); the methods
here are thin wrappers that add class-name selection and the documentation. :func:`api_reference` turns
the docstrings below into the prompt text, so the prompt and the code never disagree.
"""

from __future__ import annotations

import inspect
import textwrap

import torch

from iarcs_env import clearance
from iarcs_env import relations as rel
from iarcs_env.geometry import WALK_CELL, single_thread, wall_misalignment
from iarcs_env.rooms import get_room
from iarcs_env.scene import SceneBatch


class Scene:
    """A batch of B scenes with N object slots each, as tensors.

    Conventions: y is up and the floor is the x-z plane at y = 0; positions are metres in each room's
    frame. An object's front is its local +z axis: ``forward = (sin(yaw), cos(yaw))`` in (x, z); its left
    (seen from the object looking forward) is ``(cos(yaw), -sin(yaw))``. Object masks are (B, N) bool;
    pairwise tensors are (B, N, N) with [b, i, j] = relation of object j to object i. Values in empty slots
    are meaningless: combine tensors with masks (``objects``, ``pair_mask``, ``best_pair``, ``all_of``...).
    """

    def __init__(self, batch: SceneBatch):
        self._batch = batch
        self._cache: dict = {}

    def _cached(self, key, fn):
        if key not in self._cache:  # differentiable in the geometry when it requires grad (reward gradients)
            with single_thread():
                self._cache[key] = fn()
        value = self._cache[key]
        return value.clone() if isinstance(value, torch.Tensor) else value

    # --- the batch ---------------------------------------------------------------------------------------
    @property
    def batch_size(self) -> int:
        """B, the number of scenes."""
        return self._batch.batch_size

    @property
    def num_slots(self) -> int:
        """N, the number of object slots per scene."""
        return self._batch.num_slots

    @property
    def room(self) -> str:
        """Room type, e.g. ``"bedroom"``."""
        return self._batch.spec.name

    @property
    def classes(self) -> tuple:
        """Object class names of this room type."""
        return self._batch.spec.classes

    @property
    def present(self) -> torch.Tensor:
        """(B, N) bool: the slot holds an object."""
        return self._batch.mask.clone()

    def objects(self, *names: str) -> torch.Tensor:
        """(B, N) bool: objects of these classes or groups (any of them; no names: every object).

        Groups: GROUPS. Classes: CLASSES. A class absent from this room type gives all-False; an unknown
        name raises ValueError.
        """
        if not names:
            return self.present
        return rel.class_mask(self._batch.labels, self.classes, names)

    def count(self, *names: str) -> torch.Tensor:
        """(B,) float: number of objects of these classes or groups (no names: all objects)."""
        return self.objects(*names).float().sum(-1)

    # --- per-object geometry -----------------------------------------------------------------------------
    @property
    def position(self) -> torch.Tensor:
        """(B, N, 3) object centre (x, y, z) in metres; the floor is y = 0."""
        return self._batch.translations.clone()

    @property
    def size(self) -> torch.Tensor:
        """(B, N, 3) full extents along the object's own axes: (width x, height y, depth z)."""
        return 2 * self._batch.half_sizes

    @property
    def top_height(self) -> torch.Tensor:
        """(B, N) height of the object's top above the floor (centre y + half height)."""
        return self._batch.translations[..., 1] + self._batch.half_sizes[..., 1]

    @property
    def yaw(self) -> torch.Tensor:
        """(B, N) rotation about +y in radians."""
        return self._batch.yaws.clone()

    @property
    def forward(self) -> torch.Tensor:
        """(B, N, 2) unit facing direction (x, z) = (sin(yaw), cos(yaw))."""
        return rel.forward_xz(self._batch.yaws)

    @property
    def floor_area(self) -> torch.Tensor:
        """(B,) floor area of each room (m^2)."""
        return torch.tensor([f.area for f in self._batch.floors], dtype=self._batch.translations.dtype,
                            device=self._batch.labels.device)

    @property
    def middle_offset(self) -> torch.Tensor:
        """(B, N) distance (m) on the floor from the object's centre to the middle of the room (the centre of
        the floor's bounding box)."""
        return torch.linalg.vector_norm(self._batch.translations[..., 0:3:2], dim=-1)

    # --- pairwise relations ------------------------------------------------------------------------------
    def distance(self) -> torch.Tensor:
        """(B, N, N) centre-to-centre distance on the floor (m)."""
        return self._cached("distance", lambda: rel.centre_distance(self._batch.translations[..., 0:3:2]))

    def gap(self) -> torch.Tensor:
        """(B, N, N) shortest floor distance between the two footprints (m; 0 when they touch or overlap)."""
        b = self._batch
        return self._cached("gap", lambda: rel.footprint_gap(b.translations, b.half_sizes, b.yaws))

    def local_offset(self) -> torch.Tensor:
        """(B, N, N, 2) centre of j in i's frame: [..., 0] lateral (+ = i's left), [..., 1] forward (+ = in
        front of i), metres."""
        b = self._batch
        return self._cached("offset", lambda: rel.local_offset(b.translations[..., 0:3:2], b.yaws))

    def facing_angle(self) -> torch.Tensor:
        """(B, N, N) angle (rad, 0..pi) between i's forward and the direction from i to j (0: i faces j;
        this is also the viewing angle from i to j)."""
        b = self._batch
        return self._cached("facing", lambda: rel.facing_angle(b.translations[..., 0:3:2], b.yaws))

    # --- walls -------------------------------------------------------------------------------------------
    def _edges(self):
        return self._cached("edges", lambda: rel.floor_edges(self._batch.floors, self._batch.labels.device))

    def wall_distance(self) -> torch.Tensor:
        """(B, N) shortest distance from the footprint to the floor boundary (m; 0 when touching or outside)."""
        b = self._batch
        return self._cached("wall", lambda: rel.wall_distance(b.translations, b.half_sizes, b.yaws, self._edges())
                            .to(b.translations.dtype))

    def back_to_wall(self) -> torch.Tensor:
        """(B, N) distance from the midpoint of the object's back edge to the boundary straight behind it (m;
        about 0 for a bed whose headboard is against a wall; negative when the back pokes through the wall)."""
        b = self._batch
        return self._cached("back", lambda: rel.back_to_wall(b.translations, b.half_sizes, b.yaws, self._edges())
                            .to(b.translations.dtype))

    def wall_offset(self) -> torch.Tensor:
        """(B, N) distance (m) along the wall straight behind the object from that wall's middle to the object's
        centre (0: centred on the wall behind it; inf when no wall is behind it)."""
        b = self._batch
        return self._cached("wall_offset", lambda: rel.wall_offset(b.translations, b.yaws, b.half_sizes, self._edges())
                            .to(b.translations.dtype))

    def wall_angle(self) -> torch.Tensor:
        """(B, N) angle (rad, 0..pi/4) between the object's axes and the nearest wall direction of the floor
        (0: square to the walls; any multiple of 90 degrees counts, so a bed turned a quarter is square too)."""
        b = self._batch
        return self._cached("wall_angle", lambda: torch.deg2rad(wall_misalignment(b.yaws, b.floors, b.mask)))

    # --- free space --------------------------------------------------------------------------------------
    def _space(self, radius: float):
        b = self._batch
        return self._cached(("space", float(radius)), lambda: rel.free_grid(
            b.floors, b.translations, b.half_sizes, b.yaws, b.ground_mask, radius=float(radius), cell=WALK_CELL))

    def walkable(self, radius: float = 0.3) -> torch.Tensor:
        """(B,) R_walkable for an agent of this radius: largest connected free region / all free floor."""
        ratio = self._space(radius).walkable_ratio
        return torch.as_tensor(ratio, dtype=self._batch.translations.dtype, device=self._batch.labels.device)

    def reachable(self, radius: float = 0.3) -> torch.Tensor:
        """(B, N) bool: the ground object touches the largest free region for an agent of that radius (free
        paths 2 * radius wide reach it); False for ceiling lamps and empty slots."""
        return rel.reachable(self._space(radius), self._batch.ground_mask)

    def path_clearance(self, radius: float = 0.3) -> torch.Tensor:
        """(B, N) m: how wide the widest free path to the object is, as the clearance (distance to the nearest
        footprint or wall) at its narrowest point, from the largest free region for an agent of that radius;
        `reachable(radius)` is exactly `path_clearance(radius) >= radius`. Differentiable in the geometry (the
        objects narrowing the path move apart): `scene.above(scene.path_clearance(r), r)` rewards a path opening.
        -radius for ceiling lamps and empty slots."""
        b = self._batch
        return self._cached(("path_clearance", float(radius)), lambda: clearance.reach_clearance(
            b.floors, b.translations, b.half_sizes, b.yaws, b.ground_mask, float(radius), WALK_CELL))

    def circle_clearance(self, radius: float, near: torch.Tensor | None = None, within: float = 0.5,
                         middle: float | None = None) -> torch.Tensor:
        """(B,) m: the largest clearance (distance to the nearest ground footprint or wall) of a point where a
        disk of this radius may stand, its edge within `within` m of an object of mask `near` (anywhere when None)
        and, with `middle`, its centre at most `middle` m from the middle of the room; `free_circle` is exactly
        `circle_clearance(...) >= radius`. Differentiable in the geometry; -inf where no point qualifies."""
        b = self._batch
        key = ("circle_clearance", float(radius), None if near is None else near.cpu().numpy().tobytes(),
               float(within), middle)
        return self._cached(key, lambda: clearance.disk_clearance(
            b.floors, b.translations, b.half_sizes, b.yaws, b.ground_mask, near, float(radius) + float(within),
            middle, WALK_CELL))

    def free_circle(self, radius: float, near: torch.Tensor | None = None, within: float = 0.5,
                    middle: float | None = None) -> torch.Tensor:
        """(B,) bool: a disk of this radius fits on free floor (inside the floor, outside every ground
        footprint), with its edge within `within` m of an object of mask `near` (anywhere when near is None)
        and, when `middle` is given, its centre at most `middle` m from the middle of the room."""
        b = self._batch
        key = ("circle", float(radius), None if near is None else near.cpu().numpy().tobytes(), float(within),
               middle)
        return self._cached(key, lambda: rel.free_disk(self._space(radius), b.translations, b.half_sizes, b.yaws,
                                                       near, float(within), middle).to(b.labels.device))

    def free_share(self, depth: float, zone: str = "front") -> torch.Tensor:
        """(B, N) share (0..1) of the floor strip `depth` m wide beyond the object's edges that is free (inside
        the floor, outside every other ground footprint); zone "front", "back", "sides" (left and right) or
        "around" (all four edges)."""
        b = self._batch
        return self._cached(("share", float(depth), zone), lambda: rel.free_share(
            b.translations, b.half_sizes, b.yaws, b.ground_mask, self._edges(), float(depth), zone)
            .to(b.translations.dtype))

    # --- shaping helpers ---------------------------------------------------------------------------------
    @staticmethod
    def below(x: torch.Tensor, limit: float, scale: float = 0.1) -> torch.Tensor:
        """Soft x <= limit: 1 when x <= limit, exp(-(x - limit) / scale) above."""
        return torch.exp(-(x - limit).clamp_min(0) / scale)

    @staticmethod
    def above(x: torch.Tensor, limit: float, scale: float = 0.1) -> torch.Tensor:
        """Soft x >= limit: 1 when x >= limit, exp(-(limit - x) / scale) below."""
        return torch.exp(-(limit - x).clamp_min(0) / scale)

    @staticmethod
    def within(x: torch.Tensor, lo: float, hi: float, scale: float = 0.1) -> torch.Tensor:
        """Soft lo <= x <= hi: 1 inside, exp(-distance outside / scale) outside."""
        return torch.exp(-((lo - x).clamp_min(0) + (x - hi).clamp_min(0)) / scale)

    def pair_mask(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """(B, N, N) bool: i in mask a, j in mask b, i != j."""
        eye = torch.eye(self.num_slots, dtype=torch.bool, device=a.device)
        return a[:, :, None] & b[:, None, :] & ~eye

    def best_pair(self, score: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """(B,) max of score (B, N, N) over valid pairs (i in mask a, j in mask b, i != j); 0 when none."""
        m = self.pair_mask(a, b)
        best = score.float().masked_fill(~m, float("-inf")).flatten(1).amax(1)
        return torch.where(m.flatten(1).any(1), best, torch.zeros_like(best))

    @staticmethod
    def all_of(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(B,) min of values (B, N) over the masked objects; 1 when none."""
        v = values.float().masked_fill(~mask, float("inf")).amin(1)
        return torch.where(mask.any(1), v, torch.ones_like(v))

    @staticmethod
    def any_of(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(B,) max of values (B, N) over the masked objects; 0 when none."""
        v = values.float().masked_fill(~mask, float("-inf")).amax(1)
        return torch.where(mask.any(1), v, torch.zeros_like(v))

    @staticmethod
    def mean_of(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(B,) mean of values (B, N) over the masked objects; 0 when none."""
        m = mask.float()
        return (values.float() * m).sum(1) / m.sum(1).clamp_min(1)


def _first_paragraph(doc: str | None) -> str:
    """The first paragraph of a docstring on one line, reST double backticks made single."""
    para = inspect.cleandoc(doc or "").split("\n\n")[0]
    return " ".join(para.split()).replace("``", "`")


def _paragraphs(doc: str | None) -> list[str]:
    return [" ".join(p.split()).replace("``", "`") for p in inspect.cleandoc(doc or "").split("\n\n")]


def _groups_and_classes(text: str, room: str | None) -> str:
    """Fill the GROUPS / CLASSES placeholders of a docstring (``room``: list only its classes)."""
    def group(name, classes):
        if name == "ground":
            return "ground (every class but ceiling and pendant lamps)"
        if name == "any":
            return "any (every class)"
        return f"{name} ({', '.join(classes)})"

    classes = get_room(room).classes if room else rel.ALL_CLASSES
    groups = "; ".join(group(k, v) for k, v in rel.CLASS_GROUPS.items())
    return text.replace("GROUPS", groups).replace("CLASSES", ", ".join(classes))


def public_members() -> list[str]:
    """Names of the public members of :class:`Scene`, in definition order."""
    return [n for n in Scene.__dict__ if not n.startswith("_")]


def api_reference(room: str | None = None) -> str:
    """The scene API as prompt text: the reward-program contract, the conventions, then every public
    member of :class:`Scene` with its signature and the first paragraph of its docstring (the class list of
    ``room`` when given, else of every room type)."""
    intro = inspect.cleandoc(__doc__).split("\n\n")
    example = "```python\n" + textwrap.dedent(intro[3]).strip() + "\n```"  # code kept line by line
    lines = [_paragraphs(__doc__)[1], "", _paragraphs(__doc__)[2].rstrip(":") + ":", "", example, "",
             " ".join(_paragraphs(Scene.__doc__)), "", "Members of `scene`:"]
    for name in public_members():
        member = Scene.__dict__[name]
        if isinstance(member, property):
            head, doc = f"scene.{name}", member.fget.__doc__
        else:
            fn = member.__func__ if isinstance(member, staticmethod) else member
            params = [p.replace(annotation=inspect.Parameter.empty)
                      for p in inspect.signature(fn).parameters.values() if p.name != "self"]
            head, doc = f"scene.{name}({', '.join(map(str, params))})", fn.__doc__
        body = _first_paragraph(doc)
        if name == "objects":  # the groups and class names are part of its documentation
            body += " " + _groups_and_classes(_paragraphs(doc)[1], room)
        lines.append(f"- {head}: {body}")
    return "\n".join(lines)
