"""How well does the prior place a task's objects once they are in the room, before any training? Writes an adapter
that is the shipped stage-1 adapter (``--start stage1``) or the prior itself (``--start prior``) with the task's
required objects (iarcs_env/required_objects.py), to sample and evaluate like any adapter:

    .venv/bin/python research/required_objects.py --task two_nightstands --start stage1 --out out/req/s1_required
    iarcs sample --floors FLOORS.json --num-scenes 500 --seed 0 --checkpoint out/req/s1_required/two_nightstands \
        --out S.json
    iarcs evaluate --scenes S.json --reference FLOORS.json --task all --features none --out S_report.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.denoiser import ScenePrior  # noqa: E402
from agents.policy import DiffusionPolicy  # noqa: E402
from agents.train import load_stage1_policy  # noqa: E402
from iarcs_env.required_objects import RequiredObject  # noqa: E402

#: The objects of each relational task (what a training config names in required_objects).
NEEDS = {
    "two_nightstands": [RequiredObject(("bed",), 1, "double_bed"), RequiredObject(("nightstand",), 2, "nightstand")],
    "tv_from_bed": [RequiredObject(("bed",), 1, "double_bed"), RequiredObject(("tv_stand",), 1, "tv_stand")],
    "study_zone": [RequiredObject(("desk",), 1, "desk"),
                   RequiredObject(("chair", "stool", "dressing_chair"), 1, "chair")],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", required=True, choices=sorted(NEEDS))
    ap.add_argument("--start", choices=["stage1", "prior"], default="stage1")
    ap.add_argument("--out", required=True, help="folder; the adapter is written to OUT/TASK")
    args = ap.parse_args()
    if args.start == "stage1":
        policy, start = load_stage1_policy("bedroom"), "stage1"
    else:
        policy, start = DiffusionPolicy(ScenePrior.load_default("bedroom"), adapter="prior"), "prior"
    policy.add_adapter(args.task, init_from=start, adapted=("position", "yaw"), required=NEEDS[args.task])
    print(f"wrote {policy.save_adapter(args.out)}")


if __name__ == "__main__":
    main()
