"""Physics gradient: the LoRA adapter follows the gradient of the two universal rewards that are differentiable
in the layout (collision volume, out-of-bound area), evaluated on the clean scene the policy predicts at the
last denoising steps of its own rollouts (after DRaFT / AlignProp, which backpropagate a differentiable reward
through the sampler; here through one step's x0_hat, as DiffuScene's physical loss does in pretraining).

Per stored state x_t of the last ``gradient_steps`` stochastic steps of a rollout:

    loss = mean over scenes of  w_vol sum_{i<j ground} V_ij(x0_hat(x_t)) + w_out sum_i A_i(x0_hat(x_t))
                                + w_floor sum_{i ground} |bottom_i(x0_hat(x_t))|
                                + w_reach sum_{i ground} max(0, r - c_i(x0_hat(x_t)))

with V_ij the overlap volume of the axis-aligned bounds of boxes i and j (exact for axis-aligned furniture, as
most is, along the walls; its vertical extent carries no gradient: two objects on the floor overlap in height
whatever their heights, so flattening them shrinks the number, never the collision; with ``overlap_measure:
depth``, the penetration along the axis that separates them soonest, plus ``DEPTH_MARGIN``), A_i the area (m^2) of box
i's footprint, shrunk by ``out_of_bound_shrink`` per side (R_out's 0.05 m by default), outside the floor polygon,
and bottom_i the height (m) of a ground object's bottom above or below the floor; for a pair that the collision
reward's ``contact`` spares (a chair pushed under its table), V_ij less that volume, at least 0; or, with
``contact_gap_weight`` w_gap > 0, w_gap |d_ij - g| while their bounds' signed distance d_ij (m,
negative when they overlap) is under ``CONTACT_REACH``, g = ``contact_gap``: a seat at its table is drawn to just
short of it, not only kept from going under it too far; for a pair of ``uncharged_pairs`` classes (a chair
under its desk), nothing. w_vol is
``overlap_weight`` (1 by default), w_out ``out_of_bound_weight``, w_floor the weight of the run's ``floor_contact``
reward (0 without one: an adapter that moves objects on the floor only cannot change it), and c_i the clearance
(m) of the widest free path to object i (:func:`iarcs_env.clearance.reach_clearance`; R_reach counts it reached
when c_i >= r, the agent radius 0.3 m), weighed by w_reach = ``reach_weight`` (0 by default). Classes come from
x0_hat's arg-max (no gradient), or are the rooms' given ones for an adapter with required objects.
A policy gradient from 32 scenes an epoch has to discover, scene by scene, which way separates two objects;
this gradient says it for every pair. It uses :class:`~agents.ddpo.DDPO`'s rollouts, evaluation, checkpoints
and callbacks; only the update differs.

In stage 2 the task reward joins it: ``loss -= w_task * mean over scenes of R_task(x0_hat(x_t))``, with w_task
the composite reward's weight of its ``task`` term. The generated program runs in its sandbox, which returns
d R_task / d geometry (:meth:`rewards.sandbox.SandboxedReward.gradient`); the chain rule through the decoding is
applied here, as a vector-Jacobian product. Distances, offsets, angles, heights and the clearances of free space
(``scene.path_clearance``, ``scene.circle_clearance``) have a gradient; yes-or-no checks (``reachable``,
``free_circle``, ``walkable``, counts) have none.
"""

from __future__ import annotations

import sys

import numpy as np
import torch
from tensordict import TensorDict

from iarcs_env import geometry as geo
from iarcs_env.clearance import EDGE_POINTS, reach_clearance, room_to_pull
from iarcs_env.relation_fidelity import CHAIR_GAP
from iarcs_env.relations import _point_segment_distance as point_segment_distance, class_mask, floor_edges
from iarcs_env.scene import SceneBatch, decode_geometry, floor_half_extents, footprint_reach

from rewards.universal import class_pairs, contact_pairs

from . import distributed
from .ddpo import DDPO, DDPOConfig

CONTACT_REACH = CHAIR_GAP
"""m: a pair of the collision reward's ``contact`` classes whose bounds are closer than this is drawn together by
``contact_gap_weight`` (the chairs_at_dining_table relation's reach)."""
DEPTH_MARGIN = 0.02
"""m: with ``overlap_measure: depth``, pairs closer than this count as overlapping (pushed apart to it)."""


def physics_penalty(x0: torch.Tensor, stats, floors, out_of_bound_weight: float = 1.0,
                    floor_weight: float = 0.0, overlap_weight: float = 1.0,
                    out_of_bound_shrink: float = geo.OUT_OF_BOUND_SHRINK, contact: dict | None = None,
                    contact_gap_weight: float = 0.0, contact_gap: float = DDPOConfig.contact_gap,
                    overlap_measure: str = "volume", uncharged_pairs: list | None = None,
                    reach_weight: float = 0.0, contact_gap_walkway: bool = False,
                    passage_weight: float = 0.0) -> torch.Tensor:
    """(B,) ``overlap_weight`` times the overlap volume (m^3; or depth, ``overlap_measure``) of every pair of ground
    objects' axis-aligned bounds plus ``out_of_bound_weight`` times the out-of-bound area (m^2, footprints shrunk by
    ``out_of_bound_shrink`` m, R_out's 0.05 m by default) of every object plus ``floor_weight`` times the ground
    objects' distances (m) from the floor, of model features ``x0`` (B, N, 8 + K) on ``floors``; differentiable in
    the geometry. ``contact``: the collision reward's option; a pair of its classes is charged only the overlap
    beyond its volume, or with ``contact_gap_weight`` > 0 that weight times the distance of their bounds' signed
    distance from ``contact_gap`` while it is under ``CONTACT_REACH`` (module doc); a pair of
    ``uncharged_pairs`` classes is not charged its overlap; ``reach_weight`` times how
    much the widest free path to each ground object is narrower than R_reach's agent (m)."""
    trans, half, yaws = decode_geometry(x0, stats, floor_half_extents(floors).to(x0))
    return layout_penalty(trans, half, yaws, x0[..., 8:].argmax(-1), stats.spec, floors,
                          out_of_bound_weight=out_of_bound_weight, floor_weight=floor_weight,
                          overlap_weight=overlap_weight, out_of_bound_shrink=out_of_bound_shrink, contact=contact,
                          contact_gap_weight=contact_gap_weight, contact_gap=contact_gap,
                          overlap_measure=overlap_measure, uncharged_pairs=uncharged_pairs, reach_weight=reach_weight,
                          contact_gap_walkway=contact_gap_walkway, passage_weight=passage_weight)


def layout_penalty(trans: torch.Tensor, half: torch.Tensor, yaws: torch.Tensor, labels: torch.Tensor, spec, floors,
                   out_of_bound_weight: float = 1.0, floor_weight: float = 0.0, overlap_weight: float = 1.0,
                   out_of_bound_shrink: float = geo.OUT_OF_BOUND_SHRINK, contact: dict | None = None,
                   contact_gap_weight: float = 0.0, contact_gap: float = DDPOConfig.contact_gap,
                   overlap_measure: str = "volume", uncharged_pairs: list | None = None,
                   reach_weight: float = 0.0, contact_gap_walkway: bool = False,
                   passage_weight: float = 0.0) -> torch.Tensor:
    """:func:`physics_penalty` of rooms given in metres: translations (B, N, 3), half sizes (B, N, 3), yaws (B, N)
    and class labels (B, N) of room type ``spec`` (a label past its classes is an empty slot)."""
    valid = labels != spec.empty_index
    ground = torch.tensor(spec.ground_mask(), device=labels.device)[labels]
    separation = geo.bounds_separations(trans, half, yaws)
    overlap = separation.clamp_min(0)
    pairs = (ground[:, :, None] & ground[:, None]).triu(1)
    sooner = separation[..., 0:3:2].min(-1).values  # overlap along the axis that parts the pair soonest; -gap
    if overlap_measure == "volume":
        charge = overlap[..., 0] * overlap[..., 1].detach() * overlap[..., 2]
    elif overlap_measure == "depth":
        charge = (sooner + DEPTH_MARGIN).clamp_min(0) * (overlap[..., 1] > 0)
    else:
        raise ValueError(f"overlap_measure must be 'volume' or 'depth', got {overlap_measure!r}")
    gaps = charge.new_zeros(len(labels))
    if contact:
        spared = contact_pairs(labels, valid, spec, contact)
        if contact_gap_weight:
            drawn = spared & (-sooner < CONTACT_REACH) & pairs
            if contact_gap_walkway:  # only where drawing the pair's first class out narrows no walkway
                movers, anchors = (torch.stack([class_mask(labels, spec.classes, [pair[k]]) for pair in contact["pairs"]])
                                   .any(0) & valid & ground for k in (0, 1))
                room = room_to_pull(floors, trans, half, yaws, movers, anchors, ground & valid, contact_gap,
                                    geo.AGENT_RADIUS)
                drawn = drawn & room & room.transpose(1, 2)
            gaps = ((-sooner - contact_gap).abs() * drawn).sum((1, 2))
        if overlap_measure == "volume" and not contact_gap_weight:
            charge = torch.where(spared, (charge - contact["volume"]).clamp_min(0.0), charge)
        else:  # the pair is charged through contact_gap_weight only
            charge = charge.masked_fill(spared, 0.0)
    if uncharged_pairs:
        charge = charge.masked_fill(class_pairs(labels, valid, spec, uncharged_pairs, "ddpo.uncharged_pairs"), 0.0)
    charge = (charge * pairs).sum((1, 2))
    outside = geo.box_out_of_floor_area(trans, half, yaws, floors, valid, out_of_bound_shrink).sum(1)
    off_floor = geo.floor_gaps(trans, half, ground).sum(1)
    penalty = (overlap_weight * charge + contact_gap_weight * gaps + out_of_bound_weight * outside.to(charge)
               + floor_weight * off_floor)
    if passage_weight:
        penalty = penalty + passage_weight * narrow_passages(trans, half, yaws, labels, spec, floors, ground & valid)
    if reach_weight:
        clear = reach_clearance(floors, trans, half, yaws, ground & valid, geo.AGENT_RADIUS)
        penalty = penalty + reach_weight * (geo.AGENT_RADIUS - clear).clamp_min(0).sum(1).to(penalty)
    return penalty


PASSAGE_CLOSED = 0.05
"""m: a gap this narrow counts as closed (touching): ``passage_weight`` does not charge it."""


def passage_tent(gap: torch.Tensor) -> torch.Tensor:
    """min(g - PASSAGE_CLOSED, 2r - g) while PASSAGE_CLOSED < g < 2r (r: R_reach's agent radius), else 0: the way
    out of a gap too narrow to walk through, closed or opened to an agent's width, whichever is nearer."""
    width = 2 * geo.AGENT_RADIUS
    inside = (gap > PASSAGE_CLOSED) & (gap < width)
    return torch.where(inside, torch.minimum(gap - PASSAGE_CLOSED, width - gap), torch.zeros_like(gap))


def narrow_passages(trans, half, yaws, labels, spec, floors, ground) -> torch.Tensor:
    """(B,) :func:`passage_tent` summed over the gaps between ground objects' bounds (a seat and a table or two seats
    left out: chairs stand close at their table) and between each ground object's bounds (corners and edge midpoints)
    and each wall."""
    seat, table = (class_mask(labels, spec.classes, [name]) for name in ("seat", "table"))
    skip = (seat[:, :, None] & (seat | table)[:, None]) | (table[:, :, None] & seat[:, None])
    separation = geo.bounds_separations(trans, half, yaws)[..., 0:3:2]  # overlap (+) or minus the gap, per axis
    pairs = (ground[:, :, None] & ground[:, None]).triu(1) & (separation < 0).any(-1) & ~skip
    between = (passage_tent((-separation).clamp_min(0).norm(dim=-1)) * pairs).sum((1, 2))
    reach = footprint_reach(half[..., 0:3:2], torch.cos(yaws), torch.sin(yaws))
    points = trans[..., 0:3:2][:, :, None] + torch.tensor(EDGE_POINTS).to(trans) * reach[:, :, None]  # (B, N, 8, 2)
    edges = floor_edges(floors).to(trans)
    to_walls = point_segment_distance(points[:, :, :, None], edges[:, None, None, :, :2],
                                      edges[:, None, None, :, 2:]).amin(2)  # (B, N, E): each wall's nearest point
    return between + (passage_tent(to_walls) * ground[..., None]).sum((1, 2))


def config_penalty(x0: torch.Tensor, stats, floors, cfg: DDPOConfig, contact: dict | None = None,
                   floor_weight: float = 0.0) -> torch.Tensor:
    """:func:`physics_penalty` with the weights and measures of a run's DDPO config ``cfg``; ``contact`` and
    ``floor_weight`` come from its reward (:meth:`PhysicsGradient.contact`, :meth:`PhysicsGradient.floor_weight`)."""
    return physics_penalty(x0, stats, floors, reach_weight=cfg.reach_weight,
                           **penalty_weights(cfg, contact, floor_weight))


def penalty_weights(cfg: DDPOConfig, contact: dict | None = None, floor_weight: float = 0.0) -> dict:
    """The keyword arguments of :func:`layout_penalty` that a run's DDPO config ``cfg`` sets (all but the walkway
    term's weight, ``cfg.reach_weight``); ``contact`` and ``floor_weight`` as for :func:`config_penalty`."""
    return dict(out_of_bound_weight=cfg.out_of_bound_weight, floor_weight=floor_weight,
                overlap_weight=cfg.overlap_weight, out_of_bound_shrink=cfg.out_of_bound_shrink, contact=contact,
                contact_gap_weight=cfg.contact_gap_weight, contact_gap=cfg.contact_gap,
                contact_gap_walkway=cfg.contact_gap_walkway, passage_weight=cfg.passage_weight,
                overlap_measure=cfg.overlap_measure, uncharged_pairs=cfg.uncharged_pairs)


def task_surrogate(task_reward, x0: torch.Tensor, stats, floors) -> tuple[torch.Tensor, torch.Tensor, float]:
    """(surrogate (scalar), values (B,), the gradient's L1 norm): the task reward of the scenes that model
    features ``x0`` describe, decoded as the environment decodes them (:meth:`SceneBatch.decode`), and a surrogate
    whose gradient with respect to ``x0`` is that of the values' sum (the sandbox's gradient chained through the
    decoding)."""
    scenes = SceneBatch.decode(x0, stats, list(floors), keep_graph=True)
    values, grad = task_reward.gradient(scenes)  # the sandbox gets the values, detached
    surrogate = sum((grad[key] * getattr(scenes, key)).sum() for key in ("translations", "half_sizes", "yaws"))
    return surrogate, values, float(sum(g.abs().sum() for g in grad.values()))


def adapted_object_weights(policy, x0: torch.Tensor) -> torch.Tensor:
    """(B, N, F) weights of a regression onto rooms ``x0`` (model features): 1 on the features the policy's adapter
    adapts, of the objects present."""
    keep = policy.reference_features(policy.adapter)
    adapted = torch.ones(x0.shape[-1], dtype=torch.bool) if keep is None else ~keep
    present = x0[..., 8:].argmax(-1) != policy.prior.stats.spec.empty_index
    return (present[..., None] & adapted).float()


class PhysicsGradient(DDPO):
    """The physics gradient (module doc) with :class:`DDPO`'s surface: ``learn``, ``save``/``load``,
    callbacks. Uses ``learning_rate``, ``minibatch_size``, ``num_inner_epochs``, ``max_grad_norm``,
    ``gradient_steps``, ``overlap_weight``, ``overlap_measure``, ``contact_gap_weight``, ``contact_gap``,
    ``uncharged_pairs``, ``reach_weight``, ``out_of_bound_weight``, ``out_of_bound_shrink`` and ``kl_coef`` of
    :class:`~agents.ddpo.DDPOConfig`; the env's reward is logged, not optimised, but for a stage-2 task reward, whose
    gradient joins (module doc)."""

    name = "PHYSICS-GRADIENT"

    def __init__(self, policy, env, **kwargs):
        super().__init__(policy, env, **kwargs)
        if self.config.gradient_steps < 1:
            raise ValueError(f"gradient_steps must be at least 1 (the last steps whose x0_hat gets the gradient); "
                             f"got {self.config.gradient_steps}")
        if self.config.best_of_floor_weight > 0 and not len(self.best_of_floor_steps()):
            raise ValueError(f"best_of_floor_t {self.config.best_of_floor_t} holds none of the chain's timesteps "
                             f"({', '.join(str(int(t)) for t in self.venv.timesteps)}); widen it")
        self.checked_task_gradient = False

    def floor_weight(self) -> float:
        """The weight of the run's ``floor_contact`` reward (0 without one)."""
        return float(getattr(self.venv.reward_fn, "weights", {}).get("floor_contact", 0.0))

    def contact(self) -> dict | None:
        """The ``contact`` option of the run's collision reward (None without one): overlaps it spares."""
        return getattr(self.venv.reward_fn, "options", {}).get("collision", {}).get("contact")

    def task_reward(self):
        """(the task reward, its weight) when the env's reward has a differentiable ``task`` term, else None."""
        fn = self.venv.reward_fn
        task = getattr(fn, "functions", {}).get("task")
        return (task, fn.weights["task"]) if hasattr(task, "gradient") else None

    def best_of_floor(self, rollout: TensorDict) -> torch.Tensor:
        """(B,) bool: the scene of highest reward in each floor's group of the rollout (``best_of_floor_weight``)."""
        reward, floor = rollout["reward"][:, 0], rollout["floor_index"][:, 0]
        best = torch.zeros(len(reward), dtype=torch.bool)
        for group in floor.unique():
            members = torch.nonzero(floor == group).reshape(-1)
            best[members[reward[members].argmax()]] = True
        return best

    def best_of_floor_steps(self) -> torch.Tensor:
        """Indices of the chain's steps whose timestep lies in ``best_of_floor_t`` (inclusive)."""
        low, high = self.config.best_of_floor_t
        t = torch.as_tensor(self.venv.timesteps)
        return torch.nonzero((t >= low) & (t <= high)).reshape(-1)

    def final_rooms(self, rollout: TensorDict) -> tuple[torch.Tensor, torch.Tensor]:
        """The rooms the rollout's chains ended in (B, N, F; given classes in place) and the weights (B, N, F) of a
        regression onto them (:func:`adapted_object_weights`)."""
        last = rollout[:, -1]
        x0 = last["action"].clamp(-1, 1)
        if "classes" in last.keys():
            x0 = self.policy.prior.with_clean_classes(x0, last["classes"])
        return x0, adapted_object_weights(self.policy, x0)

    def train(self, rollout: TensorDict) -> dict[str, float]:
        cfg, venv = self.config, self.venv
        steps = self.stochastic_steps()[-cfg.gradient_steps:]
        b = rollout.batch_size[0]
        infos = []
        task, floor_weight, contact = self.task_reward(), self.floor_weight(), self.contact()
        best = self.best_of_floor(rollout) if cfg.best_of_floor_weight > 0 else None
        if best is not None:
            chosen = self.best_of_floor_steps()
            finals, weights = self.final_rooms(rollout)
        self.policy.model.eval()
        for _ in range(cfg.num_inner_epochs):
            perm = torch.randperm(b, generator=self.generator)
            for start in range(0, b, cfg.minibatch_size):
                rows = perm[start:start + cfg.minibatch_size]
                mb = rollout[rows][:, steps].reshape(-1).to(self.device)
                floors = [venv.floors[int(i)] for i in mb["floor_index"]]
                x0_hat = self.policy.predict_x0(mb["x_t"], mb["t"], mb["floor"], mb.get("classes", None))
                x0_hat = x0_hat.cpu()
                loss = config_penalty(x0_hat, venv.stats, floors, cfg, contact, floor_weight).mean()
                info = {"physics": loss.item()}
                if task is not None:
                    surrogate, values, size = task_surrogate(task[0], x0_hat, venv.stats, floors)
                    loss = loss - task[1] * surrogate / len(floors)
                    info.update(task=values.mean().item(), task_gradient=size / len(floors))
                if best is not None and best[rows].any():
                    picked = rows[best[rows]]
                    ranked = rollout[picked][:, chosen].reshape(-1).to(self.device)
                    x0_hat = self.policy.predict_x0(ranked["x_t"], ranked["t"], ranked["floor"],
                                                    ranked.get("classes", None), straight_through=True)
                    target, w = finals[picked].repeat_interleave(len(chosen), 0), weights[picked]
                    w = w.repeat_interleave(len(chosen), 0)
                    square = ((x0_hat - target.to(x0_hat)).square() * w).sum() / w.sum().clamp_min(1)
                    loss = loss + cfg.best_of_floor_weight * square
                    info["best_of_floor_square"] = square.item()
                if cfg.kl_coef > 0:  # anchored to the reference: what already passes is not pushed further
                    kl = self.kl_to_base(mb)
                    loss = loss + cfg.kl_coef * kl
                    info["kl_to_base"] = float(kl)
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                distributed.average_gradients(self.policy.trainable_parameters())
                grad_norm = torch.nn.utils.clip_grad_norm_(self.policy.trainable_parameters(), cfg.max_grad_norm)
                self.optimizer.step()
                infos.append({**info, "loss": loss.item(), "grad_norm": float(grad_norm)})
        stats = {key: float(np.mean([i[key] for i in infos if key in i]))
                 for key in dict.fromkeys(k for i in infos for k in i)}
        if task is not None and not self.checked_task_gradient:  # once, on the first update's scenes
            self.checked_task_gradient = True
            if stats["task_gradient"] == 0:
                print("warning: the task reward has no gradient (yes-or-no checks, such as counts, reachable or "
                      "free_circle, are not differentiable): the physics gradient follows the physical terms alone; "
                      "train this task with ddpo", file=sys.stderr)
        return {**stats, "approx_kl": 0.0, "clip_fraction": 0.0}
