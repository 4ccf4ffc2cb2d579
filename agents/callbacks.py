"""Training callbacks with the Stable-Baselines surface: subclass :class:`BaseCallback` and override the
hooks; ``_on_step`` (called after every epoch of rollouts and updates) returns False to stop training."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from .config import read_jsonl

if TYPE_CHECKING:
    from .ddpo import DDPO


BEST_FILE = "best.json"
"""Beside the best adapter kept by :class:`EvalCallback`: its epoch, the metric and its value."""

LOWER_IS_BETTER = ("Col_obj", "Col_scene", "R_out", "R_off_floor", "R_misaligned")
HIGHER_IS_BETTER = ("R_reach", "R_walkable", "mean_objects", "mean_ground_objects")
"""The scene metrics of a training evaluation (``DDPO.evaluate``), by the direction in which they improve;
``best_tolerance`` may guard any of them."""


def check_best_tolerance(tolerance: dict) -> dict[str, float]:
    """``{metric: allowed worsening}`` with known metric names and non-negative numbers, else a clear error."""
    known = LOWER_IS_BETTER + HIGHER_IS_BETTER
    for name, amount in tolerance.items():
        if name not in known:
            raise ValueError(f"best_tolerance: unknown metric {name!r}; choose from {', '.join(known)}")
        if not isinstance(amount, (int, float)) or amount < 0:
            raise ValueError(f"best_tolerance: {name} must be a number >= 0 (how much worse than at the start "
                             f"it may get), got {amount!r}")
    return {k: float(v) for k, v in tolerance.items()}


def worsening(metrics: dict, start: dict, name: str) -> float:
    """How much worse ``name`` is in ``metrics`` than in ``start`` (negative when it improved)."""
    change = metrics[name] - start[name]
    return change if name in LOWER_IS_BETTER else -change


#: The furniture-loss warning fires when furniture per room falls below this share of the first evaluation's.
FURNITURE_KEPT_WARNING = 0.5


def furniture_loss_warning(first: dict, now: dict) -> str | None:
    """A warning when ground objects per room (``mean_ground_objects``: furniture, lamps excluded) fell below
    :data:`FURNITURE_KEPT_WARNING` of the first logged evaluation's, else None. Collisions, out-of-bound
    objects and blocked paths all vanish with the furniture, so every physical reward can be won by
    emptying the room (docs/results/stage1_bedroom_quick.md)."""
    before, after = first.get("mean_ground_objects"), now.get("mean_ground_objects")
    if before is None or after is None or before <= 0 or after >= FURNITURE_KEPT_WARNING * before:
        return None
    return (f"warning: furniture per room fell from {before:.2f} (epoch {first.get('epoch', '?')}) to {after:.2f} "
            f"(epoch {now.get('epoch', '?')}): the policy is emptying the rooms, which wins the collision, boundary "
            "and accessibility rewards without placing anything better. Add a class term to the reward "
            "(class_presence), or keep the exported adapter from doing so with best_tolerance: "
            "{mean_ground_objects: ...} (docs/results/stage1_bedroom_quick.md)")


class BaseCallback:
    """Hooks: ``_on_training_start``, ``_on_rollout_end`` (rollout statistics in ``self.locals``),
    ``_on_step`` (after each epoch; return False to stop) and ``_on_training_end``."""

    def __init__(self, verbose: int = 0):
        self.verbose = verbose
        self.model: "DDPO | None" = None
        self.locals: dict = {}

    def init_callback(self, model: "DDPO") -> None:
        self.model = model

    @property
    def num_timesteps(self) -> int:
        return self.model.num_timesteps

    @property
    def n_calls(self) -> int:
        return self.model.epoch

    def on_training_start(self) -> None:
        self._on_training_start()

    def on_rollout_end(self, stats: dict) -> None:
        self.locals = stats
        self._on_rollout_end()

    def on_step(self, stats: dict) -> bool:
        self.locals = stats
        return bool(self._on_step())

    def on_training_end(self) -> None:
        self._on_training_end()

    def _on_training_start(self) -> None: ...

    def _on_rollout_end(self) -> None: ...

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None: ...


class CallbackList(BaseCallback):
    def __init__(self, callbacks: Sequence[BaseCallback]):
        super().__init__()
        self.callbacks = list(callbacks)

    def init_callback(self, model) -> None:
        super().init_callback(model)
        for c in self.callbacks:
            c.init_callback(model)

    def on_training_start(self) -> None:
        for c in self.callbacks:
            c.on_training_start()

    def on_rollout_end(self, stats: dict) -> None:
        for c in self.callbacks:
            c.on_rollout_end(stats)

    def on_step(self, stats: dict) -> bool:
        return all([c.on_step(stats) for c in self.callbacks])  # every callback sees every step

    def on_training_end(self) -> None:
        for c in self.callbacks:
            c.on_training_end()


def as_callback(callback) -> BaseCallback:
    """None, a callback, a list of callbacks, or a function ``f(locals, model) -> bool``."""
    if callback is None:
        return BaseCallback()
    if isinstance(callback, BaseCallback):
        return callback
    if isinstance(callback, (list, tuple)):
        return CallbackList([as_callback(c) for c in callback])
    if callable(callback):
        return _FunctionCallback(callback)
    raise TypeError(f"callback must be a BaseCallback, a list of them or a function; got {type(callback).__name__}")


class _FunctionCallback(BaseCallback):
    def __init__(self, fn):
        super().__init__()
        self.fn = fn

    def _on_step(self) -> bool:
        out = self.fn(self.locals, self.model)
        return True if out is None else bool(out)


class CheckpointCallback(BaseCallback):
    """Save the whole training state (adapter, optimiser, counters, random states) every ``save_freq``
    epochs to ``save_path`` (atomically: a crash never leaves a half-written checkpoint)."""

    def __init__(self, save_freq: int, save_path: str | Path, verbose: int = 0):
        super().__init__(verbose)
        if save_freq < 1:
            raise ValueError(f"save_freq must be at least 1 epoch, got {save_freq}")
        self.save_freq = save_freq
        self.save_path = Path(save_path)

    def _on_step(self) -> bool:
        if self.model.epoch % self.save_freq == 0:
            self.model.save(self.save_path)
            if self.verbose:
                print(f"checkpoint: epoch {self.model.epoch} -> {self.save_path}")
        return True

    def _on_training_end(self) -> None:
        self.model.save(self.save_path)


class EvalCallback(BaseCallback):
    """Every ``eval_freq`` epochs: sample scenes on fixed evaluation floor plans, compute the paper's
    metrics and the reward, log them (and a grid of top-down renders) to TensorBoard, and append them to
    ``log_path`` (JSON lines) when given. ``scene_metrics`` ``{name: f(SceneBatch) -> float}`` adds metrics
    (e.g. a task's success rate). With ``best_path``, the adapter of the evaluation with the highest
    ``best_key`` so far is kept there (peft format, with ``best.json``: its epoch and value), as
    Stable-Baselines' ``best_model_save_path``; a resumed run carries on from the best value saved.
    ``best_tolerance`` ``{metric: amount}`` (e.g. ``{"Col_obj": 0.02, "mean_objects": 0.3}``) also evaluates
    the starting adapter (epoch 0 in ``log_path``) and keeps only evaluations where no listed metric is worse
    than there by more than its amount: a task's success bought by collisions or emptied rooms is never the
    best."""

    def __init__(self, floors, eval_freq: int = 5, n_render: int = 16, seed: int = 0,
                 log_path: str | Path | None = None, scene_metrics: dict | None = None, verbose: int = 0,
                 best_path: str | Path | None = None, best_key: str = "reward", best_tolerance: dict | None = None):
        super().__init__(verbose)
        self.scene_metrics = scene_metrics
        self.floors = list(floors)
        self.eval_freq = eval_freq
        self.n_render = n_render
        self.seed = seed
        self.log_path = Path(log_path) if log_path else None
        self.history: list[dict] = []
        self.best_path = Path(best_path) if best_path else None
        self.best_key = best_key
        saved = self.best_path / BEST_FILE if self.best_path else None
        self.best_value = json.loads(saved.read_text())["value"] if saved and saved.exists() else -np.inf
        self.best_tolerance = check_best_tolerance(best_tolerance or {})
        self.start: dict | None = None
        """The starting adapter's evaluation, the reference of ``best_tolerance``."""
        self.first_eval: dict | None = None
        self.warned_furniture = False
        """Whether the furniture-loss warning (:func:`furniture_loss_warning`) was printed."""

    def _on_training_start(self) -> None:
        if not self.best_tolerance:
            return
        logged = self._logged()
        self.start = next((row for row in logged if row["epoch"] == 0), None)
        if self.start is None and self.model.epoch == 0:
            self.start = self._evaluate()
        if self.start is None:
            raise ValueError(f"best_tolerance needs the starting adapter's evaluation (epoch 0), which "
                             f"{self.log_path} of this resumed run lacks; drop best_tolerance or start a new run")

    def _on_step(self) -> bool:
        if self.model.epoch % self.eval_freq == 0:
            metrics = self._evaluate()
            if self.best_path and metrics[self.best_key] > self.best_value and self._within_tolerance(metrics):
                self.best_value = metrics[self.best_key]
                self._save_best()
        return True

    def _evaluate(self) -> dict:
        metrics = self.model.evaluate(self.floors, seed=self.seed, n_render=self.n_render,
                                      scene_metrics=self.scene_metrics)
        self.history.append(metrics)
        if self.log_path:
            with open(self.log_path, "a") as f:
                f.write(json.dumps({"epoch": self.model.epoch, "num_timesteps": self.num_timesteps, **metrics}) + "\n")
        if self.verbose:
            print(f"eval at epoch {self.model.epoch}: " + ", ".join(f"{k}={v:.4g}" for k, v in metrics.items()))
        now = {"epoch": self.model.epoch, **metrics}
        if self.first_eval is None:  # the run's first evaluation: the log's first row when resumed
            logged = self._logged()
            self.first_eval = logged[0] if logged else now
        if not self.warned_furniture:
            message = furniture_loss_warning(self.first_eval, now)
            if message:
                print(message, file=sys.stderr)
                self.warned_furniture = True
        return metrics

    def forget_after(self, epoch: int) -> None:
        """Drop logged evaluations of epochs after ``epoch``: a run resumed from that checkpoint redoes them."""
        if self.log_path and self.log_path.exists():
            kept = [row for row in self._logged() if row.get("epoch", 0) <= epoch]
            tmp = self.log_path.with_name(self.log_path.name + ".tmp")
            tmp.write_text("".join(json.dumps(row) + "\n" for row in kept))
            tmp.replace(self.log_path)

    def _logged(self) -> list[dict]:
        if not (self.log_path and self.log_path.exists()):
            return []
        return read_jsonl(self.log_path, warn=lambda message: print(message, file=sys.stderr))

    def _within_tolerance(self, metrics: dict) -> bool:
        over = [f"{name} {worsening(metrics, self.start, name):+.3g} (allowed {amount:g})"
                for name, amount in self.best_tolerance.items() if worsening(metrics, self.start, name) > amount]
        if over and self.verbose:
            print("not kept as best: worse than at the start by " + ", ".join(over))
        return not over

    def _save_best(self) -> None:
        """Write the adapter beside, then swap it in: a kill never leaves a half-written best adapter."""
        import shutil

        tmp = self.best_path.with_name(self.best_path.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        self.model.policy.save_adapter(tmp)
        (tmp / BEST_FILE).write_text(json.dumps({"epoch": self.model.epoch, "key": self.best_key,
                                                 "value": self.best_value}))
        shutil.rmtree(self.best_path, ignore_errors=True)
        tmp.rename(self.best_path)


class StopTrainingOnRewardThreshold(BaseCallback):
    """Stop once the mean rollout reward reaches ``reward_threshold``."""

    def __init__(self, reward_threshold: float, verbose: int = 0):
        super().__init__(verbose)
        self.reward_threshold = reward_threshold

    def _on_step(self) -> bool:
        keep_going = self.locals.get("reward_mean", -np.inf) < self.reward_threshold
        if not keep_going and self.verbose:
            print(f"stopping: mean reward {self.locals['reward_mean']:.3f} >= {self.reward_threshold}")
        return keep_going


class StopTrainingOnKL(BaseCallback):
    """Stop when the policy moved too far in one epoch (approximate KL above ``max_kl``)."""

    def __init__(self, max_kl: float, verbose: int = 0):
        super().__init__(verbose)
        self.max_kl = max_kl

    def _on_step(self) -> bool:
        kl = abs(float(self.locals.get("approx_kl", 0.0)))
        if kl > self.max_kl and self.verbose:
            print(f"stopping: approx KL {kl:.2e} > {self.max_kl:.2e}")
        return kl <= self.max_kl


def render_grid_tensor(images: Sequence[np.ndarray], cols: int = 4) -> torch.Tensor:
    """(3, H, W) uint8 tensor of tiled renders for TensorBoard's add_image."""
    from iarcs_env.render import image_grid

    return torch.from_numpy(np.array(image_grid(list(images), cols=cols))).permute(2, 0, 1)
