"""Pretraining of the scene prior (DDPM epsilon loss) on any layout dataset the readers load.

A :class:`PretrainConfig` dataclass (loaded from YAML, a docstring per field) and :func:`train`, with EMA
weights, condition dropout for classifier-free guidance, a tqdm bar, TensorBoard scalars and checkpoints that
resume after an interruption. Its data pipeline is :mod:`agents.pretrain_data`, its x0-hat losses
:mod:`agents.x0_losses`.

Files in ``out`` (the run folder):

* ``train_state.pt``: model, EMA, optimizer, step and RNG states; written atomically every
  ``checkpoint_every`` steps; a run started again with the same ``out`` resumes from it;
* ``prior.pt``: the EMA weights as a :class:`agents.denoiser.ScenePrior` checkpoint (what sampling and
  RL fine-tuning load), written with every checkpoint;
* ``config.yaml``, ``dataset_stats.json``, ``metrics.jsonl`` (one line per logged step) and ``tb/``.
"""

from __future__ import annotations

import copy
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import torch

from iarcs_env.rooms import get_room
from iarcs_env.scene import Layout
from iarcs_env.schedule import PREDICTION_TYPES, NoiseSchedule
from iarcs_env.stats import DatasetStats

from . import distributed
from .config import check_device, dataclass_from_dict, load_yaml_config
from .denoiser import GEOMETRY_DIM, DenoiserConfig, SceneDenoiser, ScenePrior, atomic_torch_save
from .pretrain_data import SceneTensors, encode_batch, training_data
from .x0_losses import out_of_bound_excess, overlap_excess

REPO_ROOT = Path(__file__).resolve().parents[1]
MIN_SNR_GAMMA = 5.0  # the gamma of loss_weighting: min_snr
STATE_FILE = "train_state.pt"
PRIOR_FILE = "prior.pt"


@dataclass
class PretrainConfig:
    """Pretraining of one room type's scene prior. Every field can be set in the YAML file."""

    room: str = "bedroom"
    """Room type: bedroom, livingroom or diningroom."""
    dataset: str = "procedural"
    """``procedural`` (the embedded generator), a neutral-JSON layout file or an ATISS folder. A relative
    path is looked up from the working directory, then from the repository root."""
    num_scenes: int = 10000
    """Scenes drawn from the procedural generator (ignored for files)."""
    data_seed: int = 0
    """Seed of the procedural generator (and of the validation split)."""
    val_scenes: int = 256
    """Scenes held out to measure a validation loss (0: none)."""
    extra_datasets: list = field(default_factory=list)
    """Layout files (or ATISS folders) trained on beside ``dataset``, each ``{dataset: PATH, weight: W}``: a batch
    draws its rooms from ``dataset`` with weight 1 and from each extra with its weight (uniformly within each),
    e.g. the rooms of ``iarcs augment``. They join the training rooms only; statistics and validation stay
    ``dataset``'s."""
    preset: str = "small"
    """Denoiser size preset: small (CPU) or paper (8 layers, width 512)."""
    model: dict = field(default_factory=dict)
    """Overrides of the preset's fields (num_layers, width, num_heads, ff_dim, dropout, pointnet,
    floor_tokens, floor_point_tokens, slot_embedding)."""
    steps: int = 6000
    """Total optimizer steps of the run (a resumed run continues up to this)."""
    batch_size: int = 128
    """Scenes per optimizer step (under ``torchrun``: in all, split evenly over the processes)."""
    lr: float = 5e-4
    """Peak learning rate of AdamW."""
    lr_schedule: str = "cosine"
    """After the warm-up: ``cosine`` (decays to ``lr * min_lr_ratio`` at ``steps``) or ``constant`` (for a run
    whose length a clock sets, ``iarcs pretrain --time-budget``; the EMA weights are what it exports)."""
    min_lr_ratio: float = 0.1
    """The cosine decay ends at ``lr * min_lr_ratio``."""
    warmup_steps: int = 300
    """Linear learning-rate warm-up steps."""
    weight_decay: float = 0.0
    """AdamW weight decay."""
    grad_clip: float = 1.0
    """Gradient-norm clip (0: none)."""
    ema_decay: float = 0.999
    """Decay of the exponential moving average of the weights (the exported prior uses the EMA)."""
    translation_weight: float = 1.0
    """Weight of the floor-plane translation features (x, z) in the epsilon loss, the others 1. Placement
    against the walls is learnt from these 2 of the ~30 features per slot, mostly at small t; a weight
    above 1 spends more of the loss on it (1: the plain DDPM loss)."""
    elevation_weight: float = 1.0
    """Weight of the elevation feature (y, the box centre's height) in the epsilon loss. Above 1 keeps
    furniture on the floor while an auxiliary loss pulls the network elsewhere (1: the plain DDPM loss)."""
    max_timestep: int = 0
    """Train on noise levels t < ``max_timestep`` only (0: all T): a fine-tune of the low-noise steps, which
    place objects to the centimetre (validation losses stay over all t)."""
    overlap_weight: float = 0.0
    """Weight of an auxiliary loss on the predicted clean layout x0_hat (after DiffuScene's physical IoU
    loss): for every pair of objects of the training scene, the volume (m^3) by which their predicted
    footprints overlap more than the pair's do in the data, over the pair's vertical overlap in the data,
    summed per scene (:func:`overlap_excess`), at noise levels t < ``overlap_max_timestep``. Aims at gross
    collisions without penalising the data's own tucked-in nightstands. 0: the plain DDPM loss."""
    overlap_spares_contact: bool = False
    """The overlap loss charges only pairs that do not overlap in the data (:func:`overlap_excess`'s
    ``spare_contact``): the living and dining rooms' chairs stand under their tables in the data."""
    overlap_contact_gap: float = 0.0
    """With ``overlap_spares_contact``: pairs whose footprints come within this gap (m) of each other in the data
    are spared too (``contact_gap``): the living rooms' chairs stand at their tables' edges."""
    overlap_contact_volume: float = math.inf
    """With ``overlap_spares_contact``: the spared pairs are charged their excess overlap beyond this volume (m^3;
    ``contact_volume``), so that a chair is free to stand at or under its table, not deep in it. inf: not charged."""
    overlap_max_timestep: int = 100
    """The overlap loss applies below this t only: at higher noise x0_hat is a blurred average of layouts
    whose boxes overlap by nature (about 9 m^3 per scene at t = 400 for the 3,000-step prior)."""
    out_of_bound_weight: float = 0.0
    """Weight of a second auxiliary loss on x0_hat: for every object of the training scene, the distance (m)
    by which each corner of its footprint (the data's size and yaw at x0_hat's floor position) lies behind the
    wall nearest to it, beyond the data's own corner (:func:`out_of_bound_excess`), summed per scene, at noise
    levels t < ``out_of_bound_max_timestep``. Aims at furniture in the missing part of an L-shaped room's
    bounding box. 0: none."""
    out_of_bound_max_timestep: int = 100
    """The out-of-bound loss applies below this t only."""
    cond_drop_prob: float = 0.1
    """Probability of dropping the floor condition (zeroed) per scene: enables classifier-free guidance."""
    rotation_augment: bool = True
    """Rotate each training scene by a random multiple of 90 degrees (floor and objects together)."""
    permutation_augment: bool = True
    """Shuffle each training scene's object slots."""
    canonical_order: bool = False
    """Put each room's objects in a canonical slot order: sorted by class index, empty slots last
    (:meth:`SceneTensors.from_layouts`), so that a slot's index tells what it holds, for a denoiser with
    ``model: {slot_embedding: true}``. Needs ``permutation_augment: false``."""
    prediction_type: str = "epsilon"
    """What the denoiser predicts: ``epsilon`` (the noise: the original design), ``sample`` (x0) or
    ``v_prediction`` (v); saved in the prior's schedule config, so that the prior samples as it was trained."""
    loss_weighting: str = "none"
    """Timestep weighting of the loss: ``none`` (the plain loss), or ``min_snr``: each scene's loss times
    min(SNR_t, 5) / SNR_t for epsilon prediction (min-SNR-gamma with gamma 5; min(SNR_t, 5) for x0 and
    min(SNR_t, 5) / (SNR_t + 1) for v), which gives the mid-noise steps more weight than the low-noise ones."""
    classes_given: bool = False
    """Condition the denoiser on each slot's class: the class part of x_t is the data's clean one-hot at every
    t and the loss is on the geometry only; such a prior samples with given classes (``ScenePrior.sample(...,
    classes=...)``). An experiment: can the network place objects relative to each other when it need not
    choose their classes."""
    checkpoint_every: int = 500
    """Steps between checkpoints (train_state.pt and prior.pt)."""
    log_every: int = 50
    """Steps between logged training losses (TensorBoard, metrics.jsonl)."""
    eval_every: int = 500
    """Steps between validation losses of the EMA weights."""
    out: str = "out/pretrain/bedroom_small"
    """Run folder (checkpoints, logs). Keep weights trained on research-only data out of the repository."""
    seed: int = 0
    """Seed of initialisation, batches, noise and augmentation."""
    num_threads: int = 0
    """torch CPU threads (0: torch's default)."""
    device: str = "auto"
    """Where the network trains: ``auto`` (the first CUDA GPU torch sees, else the CPU), ``cpu``, ``cuda`` or
    ``cuda:N``. Data and augmentation stay on the CPU; the seeded noise is drawn on the CPU too, so a run's
    randomness does not depend on the device."""
    precision: str = "fp32"
    """``fp32``, or ``bf16``: the denoiser's forward pass under ``torch.autocast`` in bfloat16 (weights, optimiser,
    EMA and the loss stay float32; attention runs in float32 on a CPU). Faster on recent GPUs, and 1.4x faster on
    a CPU with AMX tiles, with the same validation loss (docs/results/benchmarks.md, "Pretraining")."""
    compile: bool = False
    """``torch.compile`` the denoiser (fewer, fused GPU kernels; it compiles for a minute or two first). When
    compiling fails the run goes on without it, with the reason logged."""
    tensorboard: bool = True
    """Write TensorBoard scalars to ``out/tb``."""
    init_from: str = ""
    """Fine-tune: a fresh run starts from the weights and feature scaling of this scene-prior checkpoint
    (``default``: the shipped prior of ``room``) instead of a random initialisation, e.g. the procedural prior
    on real rooms. Its architecture must be the one ``preset`` and ``model`` describe. A resumed run ignores it."""

    def __post_init__(self):
        get_room(self.room)
        check_device(self.device)
        if self.lr_schedule not in ("cosine", "constant"):
            raise ValueError(f"lr_schedule must be cosine or constant, got {self.lr_schedule!r}")
        if self.precision not in ("fp32", "bf16"):
            raise ValueError(f"precision must be fp32 or bf16, got {self.precision!r}")
        if self.prediction_type not in PREDICTION_TYPES:
            raise ValueError(f"prediction_type must be one of {', '.join(PREDICTION_TYPES)}, got "
                             f"{self.prediction_type!r}")
        if self.loss_weighting not in ("none", "min_snr"):
            raise ValueError(f"loss_weighting must be none or min_snr, got {self.loss_weighting!r}")
        if self.canonical_order and self.permutation_augment:
            raise ValueError("canonical_order needs permutation_augment: false (shuffled slots have no order)")
        DenoiserConfig.from_preset(self.preset, **dict(self.model))
        for name in ("num_scenes", "steps", "batch_size", "checkpoint_every", "log_every", "eval_every"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        for name in ("overlap_weight", "out_of_bound_weight", "overlap_contact_gap", "overlap_contact_volume"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be at least 0, got {getattr(self, name)}")
        for name in ("translation_weight", "elevation_weight"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not 0 <= self.cond_drop_prob < 1:
            raise ValueError(f"cond_drop_prob must be in [0, 1), got {self.cond_drop_prob}")
        num_t = NoiseSchedule().num_train_timesteps
        for name in ("overlap_max_timestep", "out_of_bound_max_timestep"):
            if not 0 <= getattr(self, name) <= num_t:
                raise ValueError(f"{name} must be in [0, {num_t}], got {getattr(self, name)}")
        if not 0 <= self.max_timestep <= num_t:
            raise ValueError(f"max_timestep must be in [0, {num_t}] (0: all), got {self.max_timestep}")
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must be in [0, 1), got {self.ema_decay}")
        for k, extra in enumerate(self.extra_datasets):
            weight = extra.get("weight") if isinstance(extra, dict) else None
            if (not isinstance(extra, dict) or set(extra) != {"dataset", "weight"}
                    or not isinstance(extra["dataset"], str) or isinstance(weight, bool)
                    or not isinstance(weight, (int, float)) or not 0 < weight < float("inf")):
                raise ValueError(f"extra_datasets[{k}] must be {{dataset: PATH, weight: W}} with W > 0, got {extra!r}")

    def denoiser_config(self) -> DenoiserConfig:
        return DenoiserConfig.from_preset(self.preset, **dict(self.model))


def config_from_dict(data: dict, where: str = "config") -> PretrainConfig:
    """Build a :class:`PretrainConfig`, rejecting unknown keys and values of the wrong type."""
    return dataclass_from_dict(PretrainConfig, data, where)


def load_config(path: str | Path, **overrides) -> PretrainConfig:
    """Read a YAML config; keyword ``overrides`` (e.g. ``steps=100``) win over the file."""
    return load_yaml_config(PretrainConfig, path, **overrides)


def loss_feature_weights(cfg: PretrainConfig, feature_dim: int, plain: bool = False) -> torch.Tensor | None:
    """Per-feature weights of the epsilon loss (``translation_weight`` on x and z, ``elevation_weight`` on y,
    1 elsewhere; ``plain``: 1 on all, the validation loss); with ``classes_given`` 0 on the class part and
    (8 + K) / 8 on the geometry, a mean over the geometry. None for the plain loss."""
    weights = torch.ones(feature_dim)
    if not plain:
        weights[[0, 2]] = cfg.translation_weight
        weights[1] = cfg.elevation_weight
    if cfg.classes_given:
        weights[GEOMETRY_DIM:] = 0
        weights *= feature_dim / GEOMETRY_DIM
    return None if bool((weights == 1).all()) else weights


def denoiser_fn(model: Callable, floor: torch.Tensor, x0: torch.Tensor, cfg: PretrainConfig) -> Callable:
    """``f(x_t, t)``: ``model(x_t, t, floor)`` in float32; with ``classes_given`` the class part of x_t replaced
    by the clean one of ``x0``."""
    if not cfg.classes_given:
        return lambda x, t: model(x, t, floor).float()
    given = x0[..., GEOMETRY_DIM:]
    return lambda x, t: model(torch.cat([x[..., :GEOMETRY_DIM], given], -1), t, floor).float()


# --- training ------------------------------------------------------------------------------------------
@dataclass
class TrainResult:
    """What :func:`train` returns."""

    step: int
    """Global step reached (over all sessions of the run)."""
    losses: list = field(default_factory=list)
    """(step, training loss) of every step of this session."""
    val_losses: list = field(default_factory=list)
    """(step, validation loss of the EMA weights)."""
    resumed_from: int = 0
    """Step the session resumed from (0: a fresh run)."""
    out: Path | None = None
    prior_path: Path | None = None
    seconds: float = 0.0
    stopped_by_deadline: bool = False
    """The time budget ended the run (before ``cfg.steps`` or ``max_steps``)."""


def load_init(cfg: PretrainConfig) -> tuple[ScenePrior, dict | None]:
    """What ``cfg.init_from`` names, checked to fit the run's room and architecture: a scene-prior checkpoint
    (``default``: the shipped prior of the room), or a pretraining run folder or its ``train_state.pt``. Returns
    the prior (for a run: its EMA weights) and, for a run, its training state (weights, EMA and optimizer
    state, which the new run continues), else None."""
    where = f"init_from {cfg.init_from!r}"
    state = None
    if cfg.init_from == "default":
        prior = ScenePrior.load_default(cfg.room)
    else:
        path = Path(cfg.init_from).expanduser()
        if not path.is_absolute() and not path.exists():
            path = REPO_ROOT / path
        if path.is_dir():
            if not (path / STATE_FILE).exists():
                raise FileNotFoundError(f"{where}: {path} holds no {STATE_FILE}; give a pretraining run folder, its "
                                        f"{STATE_FILE}, a prior checkpoint (.pt) or 'default'")
            path = path / STATE_FILE
        if path.name == STATE_FILE:
            state = torch.load(path, map_location="cpu", weights_only=True)
            prior = prior_from_state(state, str(path))
        else:
            prior = ScenePrior.load(path)
    if prior.spec.name != get_room(cfg.room).name:
        raise ValueError(f"{where} is a {prior.spec.name} prior, but this run trains a {cfg.room} prior: "
                         "initialise from a prior of the same room type")
    want = cfg.denoiser_config()
    if prior.denoiser.config != want:
        diff = {k: (getattr(prior.denoiser.config, k), getattr(want, k)) for k in asdict(want)
                if getattr(prior.denoiser.config, k) != getattr(want, k)}
        raise ValueError(f"{where} has another architecture than preset {cfg.preset!r} with model {dict(cfg.model)} "
                         f"(checkpoint vs config: {diff}); set preset/model to the checkpoint's")
    predicts = prior.schedule.config.prediction_type
    if predicts != cfg.prediction_type:  # the same weights would be read as another quantity
        raise ValueError(f"{where} predicts {predicts!r}, but this run trains prediction_type "
                         f"{cfg.prediction_type!r}; set prediction_type: {predicts} in the config")
    return prior, state


def lr_at(step: int, cfg: PretrainConfig) -> float:
    """Linear warm-up, then a cosine decay to ``lr * min_lr_ratio`` at ``cfg.steps`` (``lr_schedule: cosine``)
    or the peak rate held (``constant``)."""
    if cfg.warmup_steps > 0 and step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    if cfg.lr_schedule == "constant":
        return cfg.lr
    span = max(cfg.steps - cfg.warmup_steps, 1)
    frac = min(max(step - cfg.warmup_steps, 0) / span, 1.0)
    return cfg.lr * (cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * frac)))


@dataclass
class TrainingBatch:
    """One step's batch on the training device."""

    x0: torch.Tensor
    """Clean scenes (B, N, 8 + K)."""
    floor: torch.Tensor
    """Floor conditions (B, P, 4); zero for the scenes whose condition is dropped."""
    t: torch.Tensor
    """Timesteps (B,)."""
    noise: torch.Tensor
    """epsilon (B, N, 8 + K)."""
    extents: torch.Tensor
    """The floors' half-extents (B, 2) in metres."""
    points: torch.Tensor
    """The floors' boundary points (B, P, 4): x, z, nx, nz in metres."""


def draw_batch(data: SceneTensors, cfg: PretrainConfig, spec, stats: DatasetStats, generator: torch.Generator,
               size: int) -> TrainingBatch:
    """All of a step's randomness, drawn from ``generator`` on the data's device in one order: the rooms, their
    rotations and slot permutations, which conditions are dropped, the timesteps and the noise."""
    device = data.labels.device
    if data.draw_weights is None:
        idx = torch.randint(0, len(data), (size,), generator=generator, device=device)
    else:
        idx = torch.multinomial(data.draw_weights, size, replacement=True, generator=generator)
    metric = data.batch(idx, generator, rotate=cfg.rotation_augment, permute=cfg.permutation_augment)
    x0, floor = encode_batch(spec, stats, *metric)
    if cfg.cond_drop_prob > 0:
        keep = torch.rand(size, generator=generator, device=device) >= cfg.cond_drop_prob
        floor = floor * keep[:, None, None]
    t = torch.randint(0, cfg.max_timestep or NoiseSchedule().num_train_timesteps, (size,), generator=generator,
                      device=device)
    noise = torch.randn(x0.shape, generator=generator, device=device)
    return TrainingBatch(x0, floor, t, noise, metric[5], metric[4])


def batch_loss(model: Callable, schedule: NoiseSchedule, batch: TrainingBatch, cfg: PretrainConfig, spec,
               stats: DatasetStats, weights: torch.Tensor | None) -> torch.Tensor:
    """Per-scene loss (B,): the DDPM loss (feature-weighted by ``weights``, timestep-weighted as
    ``loss_weighting`` says) plus the x0-hat losses the config asks for. ``model(x_t, t, floor)`` predicts
    epsilon (or x0, or v: ``schedule.config.prediction_type``)."""
    penalties = []
    if cfg.overlap_weight:
        penalties.append(overlap_excess(spec, stats, batch.extents, cfg.overlap_weight, cfg.overlap_max_timestep,
                                        cfg.overlap_spares_contact, cfg.overlap_contact_gap,
                                        cfg.overlap_contact_volume))
    if cfg.out_of_bound_weight:
        penalties.append(out_of_bound_excess(spec, stats, batch.extents, batch.points, cfg.out_of_bound_weight,
                                             cfg.out_of_bound_max_timestep))
    penalty = (lambda x0_hat, x0, t: sum(p(x0_hat, x0, t) for p in penalties)) if penalties else None
    scene_weights = schedule.min_snr_weights(batch.t, MIN_SNR_GAMMA) if cfg.loss_weighting == "min_snr" else None
    return schedule.training_loss(denoiser_fn(model, batch.floor, batch.x0, cfg), batch.x0, t=batch.t,
                                  noise=batch.noise, reduction="none", feature_weights=weights, x0_penalty=penalty,
                                  scene_weights=scene_weights)


def training_step(model: Callable, net: SceneDenoiser, ema: SceneDenoiser, opt: torch.optim.Optimizer,
                  schedule: NoiseSchedule, cfg: PretrainConfig, spec, stats: DatasetStats, weights,
                  next_batch: Callable[[], TrainingBatch], lr: float, ema_decay: float,
                  mark: Callable[[str], None] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """One optimizer step on ``next_batch()``: the loss of :func:`batch_loss` through ``model`` (``net`` or its
    compiled form), its gradients averaged over the processes and clipped, AdamW at ``lr``, and the EMA
    weights moved towards the new ones. Returns the loss and the gradient norm as tensors on the device (reading
    them would wait for the step). ``mark(part)``, if given, is called after each part (benchmarks time them)."""
    mark = mark or (lambda part: None)
    batch = next_batch()
    mark("data")
    for group in opt.param_groups:
        group["lr"] = lr
    with torch.autocast(batch.x0.device.type, dtype=torch.bfloat16, enabled=cfg.precision == "bf16"):
        loss = batch_loss(model, schedule, batch, cfg, spec, stats, weights).mean()
    mark("forward")
    opt.zero_grad(set_to_none=True)
    loss.backward()
    mark("backward")
    params = list(net.parameters())
    distributed.average_gradients(params)
    grad_norm = torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip if cfg.grad_clip > 0 else math.inf, foreach=True)
    opt.step()
    mark("optimizer")
    with torch.no_grad():
        torch._foreach_lerp_(list(ema.parameters()), params, 1 - ema_decay)
    mark("ema")
    return loss.detach(), grad_norm


def compiled(net: SceneDenoiser, example: Callable[[], TrainingBatch], schedule: NoiseSchedule,
             cfg: PretrainConfig, spec, stats: DatasetStats, weights, log: Callable[[str], None]) -> Callable:
    """``torch.compile(net)``, compiled on one forward and backward pass of an ``example()`` batch (its gradients
    dropped); ``net`` itself when compiling fails, with the reason logged: the run goes on eagerly."""
    try:
        model = torch.compile(net)
        t0 = time.perf_counter()
        with torch.autocast(next(net.parameters()).device.type, dtype=torch.bfloat16, enabled=cfg.precision == "bf16"):
            batch_loss(model, schedule, example(), cfg, spec, stats, weights).mean().backward()
        net.zero_grad(set_to_none=True)
        log(f"torch.compile: compiled in {time.perf_counter() - t0:.0f} s")
        return model
    except Exception as err:  # noqa: BLE001 - any compiler failure: train eagerly
        net.zero_grad(set_to_none=True)
        log(f"torch.compile failed ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}); "
            "training without it")
        return net


def _check_resumable(saved: dict, cfg: PretrainConfig, path: Path) -> None:
    for key in ("room", "preset", "model", "dataset", "num_scenes", "data_seed", "prediction_type", "classes_given",
                "canonical_order"):
        was = saved.get(key, PretrainConfig.__dataclass_fields__[key].default)  # a run from before the field
        if was != asdict(cfg)[key]:
            raise ValueError(
                f"{path} was trained with {key}={was!r} but the config says {asdict(cfg)[key]!r}; "
                "use another output folder (--out) to start a new run, or restore the setting to resume")


def train(cfg: PretrainConfig, layouts: Sequence[Layout] | None = None, max_steps: int | None = None,
          progress: bool = True, log: Callable[[str], None] = print, resume: bool = True,
          time_budget: float | None = None) -> TrainResult:
    """Train (or resume) the prior of ``cfg``; stops at ``cfg.steps`` or, earlier, at ``max_steps``
    (the global step to stop at, as if the run were interrupted there) or when ``time_budget`` seconds after
    the call are spent (with the last checkpoint's duration kept free: it writes one then, and the run can be
    resumed). ``layouts`` overrides the
    dataset of the config (tests pass hand-made rooms). Under ``torchrun`` every process draws its share of
    each batch, the gradients are averaged, and rank 0 alone writes (:mod:`agents.distributed`)."""
    from tqdm import tqdm

    t_start = time.perf_counter()
    if cfg.num_threads > 0:
        torch.set_num_threads(cfg.num_threads)
    device = distributed.setup(cfg.device)
    main, processes = distributed.is_main(), distributed.world_size()
    if cfg.batch_size % processes:
        raise ValueError(f"batch_size {cfg.batch_size} does not split evenly over {processes} processes; make it a "
                         f"multiple of {processes}")
    if not main:
        progress, log = False, lambda *args, **kwargs: None
    spec = get_room(cfg.room)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    state_path = out / STATE_FILE
    saved = None
    if resume and state_path.exists():
        saved = torch.load(state_path, map_location="cpu", weights_only=True)
        _check_resumable(saved["config"], cfg, state_path)
    init, init_state = load_init(cfg) if saved is None and cfg.init_from else (None, None)

    # data (procedural rooms: read from the cache that the first run writes)
    data, val, stats = training_data(cfg, layouts, log, progress=progress, with_stats=saved is None)
    if saved is not None:
        stats = DatasetStats.from_json(saved["stats"], spec.name)
        if stats.translation_frame != "room":
            raise ValueError(
                f"{state_path} was trained with translations in the {stats.translation_frame!r} frame, but this "
                "iARCS trains in the room frame only; use another output folder (--out) to start a new run, or "
                "resume with the iARCS version that wrote it")
    else:
        stats.translation_frame = "room"
        if init is not None:  # the network's inputs keep the scaling it was trained with
            for name in ("bounds_translations", "bounds_sizes", "bounds_angles", "translation_frame"):
                setattr(stats, name, copy.deepcopy(getattr(init.stats, name)))
        if main:
            stats.save(out / "dataset_stats.json")
            _write_yaml(out / "config.yaml", asdict(cfg))

    # model, EMA, optimizer, randomness
    torch.manual_seed(cfg.seed)
    net = SceneDenoiser(cfg.denoiser_config(), spec.feature_dim)
    net.set_metric_scale(stats)
    weights = loss_feature_weights(cfg, spec.feature_dim)
    val_weights = loss_feature_weights(cfg, spec.feature_dim, plain=True)  # validation losses stay the plain loss
    if init is not None:
        net.load_state_dict(init_state["model"] if init_state else init.denoiser.state_dict())
        log(f"initialised from {cfg.init_from}" + (" (weights, EMA and optimizer state)" if init_state else ""))
    net.to(device)
    distributed.broadcast_parameters(net.parameters())  # one initialisation on every rank
    weights, val_weights = (w.to(device) if w is not None else None for w in (weights, val_weights))
    ema = copy.deepcopy(net).eval().requires_grad_(False)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, fused=True)
    if init_state:
        ema.load_state_dict(init_state["ema"])
        opt.load_state_dict(init_state["optimizer"])
    data, val = data.to(device), val.to(device) if val is not None else None  # resident on the training device
    gen = torch.Generator(device).manual_seed(distributed.rank_seed(cfg.seed + 1))  # each rank its own batches
    schedule = NoiseSchedule(prediction_type=cfg.prediction_type)
    step = 0
    if saved is not None:
        net.load_state_dict(saved["model"])
        ema.load_state_dict(saved["ema"])
        opt.load_state_dict(saved["optimizer"])
        step = int(saved["step"])
        if saved["rng"].get("device", "cpu") == device.type:
            gen.set_state(saved["rng"]["generator"])
        else:  # the batches' stream was drawn on another kind of device: a new one starts from this step
            gen.manual_seed(distributed.rank_seed(cfg.seed + 1) + step)
            log(f"{state_path} drew its batches on {saved['rng'].get('device', 'cpu')}: a new random stream starts")
        torch.set_rng_state(saved["rng"]["torch"])
        if device.type == "cuda" and "cuda" in saved["rng"]:
            torch.cuda.set_rng_state_all(saved["rng"]["cuda"])
        if not main:  # rank 0's streams were saved; the others start new ones from here
            gen.manual_seed(distributed.rank_seed(cfg.seed + 1) + step)
        log(f"resumed {state_path} at step {step}")
    log(f"training on {device}" + (f", {processes} processes of {cfg.batch_size // processes} scenes per step"
                                   if processes > 1 else ""))
    result = TrainResult(step=step, resumed_from=step, out=out)
    stop = min(cfg.steps, max_steps) if max_steps is not None else cfg.steps
    deadline = t_start + time_budget if time_budget is not None else math.inf

    writer = None
    if cfg.tensorboard and main:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(out / "tb"), purge_step=step if step else None)
    metrics = (out / "metrics.jsonl").open("a") if main else None

    def save_checkpoint():
        state = {"step": step, "model": net.state_dict(), "ema": ema.state_dict(), "optimizer": opt.state_dict(),
                 "rng": {"generator": gen.get_state(), "device": device.type, "torch": torch.get_rng_state()},
                 "config": asdict(cfg), "stats": stats.to_json()}
        if device.type == "cuda":
            state["rng"]["cuda"] = torch.cuda.get_rng_state_all()
        atomic_torch_save(state, state_path)
        prior = ScenePrior(copy.deepcopy(ema), stats, NoiseSchedule(schedule.config), meta=prior_meta(cfg, step))
        result.prior_path = prior.save(out / PRIOR_FILE)

    def ema_loss(rooms: SceneTensors) -> float:
        """The EMA weights' plain loss on ``rooms`` (not augmented), with the same t and noise every time."""
        g = torch.Generator(device).manual_seed(1234)
        losses = []
        with torch.no_grad():
            for i in range(0, len(rooms), 256):
                idx = torch.arange(i, min(i + 256, len(rooms)), device=device)
                x0, floor = encode_batch(spec, stats, *rooms.batch(idx))
                losses.append(schedule.training_loss(denoiser_fn(ema, floor, x0, cfg), x0, g, reduction="none",
                                                     feature_weights=val_weights))
        return float(torch.cat(losses).mean())

    # as many training rooms as held-out ones: the gap between their losses measures overfitting
    seen = data.batch(torch.arange(min(len(val), len(data)), device=device)) if val is not None else None
    seen = SceneTensors(*seen) if seen is not None else None

    per_rank = cfg.batch_size // processes
    example = lambda: draw_batch(data, cfg, spec, stats, torch.Generator(device).manual_seed(0), per_rank)  # noqa: E731
    model = compiled(net, example, schedule, cfg, spec, stats, weights, log) if cfg.compile and step < stop else net
    until = f" until {time.strftime('%H:%M:%S', time.localtime(time.time() + time_budget))}" if time_budget else ""
    bar = tqdm(total=None if time_budget else stop, initial=step, disable=not progress,  # a clock's run: no total
               desc=f"pretrain {spec.name}{until}", dynamic_ncols=True, unit="step")
    running, loss_sum, summed = None, torch.zeros((), device=device), 0
    save_seconds = 0.0  # how long the last checkpoint (and validation) took: kept free before the deadline
    net.train()
    try:
        while step < stop:
            lr = lr_at(step, cfg)
            decay = cfg.ema_decay if init is not None else min(cfg.ema_decay, (1 + step) / (10 + step))
            loss, grad_norm = training_step(model, net, ema, opt, schedule, cfg, spec, stats, weights,
                                            lambda: draw_batch(data, cfg, spec, stats, gen, per_rank), lr, decay)
            step += 1
            loss_sum += loss.detach()  # read (a host synchronisation) only when logged
            summed += 1
            bar.update(1)
            late = time.perf_counter() + save_seconds >= deadline  # each process's clock; rank 0's counts
            if step % cfg.log_every == 0 or step == stop or (late and processes == 1):
                row = torch.stack([loss_sum / summed, torch.tensor(float(late and main), device=device)])
                gathered = distributed.all_gather(row.reshape(1, 2))  # read: a host synchronisation
                value, late = float(gathered[:, 0].mean()), bool(gathered[:, 1].max() > 0)  # the whole batch's
                loss_sum.zero_()
                summed = 0
                result.losses.append((step, value))
                running = value if running is None else 0.9 * running + 0.1 * value
                if late:  # the time budget is spent: every process stops here, with a checkpoint
                    stop = step
                    result.stopped_by_deadline = True
                if main:
                    t_save = time.perf_counter()
                    bar.set_postfix(loss=f"{running:.4f}", lr=f"{lr:.2e}")
                    record = {"step": step, "loss": value, "loss_avg": running, "lr": lr,
                              "grad_norm": float(grad_norm), "seconds": round(time.perf_counter() - t_start, 1)}
                    if writer is not None:
                        writer.add_scalar("train/loss", value, step)
                        writer.add_scalar("train/loss_avg", running, step)
                        writer.add_scalar("train/lr", lr, step)
                        writer.add_scalar("train/grad_norm", float(grad_norm), step)
                    if step % cfg.eval_every == 0 or step == stop:
                        if val is not None:
                            v, fit = ema_loss(val), ema_loss(seen)
                            result.val_losses.append((step, v))
                            record.update(val_loss_ema=v, train_rooms_loss_ema=fit)
                            if writer is not None:
                                writer.add_scalar("val/loss_ema", v, step)
                                writer.add_scalar("val/train_rooms_loss_ema", fit, step)
                                writer.add_scalar("val/overfit_gap", v - fit, step)
                    metrics.write(json.dumps(record) + "\n")
                    metrics.flush()
                    if step % cfg.checkpoint_every == 0 or step == stop:
                        save_checkpoint()
                        save_seconds = time.perf_counter() - t_save
            elif main and step % cfg.checkpoint_every == 0:
                save_checkpoint()
    finally:
        bar.close()
        if metrics is not None:
            metrics.close()
        if writer is not None:
            writer.close()
    result.step = step
    result.seconds = time.perf_counter() - t_start
    return result


def prior_from_state(state: dict, where: str = "train_state.pt") -> ScenePrior:
    """The EMA weights of a pretraining state (``train_state.pt``) as a :class:`ScenePrior`."""
    cfg = config_from_dict(state["config"], where)
    spec = get_room(cfg.room)
    net = SceneDenoiser(cfg.denoiser_config(), spec.feature_dim)
    net.load_state_dict(state["ema"])
    return ScenePrior(net, DatasetStats.from_json(state["stats"], spec.name),
                      NoiseSchedule(prediction_type=cfg.prediction_type), meta=prior_meta(cfg, int(state["step"])))


def prior_meta(cfg: PretrainConfig, step: int) -> dict:
    """The ``meta`` of a prior exported from a run; ``classes_given`` where the prior needs classes to sample."""
    meta = {"step": step, "preset": cfg.preset, "dataset": cfg.dataset, "room": get_room(cfg.room).name}
    return {**meta, "classes_given": True} if cfg.classes_given else meta


def export_prior(state_path: str | Path, dest: str | Path, half: bool = False) -> Path:
    """Write the EMA weights of a ``train_state.pt`` as a :class:`ScenePrior` checkpoint (``half``:
    float16 weights, half the file size; they are loaded back as float32)."""
    state = torch.load(state_path, map_location="cpu", weights_only=True)
    return prior_from_state(state, str(state_path)).save(dest, half=half)


def _write_yaml(path: Path, data: dict) -> None:
    import yaml

    path.write_text(yaml.safe_dump(data, sort_keys=False))


__all__ = ["PretrainConfig", "TrainResult", "TrainingBatch", "batch_loss", "config_from_dict", "draw_batch", "export_prior",
           "load_config", "lr_at", "prior_from_state", "train", "training_step"]
