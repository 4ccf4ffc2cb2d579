"""RL fine-tuning runs from a YAML config: stage 1 (universal rewards) and, with a ``task:`` block, stage 2
(a task reward written by the reward-synthesis agent, refined by reflection; see :mod:`agents.stage2`).
Builds the prior, the LoRA policy, the batched environment, the reward and the algorithm, trains with
checkpoints that resume, evaluates and logs to TensorBoard, and saves the adapter in peft's format.

Run folder: ``config.yaml``, ``checkpoint/`` (resumable state), ``adapters/<name>/`` (the trained adapter),
``tb/`` (TensorBoard), ``eval.jsonl`` (evaluation metrics per evaluation); stage 2 adds
``reward_memory.json`` (every reward program tried, with outcomes) and ``reward/`` (the final program).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import yaml

from . import distributed
from .config import check_device, dataclass_from_dict, load_yaml_config

CHECKPOINT_DIR = "checkpoint"
ADAPTERS_DIR = "adapters"
BEST_DIR = "best"


@dataclass
class TrainConfig:
    """An RL fine-tuning run."""

    room: str = "bedroom"
    """Room type: bedroom, livingroom or diningroom."""
    prior: str = "default"
    """Scene prior: ``default`` (the one shipped for the room) or a path to a prior .pt."""
    adapter: str = "stage1"
    """Name of the LoRA adapter to train (one per task)."""
    init_adapter: str = ""
    """Optional adapter folder (peft format) to start from; ``default``: the shipped stage-1 adapter."""
    adapt: list = field(default_factory=list)
    """Feature groups the adapter adapts (agents.policy.FEATURE_GROUPS: position, elevation, footprint, height,
    yaw, class; translation = position and elevation, size = footprint and height); the others follow
    ``init_adapter`` (the prior without one). Empty: all of them, or with ``init_adapter`` the same as that
    adapter. ``[elevation, height]`` lowers or raises objects but keeps which objects a room has and where."""
    required_objects: list = field(default_factory=list)
    """Objects the task needs in every room (stage 2, with ``init_adapter``; iarcs_env.required_objects), e.g.
    ``[{classes: bed, add: double_bed}, {classes: nightstand, at_least: 2}]``: each room is sampled by
    ``init_adapter`` first, the objects it lacks are added to its class list, and the adapter samples the room again
    with those classes given (it must not adapt ``class``). Saved with the adapter, so its samples hold them too."""
    adapt_classes: list = field(default_factory=list)
    """Classes or class groups (iarcs_env.relations.CLASS_GROUPS) whose objects the adapter changes, e.g.
    ``[support_surface]``; the other objects follow ``init_adapter`` or the prior. Which object a slot holds is given
    (``required_objects``) or, with ``adapt`` without ``class``, the reference's own prediction. Empty: every
    object, or with ``init_adapter`` the objects that adapter changes."""
    algorithm: str = "ddpo"
    """ddpo (= ddpo-is), ddpo-sf, physics-gradient (agents/physics_gradient.py) or descent-imitation
    (agents/descent_imitation.py)."""
    num_envs: int = 32
    """B: scenes per rollout batch (the vector env's size)."""
    num_steps: int = 20
    """DDIM steps per episode."""
    eta: float = 1.0
    """DDIM eta of the policy (1: DDPM-like variance)."""
    floors: str = "procedural"
    """Training floor plans: procedural, or a layout file / ATISS folder whose floors are used."""
    num_floors: int = 512
    """How many training floor plans (procedural ones are generated with ``floor_seed``)."""
    floor_seed: int = 1000
    """Seed of procedural training floors (the prior was trained on seed 0)."""
    eval_floors: int = 64
    """Held-out procedural floor plans for evaluations during training."""
    eval_seed: int = 12345
    """Seed of the evaluation floors (the same as ``iarcs_env.env.default_floors``)."""
    reward: dict = field(default_factory=lambda: {"collision": 1.0, "boundary": 1.0, "accessibility": 0.5,
                                                   "object_count": {"weight": 1.0, "mode": "log_prob"}})
    """Composite reward: {name: weight} or {name: {weight: w, option: value}} (see rewards.composite)."""
    task: dict = field(default_factory=dict)
    """Stage 2: the task (agents.stage2.TaskConfig: constraint, checker, reflect_every, model, ...); empty for
    stage 1."""
    epochs: int = 40
    """Training epochs (each: num_batches_per_epoch rollout batches, then updates)."""
    ddpo: dict = field(default_factory=dict)
    """DDPO hyper-parameters (agents.ddpo.DDPOConfig fields)."""
    eval_every: int = 5
    """Evaluate (metrics + render grid to TensorBoard) every this many epochs."""
    checkpoint_every: int = 1
    """Save the resumable state every this many epochs."""
    export: str = "last"
    """The adapter a finished run leaves in ``adapters/``: ``last``, or ``best``: the one of the evaluation with
    the highest task success (stage 2 with a checker; else the evaluation reward) on the evaluation floors.
    Either way the best one is kept in ``best/`` (``best.json``: its epoch and value) and every evaluation is
    in ``eval.jsonl``. DDPO's success can fall back after a peak (docs/results/stage2_tasks.md)."""
    best_tolerance: dict = field(default_factory=dict)
    """``{metric: amount}``: an evaluation counts for ``best`` only if none of these metrics (Col_obj, Col_scene,
    R_out, R_off_floor, R_misaligned, R_reach, R_walkable, mean_objects, mean_ground_objects: objects per room
    without lamps)
    is worse than the starting adapter's (evaluated at epoch 0) by more than its amount, e.g.
    ``{Col_obj: 0.02, R_out: 0.01, mean_ground_objects: 0.3}``."""
    seed: int = 0
    """Seeds everything (floor choice, policy noise, environment)."""
    num_threads: int = 0
    """torch threads (0: torch's default)."""
    device: str = "auto"
    """Where the policy runs: ``auto`` (the first CUDA GPU torch sees, else the CPU), ``cpu``, ``cuda`` or
    ``cuda:N``. The environment, rewards and the seeded noise stay on the CPU; a run may resume on another
    device."""
    out: str = "out/train/stage1_bedroom"
    """Run folder."""

    def __post_init__(self):
        check_device(self.device)
        for name in ("num_envs", "num_steps", "num_floors", "eval_floors", "epochs", "eval_every", "checkpoint_every"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be a positive whole number, got {value!r}")
        if not isinstance(self.eta, (int, float)) or not 0 <= self.eta <= 1:
            raise ValueError(f"eta must be a number in [0, 1] (0: deterministic DDIM, 1: DDPM-like), got {self.eta!r}")
        if self.required_objects and not self.init_adapter:
            raise ValueError("required_objects needs init_adapter: the adapter (stage 1) that samples each room first")
        if self.required_objects and "class" in self.adapt:
            raise ValueError("required_objects gives the rooms' classes, so adapt cannot hold class: use e.g. "
                             "adapt: [translation, size, yaw]")
        if self.adapt_classes and not self.required_objects and (not self.adapt or "class" in self.adapt):
            raise ValueError("adapt_classes needs the classes decided elsewhere: adapt without class (e.g. "
                             "[position, yaw]: each slot's class is then the reference's), or required_objects "
                             "(the rooms' classes given, e.g. [{classes: support_surface, add: nightstand}])")
        self.required()  # checked here, so a bad entry fails when the config is read

    def required(self) -> list:
        """``required_objects`` as :class:`iarcs_env.required_objects.RequiredObject` s of the room's classes."""
        from iarcs_env.required_objects import RequiredObject
        from iarcs_env.rooms import get_room

        if not isinstance(self.required_objects, list):
            raise ValueError(f"required_objects must be a list of mappings, got {self.required_objects!r}")
        classes = get_room(self.room).classes
        return [RequiredObject.from_dict(r, classes, f"required_objects[{i}]") for i, r in enumerate(self.required_objects)]


def load_train_config(path, **overrides) -> TrainConfig:
    return load_yaml_config(TrainConfig, path, **overrides)


def build_prior(cfg: TrainConfig):
    from .denoiser import ScenePrior

    if cfg.prior == "default":
        return ScenePrior.load_default(cfg.room)
    return ScenePrior.load(cfg.prior)


def training_floors(cfg: TrainConfig):
    from iarcs_env.datasets import load_layouts
    from iarcs_env.datasets.procedural import generate_layouts

    if cfg.floors.lower() in ("procedural", "synthetic"):
        layouts = generate_layouts(cfg.room, cfg.num_floors, seed=cfg.floor_seed)
    else:
        layouts = load_layouts(cfg.floors, cfg.room)[: cfg.num_floors]
    if not layouts:
        raise ValueError(f"no {cfg.room} floor plans in {cfg.floors}")
    return [lay.centred().floor for lay in layouts]


def build(cfg: TrainConfig, tensorboard_log: Path | None = None, task_reward=None, task_weight: float = 1.0):
    """(algorithm, policy, env) for a config; the algorithm is fresh (see :func:`run` for resuming).
    ``task_reward`` (stage 2) joins the composite reward as the term ``task``."""
    import gymnasium as gym

    import iarcs_env  # noqa: F401  (registers the environments)
    from rewards.composite import CompositeReward

    from .algorithms import get_algorithm
    from .policy import DiffusionPolicy

    prior = build_prior(cfg)
    policy = DiffusionPolicy(prior, adapter="scratch" if cfg.init_adapter else cfg.adapter, num_steps=cfg.num_steps,
                             eta=cfg.eta, adapted=cfg.adapt,
                             adapted_classes=() if cfg.init_adapter else cfg.adapt_classes)
    if cfg.init_adapter:  # the trained adapter starts as a copy of init_adapter
        path = stage1_adapter_path(cfg.room) if cfg.init_adapter == "default" else cfg.init_adapter
        src = policy.load_adapter(path, name="init")
        policy.add_adapter(cfg.adapter, init_from=src, adapted=cfg.adapt, required=cfg.required(),
                           adapted_classes=cfg.adapt_classes)
        policy.model.delete_adapter("scratch")
    policy.to(distributed.setup(cfg.device))  # before the optimiser is made over its parameters
    if task_reward is None:
        reward = CompositeReward.from_config(cfg.reward, stats=prior.stats)
    else:
        reward = CompositeReward.from_config({**cfg.reward, "task": task_weight}, stats=prior.stats,
                                             rewards={"task": task_reward})
    env = gym.make_vec(f"iARCS-{prior.spec.gym_name}-v0", num_envs=cfg.num_envs,
                       vectorization_mode="vector_entry_point", floors=training_floors(cfg), stats=prior.stats,
                       reward=reward, num_steps=cfg.num_steps)
    algo = get_algorithm(cfg.algorithm)(policy, env, tensorboard_log=tensorboard_log, seed=cfg.seed, **cfg.ddpo)
    return algo, policy, env


def run(cfg: TrainConfig, progress: bool = True, log=print):
    """Train (resuming ``cfg.out/checkpoint`` when it exists); returns the algorithm. Started by ``torchrun``,
    every process runs this and rank 0 alone writes the run folder (:mod:`agents.distributed`)."""
    from iarcs_env.env import default_floors

    from .callbacks import CheckpointCallback, EvalCallback, check_best_tolerance
    from .ddpo import DDPO

    if cfg.export not in ("last", "best"):
        raise ValueError(f"export must be 'last' or 'best', got {cfg.export!r}")
    check_best_tolerance(cfg.best_tolerance)
    if cfg.num_threads:
        torch.set_num_threads(cfg.num_threads)
    device = distributed.setup(cfg.device)
    main = distributed.is_main()
    if not main:
        progress, log = False, lambda *args, **kwargs: None
    processes = distributed.world_size()
    log(f"training on {device}" + (f", {processes} processes of {cfg.num_envs} scenes per rollout batch"
                                   if processes > 1 else ""))
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / CHECKPOINT_DIR
    saved = out / "config.yaml"
    if main and DDPO.latest_checkpoint(ckpt) and saved.exists():
        before = yaml.safe_load(saved.read_text())
        now = dataclasses.asdict(cfg)
        defaults = dataclasses.asdict(TrainConfig())  # a key missing from an older run's config had its default
        changed = [k for k in now if k not in ("epochs", "out", "eval_every", "checkpoint_every", "export",
                                               "best_tolerance", "device")
                   and before.get(k, defaults[k]) != now[k]]
        if changed:
            raise ValueError(f"{out} holds a run with other settings ({', '.join(changed)}); use another out folder")
    resume = DDPO.latest_checkpoint(ckpt)
    if main:
        saved.write_text(yaml.safe_dump(dataclasses.asdict(cfg), sort_keys=False))
    task = None
    if cfg.task:
        task = _share_task(cfg, _setup_task(cfg, out, resume, log) if main else None)
    torch.manual_seed(cfg.seed)  # the adapter's initialisation does not depend on what ran before in the process
    algo, policy, env = build(cfg, tensorboard_log=out / "tb", **({} if task is None else task["build"]))
    if resume:
        algo = DDPO.load(ckpt, policy, env, tensorboard_log=out / "tb")
        log(f"resuming {out} at epoch {algo.epoch}")
    eval_floors = default_floors(cfg.room, count=cfg.eval_floors, seed=cfg.eval_seed)
    # after each epoch, in this order: reflection, evaluation, then the checkpoint, so that a checkpoint holds
    # everything its epoch did; what a killed run did after its last checkpoint is forgotten and redone
    callbacks = [task["reflection"]] if task is not None and task["reflection"] is not None else []
    metrics = {} if task is None else task["metrics"]
    best_key = next(iter(metrics), "reward")  # the task's success rate, if it has a checker
    evaluation = EvalCallback(eval_floors, eval_freq=cfg.eval_every, log_path=out / "eval.jsonl", verbose=1,
                              scene_metrics=metrics, best_path=out / BEST_DIR, best_key=best_key,
                              best_tolerance=cfg.best_tolerance)
    if main:  # what a killed attempt logged after its last checkpoint (or without one) is redone
        evaluation.forget_after(algo.epoch if resume else -1)
    callbacks += [evaluation, CheckpointCallback(cfg.checkpoint_every, ckpt)]  # (DDPO runs them on rank 0 only)
    total = cfg.epochs * cfg.num_envs * cfg.num_steps * algo.config.num_batches_per_epoch
    try:
        algo.learn(total, callback=callbacks, progress_bar=progress)
    finally:
        if task is not None:
            task["reward"].sandbox.close()
    if not main:
        return algo
    export_adapter(cfg, policy, out, log)
    if task is not None:
        from .stage2 import save_task_outputs

        log(f"reward program: {save_task_outputs(out, task['memory'], task['agent']) / 'program.py'}")
    return algo


def export_adapter(cfg: TrainConfig, policy, out: Path, log=print) -> Path:
    """Write the run's adapter to ``out/adapters/<name>``: the last one, or with ``export: best`` the best kept."""
    import shutil

    from .callbacks import BEST_FILE

    best = out / BEST_DIR
    dest = out / ADAPTERS_DIR / cfg.adapter
    if cfg.export == "best" and (best / BEST_FILE).exists():
        shutil.rmtree(dest, ignore_errors=True)
        shutil.copytree(best / cfg.adapter, dest)
        info = json.loads((best / BEST_FILE).read_text())
        log(f"adapter: {dest} (peft format), the best evaluation's: {info['key']} {info['value']:.4g} at epoch "
            f"{info['epoch']}; TensorBoard: {out / 'tb'}")
    else:
        policy.save_adapter(out / ADAPTERS_DIR)
        if cfg.export == "best":
            log(f"warning: no evaluation was kept as best (none within best_tolerance {cfg.best_tolerance}); "
                "exporting the last epoch's adapter")
        log(f"adapter: {dest} (peft format), the last epoch's; TensorBoard: {out / 'tb'}")
    return dest


def _setup_task(cfg: TrainConfig, out: Path, resume: Path | None, log) -> dict:
    """Stage 2: the sandboxed task reward, the agent, the memory and the reflection callback."""
    from .stage2 import MEMORY_FILE, ReflectionCallback, setup_task_reward, task_config

    tcfg = task_config(cfg.task)
    if resume:  # reflections made after the checkpoint we resume from never happened
        from rewards.memory import EvolutionMemory

        epoch = json.loads((resume / "trainer.json").read_text())["epoch"]
        EvolutionMemory.open(out / MEMORY_FILE, tcfg.resolved_constraint(), cfg.room).forget_after(epoch)
    reward, agent, memory, proposal = setup_task_reward(tcfg, cfg.room, out, log=log)
    checker = None
    metrics = {}
    if tcfg.checker:
        from iarcs_env.tasks import get_task

        checker = get_task(tcfg.checker).check
        metrics[f"task_success_{tcfg.checker}"] = lambda scenes: float(np.mean(checker(scenes)))
    reflection = ReflectionCallback(agent, reward, memory, every=tcfg.reflect_every, checker=checker,
                                    fixed_weight=tcfg.weight)
    return {"build": {"task_reward": reward, "task_weight": tcfg.weight or proposal.weight}, "reward": reward,
            "agent": agent, "memory": memory, "metrics": metrics, "reflection": reflection}


def _share_task(cfg: TrainConfig, task: dict | None) -> dict:
    """Under ``torchrun``: rank 0 set the task up (``task``); the other ranks run its reward program in their own
    sandboxes and leave reflection to rank 0, which sends them each new program (``DDPO._sync_reward``)."""
    if distributed.world_size() == 1:
        return task
    code, weight = distributed.broadcast_object((task["reward"].code, task["build"]["task_weight"]) if task else None)
    if task is not None:
        return task
    from rewards.sandbox import SandboxedReward

    reward = SandboxedReward(code, room=cfg.room)
    return {"build": {"task_reward": reward, "task_weight": weight}, "reward": reward, "metrics": {},
            "reflection": None}


def load_trained_policy(run_dir: str | Path):
    """The policy of a finished (or interrupted) run folder: its prior with its adapter active."""
    from .policy import DiffusionPolicy

    run_dir = Path(run_dir)
    if not (run_dir / "config.yaml").exists():
        raise FileNotFoundError(f"{run_dir} is not a training run folder (config.yaml missing)")
    cfg = dataclass_from_dict(TrainConfig, yaml.safe_load((run_dir / "config.yaml").read_text()), str(run_dir))
    policy = DiffusionPolicy(build_prior(cfg), adapter="scratch", num_steps=cfg.num_steps, eta=cfg.eta)
    from .ddpo import DDPO

    ckpt = DDPO.latest_checkpoint(run_dir / CHECKPOINT_DIR) or run_dir / CHECKPOINT_DIR
    for folder in (run_dir / ADAPTERS_DIR / cfg.adapter, ckpt / "adapter" / cfg.adapter):
        if (folder / "adapter_config.json").exists():
            policy.load_adapter(folder, cfg.adapter)
            return policy, cfg
    raise FileNotFoundError(f"no adapter {cfg.adapter!r} in {run_dir} (train it first)")


def stage1_adapter_path(room: str = "bedroom") -> Path:
    """The stage-1 adapter shipped with the small prior of ``room`` (peft format)."""
    from iarcs_env.rooms import get_room

    return Path(__file__).parent / "checkpoints" / f"{get_room(room).name}_small_stage1" / "stage1"


def shipped_task_dir(room: str, task: str) -> Path:
    """A paper task's shipped stage-2 adapter, as an ``iarcs generate`` library entry: ``adapter/`` (peft),
    ``reward/`` (the program it was trained with) and ``constraint.txt``."""
    from iarcs_env.rooms import get_room

    return Path(__file__).parent / "checkpoints" / f"{get_room(room).name}_small_tasks" / task


def shipped_adapter_path(room: str, name: str) -> Path:
    """A LoRA adapter shipped with the small prior of ``room`` (peft format): ``stage1``, or a paper task's
    stage-2 adapter by the task's name."""
    return stage1_adapter_path(room) if name == "stage1" else shipped_task_dir(room, name) / "adapter"


def shipped_adapters(room: str) -> list[str]:
    """The names of the adapters shipped for ``room``: ``stage1`` first, then the task adapters."""
    from iarcs_env.tasks import TASKS

    return [name for name in ["stage1", *TASKS]
            if (shipped_adapter_path(room, name) / "adapter_config.json").exists()]


def load_stage1_policy(room: str = "bedroom", num_steps: int = 20):
    """The shipped prior with its shipped stage-1 adapter active (stage 2 starts from it)."""
    from .denoiser import ScenePrior
    from .policy import DiffusionPolicy

    path = stage1_adapter_path(room)
    if not (path / "adapter_config.json").exists():
        raise FileNotFoundError(f"no stage-1 adapter shipped for {room} (looked in {path}); train one with "
                                "iarcs train --config experiments/stage1_bedroom_quick.yaml")
    policy = DiffusionPolicy(ScenePrior.load_default(room), adapter="scratch", num_steps=num_steps)
    policy.load_adapter(path, "stage1")
    return policy
