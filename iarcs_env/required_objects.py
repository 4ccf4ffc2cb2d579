"""Objects a task needs in every room, and the class lists that give a room them.

A relational task (two nightstands beside the bed, a TV stand facing it, a chair at the desk) can only hold in a
room that has its objects. The prior gives them together in a fraction of the rooms (issue 37's co-occurrence
rates), and RL does not add what the prior rarely samples: a task adapter that tried relabelled the room's other
furniture instead (docs/results/stage2_tasks.md). So a task may name its objects: a room is first sampled as stage 1
would, the objects it lacks are added to its class list, and the room is sampled again with that class list given
(only the geometry of every object is sampled; :meth:`agents.denoiser.ScenePrior.with_classes`). The task adapter
may then only move, turn or resize objects. Nothing is added to a room that already has them, so the class
frequencies move only by what the task needs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch

from .relations import CLASS_GROUPS, class_mask


@dataclass(frozen=True)
class RequiredObject:
    """At least ``at_least`` objects of ``classes`` (class names or :data:`relations.CLASS_GROUPS` names) in every
    room; a room with fewer gets objects of class ``add`` (default: ``classes`` when it names one class). With
    ``share`` < 1 only that fraction of the rooms, drawn per room, gets what it lacks (one draw per room for all
    entries: the entries of equal share come together), for a task whose objects in every room would move the
    class frequencies too far from the data's."""

    classes: tuple[str, ...]
    at_least: int = 1
    add: str = ""
    share: float = 1.0

    @classmethod
    def from_dict(cls, value, vocabulary: Sequence[str], where: str = "required_objects") -> "RequiredObject":
        """One entry of a config's ``required_objects``, e.g. ``{classes: bed, at_least: 1, add: double_bed}``,
        checked against the room's class list (``vocabulary``)."""
        example = "{classes: nightstand, at_least: 2} or {classes: bed, add: double_bed}"
        keys = {"classes", "at_least", "add", "share"}
        if not isinstance(value, dict) or set(value) - keys or "classes" not in value:
            raise ValueError(f"{where}: expected a mapping like {example}, got {value!r}")
        names = (value["classes"],) if isinstance(value["classes"], str) else tuple(value["classes"])
        if not names or not all(isinstance(n, str) for n in names):
            raise ValueError(f"{where}: classes must be a class or group name or a list of them, got {value['classes']!r}")
        try:
            matching = class_mask(torch.arange(len(vocabulary))[None], list(vocabulary), names)[0]
        except ValueError as err:
            raise ValueError(f"{where}: {err}") from None
        if not matching.any():
            raise ValueError(f"{where}: {'/'.join(names)} names no object class of this room type")
        at_least = value.get("at_least", 1)
        if not isinstance(at_least, int) or isinstance(at_least, bool) or at_least < 1:
            raise ValueError(f"{where}: at_least must be a positive whole number, got {at_least!r}")
        add = value.get("add") or (names[0] if len(names) == 1 and names[0] not in CLASS_GROUPS else "")
        if not add:
            raise ValueError(f"{where}: say which class to add to a room short of {'/'.join(names)} (add: CLASS)")
        if add not in vocabulary or not matching[list(vocabulary).index(add)]:
            raise ValueError(f"{where}: add: {add!r} must be a class of this room type that {'/'.join(names)} counts")
        share = value.get("share", 1.0)
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0 < share <= 1:
            raise ValueError(f"{where}: share must be a fraction of the rooms in (0, 1], got {share!r}")
        return cls(names, at_least, add, float(share))

    def to_dict(self) -> dict:
        return {"classes": list(self.classes), "at_least": self.at_least, "add": self.add, "share": self.share}


def with_required(labels: torch.Tensor, vocabulary: Sequence[str], required: Sequence[RequiredObject],
                  generator: torch.Generator | None = None) -> torch.Tensor:
    """(B, N) class indices (``len(vocabulary)``: an empty slot) with the missing required objects put into
    empty slots, in the canonical slot order (sorted by class index, empty slots last). A room with no empty slot
    left keeps what it has. An entry with ``share`` < 1 fills only the rooms whose uniform draw (one per room,
    from ``generator``; drawn only when some share is below 1) is below its share."""
    vocabulary = list(vocabulary)
    empty = len(vocabulary)
    out = labels.clone()
    if any(r.share < 1 for r in required):
        draw = torch.rand(len(labels), generator=generator,
                          device=generator.device if generator is not None else "cpu").to(labels.device)
    else:
        draw = torch.zeros(len(labels), device=labels.device)
    for req in required:
        have = class_mask(out, vocabulary, req.classes).sum(1)
        for b in torch.nonzero((have < req.at_least) & (draw < req.share)).flatten().tolist():
            free = torch.nonzero(out[b] == empty).flatten()[:req.at_least - int(have[b])]
            out[b, free] = vocabulary.index(req.add)
    return out.sort(dim=1).values
