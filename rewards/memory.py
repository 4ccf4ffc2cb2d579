"""The reward evolution memory (paper section 3.4): every reward program a run tried, with the reasoning
behind it and what happened when training used it. One JSON file per run, rewritten atomically after
every change, so that a resumed run continues with the same program and the agent keeps its history.

    memory = EvolutionMemory.open(run_dir / "reward_memory.json", constraint, room)
    memory.record("synthesize", epoch=0, proposal=p, accepted=True)
    ...
    memory.current()        # the reward program in use (the last accepted one)
    memory.history()        # [{"proposal": {...}, "outcome": {...}}, ...] for the agent's reflection
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from .proposal import RewardProposal


class EvolutionMemory:
    """Entries, oldest first: ``{"kind": "synthesize"|"reflect", "stage", "epoch", "proposal", "accepted",
    "message", "outcomes"}``. ``outcomes`` lists the training feedback (one window per reflection) gathered
    while the proposal was the reward in use."""

    def __init__(self, path: str | Path, constraint: str, room: str, entries: list[dict] | None = None):
        self.path = Path(path)
        self.constraint = constraint
        self.room = room
        self.entries: list[dict] = list(entries or [])

    @classmethod
    def open(cls, path: str | Path, constraint: str, room: str) -> "EvolutionMemory":
        """Load the memory at ``path`` (it must be for the same constraint), or start an empty one."""
        path = Path(path)
        if not path.exists():
            return cls(path, constraint, room)
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise ValueError(f"{path} is not a valid reward memory ({err}); move it away to start afresh") from None
        if data.get("constraint") != constraint:
            raise ValueError(f"{path} holds the memory of another constraint ({data.get('constraint')!r}); "
                             "use another run folder")
        return cls(path, constraint, data.get("room", room), data.get("entries", []))

    def save(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.write_text(json.dumps({"constraint": self.constraint, "room": self.room, "entries": self.entries},
                                  indent=1))
        os.replace(tmp, self.path)

    def record(self, kind: str, epoch: int, proposal: RewardProposal, accepted: bool, message: str = "",
               outcome: dict[str, Any] | None = None) -> dict:
        """Append one attempt (and save). ``outcome``, the feedback on the program in use until now, joins
        that program's entry."""
        if outcome is not None:
            last = self.last_accepted_entry()
            if last is not None:
                last["outcomes"].append(outcome)
        entry = {"kind": kind, "stage": self.stages(), "epoch": int(epoch), "time": time.time(),
                 "proposal": proposal.to_dict(), "accepted": bool(accepted), "message": message, "outcomes": []}
        self.entries.append(entry)
        self.save()
        return entry

    def stages(self) -> int:
        """Reflections recorded so far (the next reflection's stage index)."""
        return sum(e["kind"] == "reflect" for e in self.entries)

    def last_accepted_entry(self) -> dict | None:
        return next((e for e in reversed(self.entries) if e["accepted"]), None)

    def current(self) -> RewardProposal | None:
        """The reward program in use: the last accepted proposal (None before the first synthesis)."""
        entry = self.last_accepted_entry()
        return RewardProposal.from_dict(entry["proposal"]) if entry else None

    def history(self) -> list[dict]:
        """Every attempt as ``{"epoch", "proposal", "accepted", "message", "outcome"}`` for reflection
        (``outcome``: the feedback windows while it was in use; empty for rejected attempts)."""
        return [{"epoch": e["epoch"], "proposal": e["proposal"], "accepted": e["accepted"], "message": e["message"],
                 "outcome": e["outcomes"]} for e in self.entries]

    def task_success_history(self) -> list[float]:
        """Task success per epoch over the whole run, oldest first (from the recorded feedback windows)."""
        return [s for e in self.entries for w in e["outcomes"] for s in w.get("task_success", [])]

    def forget_after(self, epoch: int) -> None:
        """Drop attempts (and feedback) recorded after ``epoch`` (a resumed run restarts from an earlier
        checkpoint)."""
        kept = [e for e in self.entries if e["epoch"] <= epoch]
        for e in kept:
            e["outcomes"] = [w for w in e["outcomes"] if w.get("epoch", 0) <= epoch]
        self.entries = kept
        self.save()
