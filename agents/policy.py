"""The diffusion policy of the denoising MDP (DDPO): one DDIM step of the prior's denoiser as a Gaussian,

    pi_theta(x_{t-1} | x_t, t, floor) = N(mu_theta(x_t, t, floor), sigma_t^2 I),

with LoRA adapters (peft; r = 16, alpha = 16 on the attention's q/k/v/out projections) as the trainable
parameters theta. Each task gets its own named adapter, saved and loaded in peft's own format
(``adapter_config.json`` + ``adapter_model.safetensors``). The log-probability is the MEAN of per-element
Gaussian log-densities over a scene (so its scale does not grow with the number of slots), shared with :mod:`iarcs_env.schedule`.

An adapter may adapt only some feature groups of a slot (``adapted``; e.g. ``("position", "yaw")``): the
others follow its *reference*, eps = where(adapted, eps_theta, eps_ref). The reference is the adapter it was
initialised from (a stage-2 adapter follows the stage-1 policy it starts from, so it keeps stage 1's
objects and physical plausibility and changes only what the task needs), or the prior for an adapter made
from scratch. Without ``class``, the reference also decides which slots hold objects: a slot whose class the
reference predicts (from x0_hat) to be ``empty`` keeps the reference's eps on every feature. An unused slot
is class ``empty`` *and* geometry 0, so without this rule an adapter of translation and yaw alone still
removes objects by pulling their geometry to 0 (a stage-1 run did: 3.7 -> 3.3 objects per room) or could
fill empty slots. So an adapter of ``("position", "yaw")`` moves and turns objects on the floor but does not
add, remove, resize, lift or sink them. An adapter with required objects (:mod:`iarcs_env.required_objects`)
samples its rooms with their classes given, so no slot can change: its slots given empty follow the reference.
The reference is saved inside the adapter's folder (``reference/``), so a saved adapter samples the same wherever
it is loaded.
"""

from __future__ import annotations

import contextlib
import copy
import json
from pathlib import Path
from typing import Sequence

import torch
from peft import LoraConfig, PeftModel, get_peft_model
from torch import nn

from iarcs_env.floorplan import FloorPlan
from iarcs_env.relations import class_mask
from iarcs_env.required_objects import RequiredObject, with_required
from iarcs_env.scene import SceneBatch
from iarcs_env.schedule import ddim_previous, gaussian_log_prob, standard_normal

from .denoiser import ScenePrior

LORA_TARGETS = ["q_proj", "k_proj", "v_proj", "out_proj"]
FEATURE_GROUPS = {"position": [0, 2], "elevation": [1], "footprint": [3, 5], "height": [4], "yaw": [6, 7],
                  "class": slice(8, None)}
"""The slot features (iarcs_env.scene: translation xyz, half size xyz, cos/sin yaw, class) an adapter can adapt,
by group: position on the floor (x, z), elevation (y, the centre's height), footprint, height, yaw, class.
``translation`` names position and elevation, ``size`` footprint and height."""
ALIASES = {"translation": ("position", "elevation"), "size": ("footprint", "height")}
ADAPTED_FILE = "iarcs_adapted.json"
"""Written beside peft's files: the feature groups the adapter adapts (absent: all of them) and the name of
its reference adapter (absent or null: the prior), whose own folder is ``reference/`` beside it."""
REFERENCE_DIR = "reference"


def check_feature_groups(groups) -> tuple[str, ...]:
    """The adapted feature groups in canonical order; every group when ``groups`` is empty."""
    groups = [part for g in (groups or FEATURE_GROUPS) for part in ALIASES.get(g, (g,))]
    unknown = sorted(set(groups) - set(FEATURE_GROUPS))
    if unknown:
        raise ValueError(f"unknown feature group(s) {', '.join(unknown)}; choose from {', '.join(FEATURE_GROUPS)} "
                         "(or translation = position and elevation, size = footprint and height)")
    return tuple(g for g in FEATURE_GROUPS if g in groups)


class MeanNormal(torch.distributions.Normal):
    """Diagonal Gaussian over a scene (..., N, F) whose ``log_prob`` is the mean over the scene's elements
    (the DDPO convention), so TorchRL's PPO ratio is exp(mean log-density difference)."""

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        return super().log_prob(value).flatten(-2).mean(-1)

    def entropy(self) -> torch.Tensor:
        return super().entropy().flatten(-2).mean(-1)

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return self.mean


class DiffusionPolicy(nn.Module):
    """The prior's denoiser (frozen) with LoRA adapters, seen as the Gaussian policy of the MDP.

    Args:
        prior: the pretrained scene prior (its denoiser is wrapped in place).
        adapter: name of the first adapter (one per task, e.g. "stage1", "reach_1m").
        num_steps: DDIM steps of an episode (must match the environment's).
        eta: DDIM stochasticity; 1 gives the DDPM-like variance DDPO needs.
        lora_r, lora_alpha: LoRA rank and scale.
        adapted: feature groups of :data:`FEATURE_GROUPS` the first adapter adapts (empty: all).
        adapted_classes: classes or class groups whose objects the first adapter changes (empty: all).
    """

    def __init__(self, prior: ScenePrior, adapter: str = "stage1", num_steps: int = 20, eta: float = 1.0,
                 lora_r: int = 16, lora_alpha: int = 16, adapted=(), adapted_classes=()):
        super().__init__()
        self.prior = prior
        self.num_steps = num_steps
        self.eta = eta
        self.lora_config = LoraConfig(r=lora_r, lora_alpha=lora_alpha, target_modules=LORA_TARGETS, lora_dropout=0.0)
        for p in prior.denoiser.parameters():
            p.requires_grad_(False)
        self.model: PeftModel = get_peft_model(prior.denoiser, self.lora_config, adapter_name=adapter)
        self.model.eval()  # no dropout: sampling and training log-probs must agree
        self.schedule = prior.schedule
        self.adapted: dict[str, tuple[str, ...]] = {adapter: check_feature_groups(adapted)}
        self.references: dict[str, str | None] = {adapter: None}
        """adapter -> the adapter its non-adapted features follow (None: the prior)."""
        self.required: dict[str, tuple[RequiredObject, ...]] = {adapter: ()}
        """adapter -> the objects its task needs in every room (:mod:`iarcs_env.required_objects`)."""
        self.adapted_classes: dict[str, tuple[str, ...]] = {adapter: self._check_classes(adapted_classes, adapter)}
        """adapter -> the classes or class groups whose objects it changes (empty: all); the rest follow its
        reference."""
        self._adapters_off = False

    # --- adapters ---------------------------------------------------------------------------------------
    @property
    def adapter(self) -> str:
        return self.model.active_adapter

    def add_adapter(self, name: str, init_from: str | None = None, adapted=(), required=(),
                    adapted_classes=()) -> None:
        """A new adapter (zero-initialised B, so the policy starts as the prior), or a copy of ``init_from``.
        ``adapted``: its feature groups (empty: those of ``init_from``, or all). The features it does not
        adapt follow ``init_from`` (kept frozen, and saved with it), or the prior; ``init_from``'s own reference
        when ``init_from`` adapts the same features (a second training phase of a task adapter: the same mix,
        one network pass less a step). ``required``: the :class:`RequiredObject` s of its task (its rooms'
        classes are then given: it must not adapt ``class``). ``adapted_classes``: the classes or class groups
        whose objects it changes (empty: those of ``init_from``, or all); the other objects follow the reference.
        Needs ``required`` (the rooms' classes given)."""
        # a copy keeps init_from's layers and rank (an adapter trained with other target_modules loses none of them)
        self.model.add_adapter(name, copy.deepcopy(self.model.peft_config[init_from]) if init_from else self.lora_config)
        self.adapted[name] = check_feature_groups(adapted or (self.adapted[init_from] if init_from else ()))
        if required and "class" in self.adapted[name]:
            raise ValueError("an adapter with required objects samples its rooms' classes given, so it cannot adapt "
                             "them: leave class out of adapt")
        self.required[name] = tuple(required)
        self.adapted_classes[name] = self._check_classes(
            adapted_classes or (self.adapted_classes.get(init_from, ()) if init_from else ()), name)
        reference = init_from if len(self.adapted[name]) < len(FEATURE_GROUPS) else None
        if reference is not None and self.references.get(init_from) and self.adapted[init_from] == self.adapted[name]:
            reference = self.references[init_from]  # init_from leaves the same features to its own reference
        self.references[name] = reference
        if init_from is not None:
            src = {k: v for k, v in self.model.state_dict().items() if f".{init_from}." in k}
            self.model.load_state_dict({k.replace(f".{init_from}.", f".{name}."): v for k, v in src.items()},
                                       strict=False)
        self.set_adapter(name)

    def _check_classes(self, names, adapter: str) -> tuple[str, ...]:
        """``names`` (classes or class groups an adapter changes) checked against the room and the adapter."""
        names = tuple(names)
        if names:
            if not self.required.get(adapter) and "class" in self.adapted[adapter]:
                raise ValueError("adapting only some classes' objects needs the classes decided elsewhere: leave "
                                 "class out of adapt, or add required_objects (e.g. [{classes: support_surface, "
                                 "add: nightstand}])")
            if not self.class_filter(names).any():
                raise ValueError(f"adapt_classes {list(names)} names no object class of a {self.prior.spec.name}")
        return names

    def class_filter(self, names: Sequence[str]) -> torch.Tensor:
        """(K + 1,) bool over the room's class indices and ``empty``: True for the classes ``names`` covers."""
        classes = self.prior.spec.classes
        return class_mask(torch.arange(len(classes) + 1)[None], classes, names)[0]

    def set_adapter(self, name: str) -> None:
        self.model.set_adapter(name)
        self.model.eval()

    def save_adapter(self, folder: str | Path, name: str | None = None) -> Path:
        """Write one adapter in peft's format to ``folder/<name>/``."""
        name = name or self.adapter
        self.model.save_pretrained(str(folder), selected_adapters=[name])
        path = Path(folder) / name if name != "default" else Path(folder)
        reference = self.references.get(name)
        if reference is not None:
            reference = self.save_adapter(path / REFERENCE_DIR, reference).name
        (path / ADAPTED_FILE).write_text(json.dumps({"adapted": list(self.adapted[name]), "reference": reference,
                                                     "required_objects": [r.to_dict() for r in self.required[name]],
                                                     "adapted_classes": list(self.adapted_classes[name])}))
        return path

    def load_adapter(self, folder: str | Path, name: str | None = None) -> str:
        """Load an adapter saved by :meth:`save_adapter` (``folder`` is the adapter's own folder)."""
        folder = Path(folder)
        if not (folder / "adapter_config.json").exists():
            raise FileNotFoundError(f"no peft adapter in {folder} (adapter_config.json missing)")
        name = name or folder.name
        meta = json.loads((folder / ADAPTED_FILE).read_text()) if (folder / ADAPTED_FILE).exists() else {}
        reference = None
        if meta.get("reference"):
            reference = self.load_adapter(folder / REFERENCE_DIR / meta["reference"], f"{name}_reference")
        if name in self.model.peft_config:
            self.model.delete_adapter(name)
        self.model.load_adapter(str(folder), adapter_name=name, is_trainable=True)
        self.adapted[name] = check_feature_groups(meta.get("adapted", ()))
        self.references[name] = reference
        self.required[name] = tuple(RequiredObject.from_dict(r, self.prior.spec.classes, f"{folder / ADAPTED_FILE}")
                                    for r in meta.get("required_objects", ()))
        self.adapted_classes[name] = self._check_classes(meta.get("adapted_classes", ()), name)
        self.set_adapter(name)
        return name

    @contextlib.contextmanager
    def base_policy(self):
        """Context in which the policy is the prior (adapters disabled), e.g. for a KL penalty; re-entrant."""
        if self._adapters_off:
            yield
            return
        self._adapters_off = True
        try:
            with self.model.disable_adapter():
                yield
        finally:
            self._adapters_off = False

    @contextlib.contextmanager
    def reference_policy(self):
        """Context in which the policy is the active adapter's reference: the adapter it started from (its
        reference's own mix), or the prior. The policy a KL penalty holds the adapter near."""
        reference = self.references.get(self.adapter)
        if reference is None:
            with self.base_policy():
                yield
        else:
            with self._using(reference):
                yield

    def trainable_parameters(self) -> list[nn.Parameter]:
        return [p for p in self.model.parameters() if p.requires_grad]

    # --- the Gaussian -----------------------------------------------------------------------------------
    def reference_features(self, adapter: str | None = None) -> torch.Tensor | None:
        """(F,) bool mask of the slot features an adapter (default: the active one) leaves to its reference
        (None: it adapts all)."""
        groups = self.adapted.get(adapter or self.adapter, tuple(FEATURE_GROUPS))
        if len(groups) == len(FEATURE_GROUPS):
            return None
        keep = torch.ones(self.prior.spec.feature_dim, dtype=torch.bool)
        for g in groups:
            keep[FEATURE_GROUPS[g]] = False
        return keep

    @contextlib.contextmanager
    def _using(self, adapter: str):
        """Context in which ``adapter`` is the active one (the previous one afterwards)."""
        active = self.adapter
        if adapter == active:
            yield
            return
        self.set_adapter(adapter)
        try:
            yield
        finally:
            self.set_adapter(active)

    def eps(self, x_t: torch.Tensor, t: torch.Tensor, floor: torch.Tensor | None = None,
            floor_context: torch.Tensor | None = None, adapter: str | None = None,
            classes: torch.Tensor | None = None) -> torch.Tensor:
        """eps_theta(x_t, t, floor) of an adapter (default: the active one), with its reference's eps on the
        features it does not adapt (the prior's inside :meth:`base_policy`). ``classes``: the rooms' given
        classes (B, N) of an adapter with required objects; its slots given empty follow the reference."""
        name = adapter or self.adapter
        with self._using(name):
            eps = self.model(x_t, t, floor=floor, floor_context=floor_context)
        keep = self.reference_features(name)
        only = self.adapted_classes.get(name) if classes is not None else ()
        if (keep is None and not only) or self._adapters_off:
            return eps
        if keep is None:
            keep = torch.zeros(self.prior.spec.feature_dim, dtype=torch.bool)
        reference = self.references.get(name)
        with torch.no_grad():
            if reference is None:
                with self.base_policy():
                    base = self.model(x_t, t, floor=floor, floor_context=floor_context)
            else:
                base = self.eps(x_t, t, floor=floor, floor_context=floor_context, adapter=reference)
        keep = keep.to(eps.device).expand_as(eps)
        if classes is not None:
            # slots given empty stay the reference's: their geometry is never scored, so adapting it is noise
            fixed = classes == self.prior.spec.empty_index
            if only:  # objects of the classes it does not change: the reference's too
                fixed = fixed | ~self.class_filter(only).to(classes.device)[classes]
            keep = keep | fixed.to(keep.device)[..., None]
        elif "class" not in self.adapted[name] and not self.required.get(name):
            # slots the reference leaves empty, or fills with a class the adapter does not change, stay its
            predicted = self.schedule.predict_x0(x_t, t, base)[..., FEATURE_GROUPS["class"]].argmax(-1)
            fixed = predicted == self.prior.spec.empty_index
            if self.adapted_classes.get(name):
                fixed = fixed | ~self.class_filter(self.adapted_classes[name]).to(predicted.device)[predicted]
            keep = keep | fixed[..., None]
        return torch.where(keep, base, eps)

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, floor: torch.Tensor,
                classes: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """mu_theta and sigma_t of pi(x_{t-1} | x_t, t, floor); shapes (B, N, F) (sigma broadcast)."""
        out = self._step(x_t, t, floor, classes)
        return out.mean, out.std.expand_as(x_t)

    def _step(self, x_t, t, floor, classes=None):
        """The DDIM step's Gaussian and x0_hat (a ``DDIMStepOutput`` whose sample is not drawn); ``classes``: see
        :meth:`eps`."""
        t = torch.as_tensor(t, device=x_t.device).long().reshape(-1)
        if t.numel() == 1:
            t = t.expand(x_t.shape[0])
        eps = self.eps(x_t, t, floor, classes=classes)
        t_prev = ddim_previous(t, self.num_steps, self.schedule.num_train_timesteps)
        # passing prev_sample makes step() compute the Gaussian without drawing from it
        return self.schedule.step(eps, t, x_t, eta=self.eta, prev_sample=x_t, prev_timestep=t_prev)

    def predict_x0(self, x_t, t, floor, classes=None, straight_through: bool = False) -> torch.Tensor:
        """x0_hat_theta(x_t): the clean scene the step predicts (differentiable in the adapter); with the rooms'
        given ``classes`` (see :meth:`eps`) its class part is theirs. The DDIM step clips it to [-1, 1], where a
        feature at its bound (in the room frame an object against a wall) has no gradient; ``straight_through``: the
        clipped value with the gradient of the unclipped one."""
        if straight_through:  # one forward pass, clipped as the DDIM step clips
            t = torch.as_tensor(t, device=x_t.device).long().reshape(-1).expand(x_t.shape[0])
            raw = self.schedule.predict_x0(x_t, t, self.eps(x_t, t, floor, classes=classes))
            bound = self.schedule.config.clip_sample_range if self.schedule.config.clip_sample else float("inf")
            x0 = raw + (raw.clamp(-bound, bound) - raw).detach()
        else:
            x0 = self._step(x_t, t, floor, classes).pred_original_sample
        return x0 if classes is None else self.prior.with_clean_classes(x0, classes)

    def log_prob(self, x_t, t, floor, x_prev, classes=None) -> torch.Tensor:
        """log pi(x_prev | x_t, t, floor), mean-reduced per scene: (B,)."""
        mean, std = self(x_t, t, floor, classes)
        return gaussian_log_prob(x_prev, mean, std)

    @torch.no_grad()
    def act(self, x_t, t, floor, generator: torch.Generator | None = None, deterministic: bool = False,
            return_x0: bool = False, classes: torch.Tensor | None = None):
        """Sample x_{t-1} (the mean when ``deterministic``) and its log-probability (and, with ``return_x0``,
        the clean scene x0_hat the step predicts)."""
        out = self._step(x_t, t, floor, classes)
        mean, std = out.mean, out.std.expand_as(x_t)
        if deterministic or self.eta == 0:
            x_prev = mean
        else:
            x_prev = mean + std * standard_normal(mean.shape, generator, mean.device, mean.dtype)
        log_prob = gaussian_log_prob(x_prev, mean, std)  # std is already floored at MIN_STD
        return (x_prev, log_prob, out.pred_original_sample) if return_x0 else (x_prev, log_prob)

    @torch.no_grad()
    def required_classes(self, floors: Sequence[FloorPlan], generator: torch.Generator | None = None,
                         batch_size: int | None = None, num_steps: int | None = None,
                         eta: float | None = None) -> torch.Tensor | None:
        """(B, N) class indices of rooms for ``floors`` that hold the active adapter's required objects: sampled by
        its reference (stage 1; DDIM steps and eta default to the policy's), the missing objects added
        (:func:`iarcs_env.required_objects.with_required`); None for an adapter without required objects."""
        required = self.required.get(self.adapter)
        if not required:
            return None
        with self.reference_policy():
            first = self.prior.sample(floors, num_steps or self.num_steps, self.eta if eta is None else eta, generator,
                                      batch_size=batch_size, eps_fn=self.eps)
        return with_required(first.labels, self.prior.spec.classes, required, generator)

    @torch.no_grad()
    def sample(self, floors: Sequence[FloorPlan], generator: torch.Generator | None = None,
               batch_size: int = 64, **kwargs) -> SceneBatch:
        """Scenes for the given floor plans with the active adapter (a whole DDIM rollout; with required objects,
        a stage-1 rollout first for the rooms' classes). ``kwargs``: more of :meth:`ScenePrior.sample`'s
        arguments (``guidance_scale``, ``ids``, ``num_steps`` and ``eta``: default the policy's)."""
        kwargs = {"num_steps": self.num_steps, "eta": self.eta, **kwargs}
        classes = self.required_classes(floors, generator, batch_size, kwargs["num_steps"], kwargs["eta"])
        return self.prior.sample(floors, generator=generator, batch_size=batch_size, eps_fn=self.eps, classes=classes,
                                 **kwargs)

    def actor(self):
        """A TorchRL ``ProbabilisticActor`` view: reads ``x_t``, ``t``, ``floor`` (and the rooms' given ``classes``
        for an adapter with required objects); writes ``action`` and its mean-reduced ``sample_log_prob``."""
        from tensordict.nn import TensorDictModule
        from torchrl.modules import ProbabilisticActor

        in_keys = ["x_t", "t", "floor"] + (["classes"] if self.required.get(self.adapter) else [])
        module = TensorDictModule(_Gaussian(self), in_keys=in_keys, out_keys=["loc", "scale"])
        return ProbabilisticActor(module, in_keys=["loc", "scale"], out_keys=["action"],
                                  distribution_class=MeanNormal, return_log_prob=True,
                                  log_prob_key="sample_log_prob")


class _Gaussian(nn.Module):
    """(x_t, t, floor[, classes]) -> (loc, scale) for TensorDictModule (t may carry a trailing dim of 1)."""

    def __init__(self, policy: DiffusionPolicy):
        super().__init__()
        self.policy = policy

    def forward(self, x_t, t, floor, classes=None):
        batch = x_t.shape[:-2]
        if classes is not None:
            classes = classes.reshape(-1, classes.shape[-1])
        mean, std = self.policy(x_t.reshape(-1, *x_t.shape[-2:]), t.reshape(-1), floor.reshape(-1, *floor.shape[-2:]),
                                classes)
        return mean.reshape(*batch, *mean.shape[-2:]), std.reshape(*batch, *std.shape[-2:])
