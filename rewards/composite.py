"""A weighted sum of registered rewards that also returns each term, so that training can log them and
reward reflection can reason about each one.

    reward = CompositeReward({"collision": 1.0, "boundary": 1.0, "accessibility": 0.5, "object_count": 0.5},
                             stats=stats, accessibility={"cell": 0.05})
    total, terms = reward(batch)        # total (B,), terms {"collision": (B,), ...} (unweighted values)

Keyword arguments whose name is a reward's name carry options for that reward alone; any other keyword
(``stats`` for instance) goes to every reward whose function accepts it.
"""

from __future__ import annotations

import inspect
from typing import Callable, Mapping

import torch

from iarcs_env.scene import SceneBatch

from .universal import REWARDS, get_reward


class CompositeReward:
    """``total = sum_k weights[k] * terms[k]`` over registered (or given) reward functions."""

    def __init__(self, weights: Mapping[str, float], rewards: Mapping[str, Callable] | None = None, **kwargs):
        if not weights:
            raise ValueError("a composite reward needs at least one term, e.g. {'collision': 1.0}")
        self.weights = {str(k): float(v) for k, v in weights.items()}
        self.functions: dict[str, Callable] = {}
        self.options: dict[str, dict] = {}
        extra = dict(rewards or {})
        for name in self.weights:
            fn = extra[name] if name in extra else get_reward(name)
            self.functions[name] = fn
            params = inspect.signature(fn).parameters
            takes_any = any(p.kind is p.VAR_KEYWORD for p in params.values())
            opts = {k: v for k, v in kwargs.items()
                    if k not in REWARDS and k not in extra and (takes_any or k in params)}
            own = kwargs.get(name, {})
            if not isinstance(own, Mapping):
                raise ValueError(f"options for reward {name!r} must be a mapping, got {own!r}")
            unknown = [k for k in own if not takes_any and k not in params]
            if unknown:
                raise ValueError(f"reward {name!r} has no option(s) {', '.join(unknown)}; "
                                 f"it takes {', '.join(p for p in params if p != 'batch')}")
            opts.update(own)
            self.options[name] = opts

    #: Stage-1 weights of the universal rewards (paper section 3.3).
    UNIVERSAL_WEIGHTS = {"collision": 1.0, "boundary": 1.0, "accessibility": 0.5, "object_count": 0.5}

    @classmethod
    def universal(cls, stats=None, **kwargs) -> "CompositeReward":
        """The stage-1 composite of the four universal rewards; ``stats`` give the object-count prior.

        The object-count term is per scene (the training log-probability of its count): the batch-level KL
        gives every scene of a batch the same value, so after per-floor advantage normalisation it carries
        no signal, and DDPO then learns to empty rooms (which never collide nor leave the floor)."""
        kwargs.setdefault("object_count", {"mode": "log_prob"})
        return cls(dict(cls.UNIVERSAL_WEIGHTS), stats=stats, **kwargs)

    @classmethod
    def from_config(cls, config: Mapping, **kwargs) -> "CompositeReward":
        """Build from a config dict, either ``{"weights": {name: w}, "options": {name: {...}}}`` or
        ``{name: w}`` or ``{name: {"weight": w, **options}}`` (mixable). ``kwargs`` (e.g. ``stats``) are
        shared options."""
        config = dict(config)
        weights = dict(config.pop("weights", {}) or {})
        options = {k: dict(v) for k, v in (config.pop("options", {}) or {}).items()}
        for name, value in config.items():
            if isinstance(value, Mapping):
                value = dict(value)
                if "weight" not in value:
                    raise ValueError(f"reward {name!r} in the config needs a 'weight'")
                weights[name] = value.pop("weight")
                options.setdefault(name, {}).update(value)
            else:
                weights[name] = value
        return cls(weights, **options, **kwargs)

    def __call__(self, batch: SceneBatch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        terms = {name: fn(batch, **self.options[name]) for name, fn in self.functions.items()}
        total = torch.zeros(batch.batch_size, dtype=torch.float32, device=batch.labels.device)
        for name, value in terms.items():
            total = total + self.weights[name] * value.to(total)
        return total, terms

    def __repr__(self) -> str:
        return "CompositeReward(" + ", ".join(f"{k}={v:g}" for k, v in self.weights.items()) + ")"
