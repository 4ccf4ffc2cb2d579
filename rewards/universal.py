"""Universal rewards (iARCS appendix, Algorithms 1-4), batched: each is a function of a
:class:`~iarcs_env.scene.SceneBatch` returning one value per scene as a float32 tensor ``(B,)`` on the
batch's device. They are registered by name in :data:`REWARDS` (add your own with :func:`register_reward`).

* ``collision`` (Alg. 1): +1 when no two ground objects penetrate (3D box overlap > ``threshold`` m^3,
  the metric's 1e-6), otherwise minus the total penetration volume (m^3) of the penetrating pairs. With
  ``per_object`` (our addition, default 0) also minus that much per colliding ground object: a scene with
  one colliding pair scores better than one with three, which the scene-level bonus does not tell apart.
  With ``contact`` (our addition), ``{"pairs": [[a, b], ...], "volume": V}`` (classes or class groups such as
  ``bed``), an overlap of such a pair up to V m^3 is contact, not penetration: the data put a nightstand's box
  into its bed's (half the real nightstands, 62% of the procedural ones; at most 0.04 m^3 in the procedural
  rooms), so a reward that counts that overlap teaches stage 1 to pull the nightstands away from the bed.
* ``boundary`` (Alg. 2): +2 when no object's footprint (shrunk by ``shrink`` = 0.05 m per side, as the
  R_out metric) has more than ``threshold`` = 1e-5 m^2 outside the floor polygon, otherwise minus the total
  out-of-bound area (m^2) of those objects; with ``per_object`` also minus that much per such object.
* ``accessibility`` (Alg. 3): on an occupancy grid (``cell`` m, 0.1 by default for speed; the metrics use
  0.05) with ground objects inflated and the walls eroded by the agent radius (0.3 m),
  ``1.0 * coverage - 0.1 * regions + 0.5 * clearance`` where ``coverage`` = cells of the largest free
  4-connected region / free cells of the same room with no furniture (1 for an empty room), ``regions`` =
  number of free regions, ``clearance`` = mean distance (m) from a free cell to the nearest blocked cell
  (Euclidean distance transform). With ``per_object`` (our addition, default 0) also minus that much per ground
  object the agent cannot reach (the R_reach metric's count, on this grid).
* ``floor_contact`` (our addition): +``bonus`` (1) when every ground object's bottom is within ``tolerance``
  (0.05 m, the R_off_floor metric's) of the floor, otherwise minus the total distance (m) beyond it of those
  that are not, sunk or lifted. Without it an adapter that may change an object's elevation passes a height
  limit by sinking beds into the floor, and dodges collisions by lifting furniture.
* ``wall_alignment`` (our addition): +``bonus`` (1) when every ground object's axes are within ``tolerance``
  (10 degrees, the R_misaligned metric's) of a wall direction, otherwise minus the total angle (radians)
  beyond it of those that are not.
* ``object_count`` (Alg. 4): ``mode="kl"`` (default): minus KL(batch || training) between the batch's
  object-count histogram and the training set's (``DatasetStats.count_distribution``), both smoothed
  with ``eps``; the same value for every scene of the batch (it rewards the batch as a whole, which keeps
  the count distribution from collapsing). ``mode="log_prob"``: per scene, the training log-probability
  of the scene's object count (smoothed), which ranks scenes within a batch. ``mode="match"``: per scene,
  ``log(p_train(n) / p_batch(n))`` of its count n, the per-scene score of ``-KL(batch || training)`` (see
  below).
* ``class_presence`` (our addition to the object-count prior): per scene, the training log-likelihood of
  which classes it contains, sum_c [x_c log p_c + (1 - x_c) log(1 - p_c)], with x_c = 1 when the scene has
  an object of class c and p_c = ``DatasetStats.class_presence`` (clipped to [eps, 1 - eps]). The count
  term alone lets stage 1 drop the hardest object to place (the bed of a bedroom: 0.85 beds per room in
  the prior's samples, 0.18 after stage 1); this term makes a bedroom without a bed cost what it costs
  under the data. That log-likelihood is mode-seeking: it rewards every class present in fewer than half
  of the training rooms for being absent. ``mode="match"`` rewards matching the rates instead:
  sum_c [x_c log(p_c / q_c) + (1 - x_c) log((1 - p_c) / (1 - q_c))] with q_c the batch's own presence
  rate. Its batch mean is ``-KL(q || p)`` summed over the classes' Bernoullis, and (up to a constant per
  batch, which the per-floor advantage normalisation removes) it is the per-scene score whose policy
  gradient descends that KL: a class rarer in the batch than in the data pays for being present, a class
  rarer in the data pays for being absent, and every term is 0 once the batch has the training rates.
  ``mode="absence"`` keeps only the log-likelihood's price of a missing class, sum_c (1 - x_c) log(1 - p_c):
  a bedroom without a bed costs log(1 - 0.86) = -2.0, one without a TV stand log(1 - 0.19) = -0.2, and no
  class ever pays for being present, so the rare classes that the log-likelihood removes (TV stands, desks:
  the objects of the stage-2 tasks) are not pushed out.
  Presence alone leaves the number of objects of a class free: with ``object_count`` in ``"match"`` mode
  stage 1 filled rooms with pendant lamps (they never collide; 0.60 -> 1.30 per room).
* ``class_frequency`` (our addition): per scene, sum over its objects of log(f_c / g_c), f_c the share of
  class c among the training objects (``DatasetStats.class_frequencies``) and g_c its share among the
  batch's objects (both smoothed with ``eps``): the per-object score of ``-KL(batch || training)`` over
  object labels (the KL_class metric), 0 once the batch has the training shares.
* ``object_size`` (our addition): per scene, sum over its objects and their three axes of
  ``log N(log h; mu_c, sigma_c) - log N(log h; m_c, s_c)``: h an object's half-size, (mu_c, sigma_c) the
  mean and standard deviation of class c's log half-sizes in the training rooms
  (``DatasetStats.class_sizes``) and (m_c, s_c) those of the batch's own objects of class c: the
  per-object score of ``-KL(batch || training)`` of each class's size distribution, like
  ``class_frequency`` (deviations capped at 3 standard deviations), centred on its mean over the batch's
  objects of the class. The centring matters: uncentred, every object scores ``-KL`` on average, and stage 1
  halved the objects per room (3.9 -> 1.8) to score less of it. Without the term stage 1 shrinks furniture:
  smaller beds collide less and stick out of the room less (the shipped stage-1 adapter's double beds have
  14.5% less footprint than the prior's); with it at weight 0.3 the beds keep their size and R_out no longer
  falls (docs/results/stage1_bedroom_quick.md).

* ``required_class`` (our addition): 0 when the scene holds an object of ``classes`` (a group of
  ``iarcs_env.relations.CLASS_GROUPS`` such as ``"bed"``, or a list of classes), else -1. The content terms
  above price a bedroom without a bed at about log(1 - 0.8) = -1.6, while with ``per_object`` a bed touching
  two nightstands costs three colliding objects: stage 1 then removes the bed. This term lets a config
  make a missing bed cost more than any collision it avoids.

Ground objects are all but ceiling and pendant lamps; object counts include every non-empty slot.
The rewards run torch single-threaded (``iarcs_env.geometry.single_thread``): their tensors are small, and
intra-op threads only slow them down on a busy CPU.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from iarcs_env import geometry as geo
from iarcs_env.geometry import single_thread
from iarcs_env.walkable import free_space
from iarcs_env.relations import ALL_CLASSES, CLASS_GROUPS, class_mask
from iarcs_env.scene import SceneBatch
from iarcs_env.stats import DatasetStats

RewardFn = Callable[..., torch.Tensor]

#: name -> batched reward function ``f(batch, **options) -> (B,)``.
REWARDS: dict[str, RewardFn] = {}


def register_reward(name: str):
    """Decorator registering ``f(batch: SceneBatch, **options) -> Tensor (B,)`` under ``name``."""

    def wrap(fn: RewardFn) -> RewardFn:
        if name in REWARDS and REWARDS[name] is not fn:
            raise ValueError(f"a reward named {name!r} is already registered")
        REWARDS[name] = fn
        fn.reward_name = name
        return fn

    return wrap


def get_reward(name: str) -> RewardFn:
    try:
        return REWARDS[name]
    except KeyError:
        raise ValueError(f"unknown reward {name!r}; registered rewards: {', '.join(sorted(REWARDS))}") from None


def _out(values, batch: SceneBatch) -> torch.Tensor:
    return torch.as_tensor(values).to(device=batch.labels.device, dtype=torch.float32)


@register_reward("collision")
@single_thread()
def collision_reward(batch: SceneBatch, threshold: float = geo.COLLISION_VOLUME, bonus: float = 1.0,
                     per_object: float = 0.0, contact: dict | None = None) -> torch.Tensor:
    """+``bonus`` when no ground objects penetrate, else minus the total penetration volume (m^3); minus
    ``per_object`` for each colliding ground object (the Col_obj metric's count). ``contact``: class pairs
    whose overlap up to ``contact["volume"]`` m^3 does not count."""
    vol = geo.box_overlap_volumes(batch.translations, batch.half_sizes, batch.yaws, batch.ground_mask)
    penetrating = vol > threshold
    if contact:
        penetrating &= ~(contact_pairs(batch.labels, batch.mask, batch.spec, contact) & (vol <= contact["volume"]))
    total = (vol * penetrating).triu(1).sum((1, 2))
    reward = torch.where(penetrating.flatten(1).any(1), -total, torch.full_like(total, bonus))
    return _out(reward - per_object * penetrating.any(2).sum(1), batch)


def contact_pairs(labels: torch.Tensor, valid: torch.Tensor, spec, contact: dict) -> torch.Tensor:
    """(B, N, N) bool: the valid slots i, j whose classes (``labels``, of room type ``spec``) form one of
    ``contact["pairs"]`` (either order); ``contact`` is the collision reward's option (module doc)."""
    if set(contact) != {"pairs", "volume"}:
        raise ValueError(f"collision contact: expected {{pairs: [[a, b], ...], volume: m^3}}, got {contact!r}")
    return class_pairs(labels, valid, spec, contact["pairs"], "collision contact")


def class_pairs(labels: torch.Tensor, valid: torch.Tensor, spec, pairs, option: str) -> torch.Tensor:
    """(B, N, N) bool: the valid slots i, j whose classes form one of ``pairs`` (class names or groups, either
    order); ``option`` names the setting that lists them in the errors."""
    out = torch.zeros(labels.shape + labels.shape[-1:], dtype=torch.bool, device=labels.device)
    for pair in pairs:
        if len(pair) != 2:
            raise ValueError(f"{option}: each pair names two classes or class groups, got {pair!r}")
        a, b = (class_mask(labels, spec.classes, [name]) & valid for name in pair)  # unknown: raises
        for name in pair:
            if not set(CLASS_GROUPS.get(name, (name,))) & set(spec.classes):
                raise ValueError(f"{option}: {spec.name} rooms have no {name!r}; name classes or "
                                 f"groups of this room type ({', '.join(spec.classes)})")
        out |= (a[:, :, None] & b[:, None, :]) | (b[:, :, None] & a[:, None, :])
    return out


@register_reward("boundary")
@single_thread()
def boundary_reward(batch: SceneBatch, shrink: float = geo.OUT_OF_BOUND_SHRINK,
                    threshold: float = geo.OUT_OF_BOUND_AREA, bonus: float = 2.0,
                    ground_only: bool = False, per_object: float = 0.0) -> torch.Tensor:
    """+``bonus`` when every footprint stays on the floor, else minus the out-of-bound area (m^2); minus
    ``per_object`` for each object out of bound (the R_out metric's count)."""
    mask = batch.ground_mask if ground_only else batch.mask
    area = geo.box_out_of_floor_area(batch.translations, batch.half_sizes, batch.yaws, batch.floors, mask, shrink)
    outside = area > threshold
    total = (area * outside).sum(1)
    reward = torch.where(outside.any(1), -total, torch.full_like(total, bonus))
    return _out(reward - per_object * outside.sum(1), batch)


@register_reward("accessibility")
@single_thread()
def accessibility_reward(batch: SceneBatch, cell: float = 0.1, agent_radius: float = geo.AGENT_RADIUS,
                         w_coverage: float = 1.0, w_regions: float = 0.1, w_clearance: float = 0.5,
                         per_object: float = 0.0) -> torch.Tensor:
    """``w_coverage * coverage - w_regions * regions + w_clearance * clearance`` (see the module doc); minus
    ``per_object`` for each ground object the agent cannot reach (the R_reach metric's count, on this grid)."""
    space = free_space(batch.floors, batch.translations, batch.half_sizes, batch.yaws, batch.ground_mask,
                           cell=cell, radius=agent_radius, reach=per_object != 0, clearance=w_clearance != 0)
    coverage = np.where(space.floor_cells > 0, space.largest_cells / np.maximum(space.floor_cells, 1), 0.0)
    clearance = np.nan_to_num(space.clearance) if w_clearance else 0.0
    reward = w_coverage * coverage - w_regions * space.regions + w_clearance * clearance
    if per_object:
        unreachable = batch.ground_mask.cpu().numpy() & ~space.reach
        reward = reward - per_object * unreachable.sum(1)
    return _out(reward, batch)


@register_reward("floor_contact")
def floor_contact_reward(batch: SceneBatch, tolerance: float = geo.FLOOR_CONTACT_TOL,
                         bonus: float = 1.0) -> torch.Tensor:
    """+``bonus`` when every ground object stands on the floor, else minus the total gap beyond ``tolerance``."""
    excess = (geo.floor_gaps(batch.translations, batch.half_sizes, batch.ground_mask) - tolerance).clamp(min=0)
    total = excess.sum(1)
    return _out(torch.where(total > 0, -total, torch.full_like(total, bonus)), batch)


@register_reward("wall_alignment")
def wall_alignment_reward(batch: SceneBatch, tolerance: float = geo.ALIGNMENT_TOL_DEG,
                          bonus: float = 1.0) -> torch.Tensor:
    """+``bonus`` when every ground object is aligned with a wall, else minus the total angle beyond ``tolerance``
    (radians)."""
    excess = (geo.wall_misalignment(batch.yaws, batch.floors, batch.ground_mask) - tolerance).clamp(min=0)
    total = torch.deg2rad(excess).sum(1)
    return _out(torch.where(total > 0, -total, torch.full_like(total, bonus)), batch)


def _count_distribution(stats: DatasetStats | None, distribution, n: int) -> np.ndarray:
    if distribution is None:
        if stats is None:
            raise ValueError("the object_count reward needs the training set's statistics: pass stats=DatasetStats "
                             "(or count_distribution=[p0, p1, ...])")
        distribution = stats.count_distribution(max(n, len(stats.object_count_histogram) - 1))
    p = np.zeros(max(n + 1, len(distribution)))
    p[: len(distribution)] = np.asarray(distribution, dtype=np.float64)
    return p / max(p.sum(), 1e-12)


@register_reward("object_count")
@single_thread()
def object_count_reward(batch: SceneBatch, stats: DatasetStats | None = None, count_distribution=None,
                        mode: str = "kl", eps: float = 1e-4, ground_only: bool = False) -> torch.Tensor:
    """Object-count prior: ``-KL(batch || training)`` for every scene (``mode="kl"``), the training
    log-probability of each scene's count (``mode="log_prob"``) or its per-scene score
    ``log(p_train(n) / p_batch(n))`` (``mode="match"``). With ``ground_only`` it counts the furniture
    (ground objects) alone, against ``count_distribution`` (the training rooms' furniture counts, which the
    statistics do not hold): a lamp, which never collides, then cannot stand in for a removed nightstand."""
    if mode not in ("kl", "log_prob", "match"):
        raise ValueError(f"object_count mode must be 'kl', 'log_prob' or 'match', not {mode!r}")
    if ground_only and count_distribution is None:
        raise ValueError("object_count with ground_only needs count_distribution=[p0, p1, ...], the share of "
                         "training rooms with 0, 1, 2, ... ground objects (the statistics count every object)")
    train = _count_distribution(stats, count_distribution, batch.num_slots)
    counted = batch.ground_mask if ground_only else batch.mask
    counts = np.clip(counted.sum(1).cpu().numpy(), 0, len(train) - 1)
    p_train = (train + eps) / (train + eps).sum()
    if mode == "log_prob":
        return _out(np.log(p_train)[counts], batch)
    hist = np.bincount(counts, minlength=len(train)).astype(np.float64)
    p_batch = hist / max(hist.sum(), 1) + eps
    p_batch = p_batch / p_batch.sum()
    if mode == "match":
        return _out(np.log(p_train / p_batch)[counts], batch)
    kl = float(np.sum(p_batch * np.log(p_batch / p_train)))
    return _out(np.full(batch.batch_size, -kl), batch)


@register_reward("class_presence")
@single_thread()
def class_presence_reward(batch: SceneBatch, stats: DatasetStats | None = None, class_presence=None,
                          mode: str = "log_prob", eps: float = 1e-3) -> torch.Tensor:
    """Class-presence prior: the training log-likelihood of the set of classes in each scene (a product of
    one Bernoulli per class, with the training rooms' presence rates ``class_presence`` or
    ``stats.class_presence``; ``mode="log_prob"``), its part for the classes missing from the scene
    (``mode="absence"``), or its rate-matching score against the batch's own presence rates
    (``mode="match"``; module doc)."""
    if mode not in ("log_prob", "absence", "match"):
        raise ValueError(f"class_presence mode must be 'log_prob', 'absence' or 'match', not {mode!r}")
    if class_presence is None:
        if stats is None or not stats.class_presence:
            raise ValueError("the class_presence reward needs each class's presence rate in the training rooms: "
                             "pass stats=DatasetStats with class_presence (recompute the statistics with "
                             "DatasetStats.from_layouts) or class_presence={label: rate}")
        class_presence = stats.class_presence
    p = _per_class(batch, class_presence, "class_presence").float().clamp(eps, 1 - eps)
    present = (_class_counts(batch) > 0).float()  # (B, C)
    if mode == "match":
        q = present.mean(0).clamp(eps, 1 - eps)
        return (present * (p / q).log() + (1 - present) * ((1 - p) / (1 - q)).log()).sum(1)
    if mode == "absence":
        return ((1 - present) * (1 - p).log()).sum(1)
    return (present * p.log() + (1 - present) * (1 - p).log()).sum(1)


@register_reward("class_frequency")
@single_thread()
def class_frequency_reward(batch: SceneBatch, stats: DatasetStats | None = None, class_frequencies=None,
                           eps: float = 1e-3) -> torch.Tensor:
    """Class-frequency matching: per scene, ``sum over its objects of log(f_c / g_c)`` with the training
    shares ``f`` (``class_frequencies`` or ``stats.class_frequencies``) and the batch's own shares ``g``."""
    if class_frequencies is None:
        if stats is None or not stats.class_frequencies:
            raise ValueError("the class_frequency reward needs the training rooms' class frequencies: pass "
                             "stats=DatasetStats (with class_frequencies) or class_frequencies={label: share}")
        class_frequencies = stats.class_frequencies
    f = _per_class(batch, class_frequencies, "class_frequencies") + eps
    counts = _class_counts(batch).to(f)  # (B, C)
    g = counts.sum(0) / counts.sum().clamp(min=1) + eps
    return (counts @ ((f / f.sum()).log() - (g / g.sum()).log())).float()


@register_reward("object_size")
@single_thread()
def object_size_reward(batch: SceneBatch, stats: DatasetStats | None = None, class_sizes=None,
                       min_std: float = 0.02, max_z: float = 3.0) -> torch.Tensor:
    """Per-class size matching: per scene, the sum over its objects of the log-density of their log half-sizes
    under the training sizes (``class_sizes`` or ``stats.class_sizes``) minus that under the batch's own
    sizes, less that difference's mean over the batch's objects of the class; standard deviations floored at
    ``min_std``, deviations counted up to ``max_z`` of them (one misshapen object then cannot outweigh every
    other term). Classes without training sizes, or with fewer than two objects in the batch, score 0."""
    if class_sizes is None:
        if stats is None or not stats.class_sizes:
            raise ValueError("the object_size reward needs each class's sizes in the training rooms: pass "
                             "stats=DatasetStats with class_sizes (recompute the statistics with "
                             "DatasetStats.from_layouts) or class_sizes={label: {'log_mean': [x, y, z], "
                             "'log_std': [x, y, z]}}")
        class_sizes = stats.class_sizes
    classes = batch.spec.classes
    unknown = sorted(set(class_sizes) - set(classes))
    if unknown:
        raise ValueError(f"class_sizes names classes that {batch.spec.name} rooms do not have: {unknown}")
    x = batch.half_sizes.double().clamp(min=1e-4).log()  # (B, N, 3)
    score = torch.zeros_like(x[..., 0])
    for c, ref in class_sizes.items():
        objects = batch.labels == classes.index(c)
        if objects.sum() < 2:
            continue
        v = x[objects]
        mean, std = (torch.tensor(ref[k]).to(v) for k in ("log_mean", "log_std"))
        # log N(v; training) - log N(v; batch): the log-std constants go with the centring below
        score_c = 0.5 * (_squared_z(v, v.mean(0), v.std(0, unbiased=False), min_std, max_z)
                         - _squared_z(v, mean, std, min_std, max_z))
        score[objects] = score_c - score_c.mean()
    return _out(score.sum(1), batch)


def _squared_z(x: torch.Tensor, mean: torch.Tensor, std: torch.Tensor, min_std: float, max_z: float) -> torch.Tensor:
    """Sum over the last axis of z^2, z = (x - mean) / std, standard deviations floored at ``min_std`` and |z|
    capped at ``max_z``."""
    return (((x - mean) / std.clamp(min=min_std)).clamp(-max_z, max_z) ** 2).sum(-1)


@register_reward("required_class")
def required_class_reward(batch: SceneBatch, classes: str | list[str] = "bed") -> torch.Tensor:
    """0 for a scene with an object of ``classes`` (a class group name, e.g. ``"bed"``, or a list of
    classes), -1 for a scene without one."""
    labels = CLASS_GROUPS.get(classes, (classes,)) if isinstance(classes, str) else tuple(classes)
    columns = [batch.spec.classes.index(c) for c in labels if c in batch.spec.classes]
    if not columns or any(c not in ALL_CLASSES for c in labels):
        raise ValueError(f"required_class: {classes!r} is neither a class group ({', '.join(sorted(CLASS_GROUPS))}) "
                         f"nor classes of {batch.spec.name} rooms ({', '.join(batch.spec.classes)})")
    return _out((_class_counts(batch)[:, columns].sum(1) > 0).float() - 1.0, batch)


def _per_class(batch: SceneBatch, values: dict, name: str) -> torch.Tensor:
    """``values`` ({label: number}, absent labels 0) as a float64 tensor in the order of the room's classes."""
    labels = batch.spec.classes
    unknown = sorted(set(values) - set(labels))
    if unknown:
        raise ValueError(f"{name} names classes that {batch.spec.name} rooms do not have: {unknown}")
    return torch.tensor([float(values.get(c, 0.0)) for c in labels], dtype=torch.float64, device=batch.labels.device)


def _class_counts(batch: SceneBatch) -> torch.Tensor:
    """(B, C) objects of each class per scene."""
    k = len(batch.spec.classes)
    onehot = torch.nn.functional.one_hot(batch.labels.clamp(min=0), k + 1)[..., :k]
    return (onehot * batch.mask[..., None]).sum(1)
