"""Add the training rooms' per-class sizes (``DatasetStats.class_sizes``, which the ``object_size`` reward
needs) to a prior checkpoint written before the field existed, and to the matching statistics file.

    python experiments/add_class_sizes.py agents/checkpoints/bedroom_small.pt experiments/pretrain_bedroom_gpu.yaml \\
        --stats iarcs_env/data/stats/bedroom.json

The training rooms are rebuilt from the pretraining config (dataset, seed and validation split) and must give
the checkpoint's own object-count histogram and class presence, or nothing is written. The weights are
untouched: the checkpoint samples exactly as before.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.pretrain import load_config  # noqa: E402
from agents.pretrain_data import load_training_layouts, training_split  # noqa: E402
from iarcs_env.stats import DatasetStats  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", help="prior checkpoint (.pt) to update in place")
    ap.add_argument("config", help="the pretraining config that made it (its dataset, data_seed and val_scenes)")
    ap.add_argument("--stats", help="a statistics JSON file to give the same class sizes "
                                    "(e.g. iarcs_env/data/stats/bedroom.json)")
    args = ap.parse_args(argv)

    state = torch.load(args.checkpoint, map_location="cpu", weights_only=False)
    cfg = load_config(args.config)
    if cfg.room != state["room_type"]:
        sys.exit(f"{args.config} trains {cfg.room} rooms, but {args.checkpoint} is a {state['room_type']} prior")
    train, _ = training_split(load_training_layouts(cfg), cfg)
    fresh = DatasetStats.from_layouts(train, cfg.room)
    for name in ("object_count_histogram", "class_presence"):
        stored, recomputed = state["stats"][name], getattr(fresh, name)
        if stored != recomputed:
            sys.exit(f"{args.config} does not rebuild the training rooms of {args.checkpoint}: its {name} differs "
                     f"({stored} stored, {recomputed} recomputed); nothing written")
    state["stats"]["class_sizes"] = fresh.class_sizes
    torch.save(state, args.checkpoint)
    print(f"{args.checkpoint}: class sizes of {len(fresh.class_sizes)} classes from {len(train)} training rooms")
    if args.stats:
        data = json.loads(Path(args.stats).read_text())
        data["class_sizes"] = fresh.class_sizes
        Path(args.stats).write_text(json.dumps(data, indent=1))
        print(f"{args.stats}: the same")


if __name__ == "__main__":
    main()
