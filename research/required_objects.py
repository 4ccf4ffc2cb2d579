"""Does the prior place a task's objects well once they are in the room? Sample the stage-1 rooms, add the objects a
task needs to the rooms that lack them (their class lists only), then sample the rooms again with those class lists
given (RePaint-style: the class part of x_t is the given classes noised to t at every step; the geometry of every
object is sampled afresh) and write the result for ``iarcs evaluate``.

    .venv/bin/python research/required_objects.py --floors FLOORS.json --scenes S1.json --task two_nightstands \
        --out out/req/tn.json
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.train import load_stage1_policy  # noqa: E402
from iarcs_env.datasets import load_layouts, save_layouts  # noqa: E402
from iarcs_env.relations import CLASS_GROUPS  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402

#: What each task needs: (classes any of which counts, how many, the class added when short).
NEEDS = {
    "two_nightstands": [(CLASS_GROUPS["bed"], 1, "double_bed"), (("nightstand",), 2, "nightstand")],
    "tv_from_bed": [(CLASS_GROUPS["bed"], 1, "double_bed"), (("tv_stand",), 1, "tv_stand")],
    "study_zone": [(("desk",), 1, "desk"), (("chair", "stool", "dressing_chair"), 1, "chair")],
}


def completed_labels(labels: list[str], task: str) -> list[str]:
    """``labels`` with the task's missing objects added."""
    out = list(labels)
    for names, count, added in NEEDS[task]:
        out += [added] * max(0, count - sum(lab in names for lab in out))
    return out


def class_indices(rooms: list[list[str]], vocabulary: list[str], num_slots: int) -> torch.Tensor:
    """(B, N) class indices in the canonical slot order (sorted by class index, empty last)."""
    empty = len(vocabulary) - 1
    out = torch.full((len(rooms), num_slots), empty, dtype=torch.long)
    for b, labels in enumerate(rooms):
        idx = sorted(vocabulary.index(lab) for lab in labels)[:num_slots]
        out[b, :len(idx)] = torch.tensor(idx)
    return out


def sample_with_classes(policy, floors, classes: torch.Tensor, seed: int, batch_size: int = 100) -> SceneBatch:
    """Rooms sampled with the policy, their classes given: the class part of x_t replaced by the classes' one-hot
    (+-1) noised to t (fresh noise each step)."""
    prior = policy.prior
    gen = torch.Generator().manual_seed(seed)
    given_all = 2 * F.one_hot(classes, prior.spec.num_classes).float() - 1
    geo = prior.spec.feature_dim - prior.spec.num_classes
    scenes = []
    for i in range(0, len(floors), batch_size):
        given = given_all[i:i + batch_size]

        def eps_fn(x, t, floor_context=None, given=given):
            noised = prior.schedule.q_sample(given, t, torch.randn(given.shape, generator=gen))
            return policy.eps(torch.cat([x[..., :geo], noised], -1), t, floor_context=floor_context)

        batch = prior.sample(floors[i:i + batch_size], num_steps=policy.num_steps, eta=policy.eta, generator=gen,
                             eps_fn=eps_fn)
        scenes.extend(batch.to_layouts())
    return scenes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--floors", required=True)
    ap.add_argument("--scenes", required=True, help="the first pass: stage-1 rooms on those floors")
    ap.add_argument("--task", required=True, choices=sorted(NEEDS))
    ap.add_argument("--all", action="store_true", help="resample every room, not only those that lacked objects")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    floors = [lay.floor for lay in load_layouts(args.floors)]
    first = load_layouts(args.scenes)
    policy = load_stage1_policy("bedroom")
    vocab = list(policy.prior.spec.vocabulary)
    rooms = [completed_labels(lay.labels, args.task) for lay in first]
    redo = [b for b, lay in enumerate(first) if args.all or rooms[b] != lay.labels]
    added = Counter(lab for b in redo for lab in (Counter(rooms[b]) - Counter(first[b].labels)).elements())
    print(f"{len(redo)} of {len(first)} rooms resampled; objects added: {dict(added)}")
    classes = class_indices([rooms[b] for b in redo], vocab, policy.prior.num_slots)
    resampled = sample_with_classes(policy, [floors[b] for b in redo], classes, args.seed)
    out = list(first)
    for b, lay in zip(redo, resampled):
        lay.id = first[b].id
        out[b] = lay
    save_layouts(out, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
