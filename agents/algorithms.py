"""The RL algorithms a training config can name (``algorithm:``), by name: DDPO-IS and DDPO-SF
(:mod:`agents.ddpo`), the physics gradient (:mod:`agents.physics_gradient`; in stage 2 it also follows the task
reward's own gradient, taken in the reward's sandbox) and descent imitation (:mod:`agents.descent_imitation`).
Other algorithms plug in by subclassing :class:`agents.ddpo.DDPO` and being added here."""

from __future__ import annotations

from .ddpo import DDPO, DDPOSF
from .descent_imitation import DescentImitation
from .physics_gradient import PhysicsGradient

ALGORITHMS: dict[str, type[DDPO]] = {cls.name: cls for cls in (DDPO, DDPOSF, PhysicsGradient, DescentImitation)}


def get_algorithm(name: str) -> type[DDPO]:
    """``ddpo`` / ``ddpo-is``, ``ddpo-sf``, ``physics-gradient`` or ``descent-imitation`` (case-insensitive)."""
    key = name.upper().replace("_", "-")
    key = {"DDPO": "DDPO-IS"}.get(key, key)
    if key not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {name!r}; choose one of: ddpo (= ddpo-is), ddpo-sf, physics-gradient, "
                         "descent-imitation")
    return ALGORITHMS[key]
