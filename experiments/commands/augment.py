"""``iarcs augment``: rooms sampled with an adapter (stage 1 by default) on the prior's own training floors, written
as a dataset, then the prior fine-tuned on its data plus those rooms (the paper's Table 4: retraining the base
generator with iARCS-generated rooms lowers its collisions and out-of-bound objects).

Everything lands in ``--out``: ``chunks/`` (the sampling, a file per 250 floors: an interrupted run resumes where
it stopped and samples the same rooms), ``scenes.json`` and ``atiss/`` (the augmentation, neutral JSON and an
ATISS folder), ``finetune.yaml`` (the fine-tuning config), ``control.yaml`` (the same fine-tune on the prior's data
alone, Table 4's control: run it with ``iarcs pretrain --config`` for as many steps) and ``prior/`` (the fine-tune's
run folder: ``prior.pt``).
"""

from __future__ import annotations

from dataclasses import asdict, replace
from pathlib import Path

from experiments.cli import add_device_option, finite_float

EXPERIMENTS = Path(__file__).resolve().parents[1]
#: The recipe each room's shipped prior was trained with: its training floors and its losses.
RECIPES = {"bedroom": EXPERIMENTS / "pretrain_bedroom_finish_cpu.yaml",
           "livingroom": EXPERIMENTS / "pretrain_livingroom_finish_cpu.yaml",
           "diningroom": EXPERIMENTS / "pretrain_diningroom_slots_cpu_minsnr_overlap.yaml"}
CHUNK = 250
#: Fine-tuning a trained prior: a small learning rate held after a short warm-up (a clock ends the run) and a
#: faster EMA than a from-scratch run's. In 433 bedroom steps lr 1e-4 with EMA 0.99 lost 8% of the prior's relation
#: recall (Col_obj -22.5%); 3e-5 with 0.995 loses 4% (Col_obj -18.0%; docs/results/augmentation.md).
FINETUNE = {"lr": 3.0e-5, "warmup_steps": 20, "lr_schedule": "constant", "ema_decay": 0.995, "steps": 1_000_000}


def register(sub) -> None:
    p = sub.add_parser("augment", help="rooms sampled with an adapter on the prior's training floors, then the "
                                        "prior fine-tuned on its data plus them (resumes)")
    p.add_argument("--room", required=True, help="bedroom, livingroom or diningroom")
    p.add_argument("--num-scenes", type=int, default=4000, help="rooms to sample (default 4000)")
    p.add_argument("--out", required=True, help="folder for the rooms, the fine-tuning config and the new prior")
    p.add_argument("--adapter", default="stage1",
                   help="stage1 (the shipped stage-1 adapter, default), a LoRA adapter folder of the shipped prior, "
                        "or an `iarcs train` run folder (e.g. a task's)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampling (default 0)")
    p.add_argument("--minutes", type=finite_float, default=20.0,
                   help="fine-tuning time budget in minutes (default 20; 0: sample only)")
    p.add_argument("--weight", type=finite_float, default=None,
                   help="the sampled rooms' share of a batch against the prior's data (weight 1); default: their "
                        "number over the data's, every room alike")
    add_device_option(p, "fine-tuning")
    p.set_defaults(func=cmd_augment)


def cmd_augment(args) -> int:
    import torch
    from tqdm import tqdm

    from agents.pretrain import load_config, train
    from experiments.cli import CLIError
    from experiments.commands.prior import load_sampler
    from iarcs_env.datasets import load_layouts, save_layouts
    from iarcs_env.datasets.procedural import generate_layouts
    from iarcs_env.rooms import get_room

    try:
        room = get_room(args.room).name
    except ValueError as err:
        raise CLIError(str(err)) from None
    recipe = load_config(RECIPES[room])
    if not 0 < args.num_scenes <= recipe.num_scenes:
        raise CLIError(f"--num-scenes must be in 1..{recipe.num_scenes} (the {room} prior's training floors), "
                       f"got {args.num_scenes}")
    if args.minutes < 0 or (args.weight is not None and args.weight <= 0):
        raise CLIError("--minutes must be >= 0 and --weight > 0")
    if args.adapter == "stage1":
        from agents.train import load_stage1_policy

        policy = load_stage1_policy(room)
    else:
        _, policy = load_sampler(args.adapter, room)
        if policy is None:
            raise CLIError(f"--adapter {args.adapter} is a prior, not an adapter: give a LoRA adapter folder or an "
                           "`iarcs train` run folder")
    out = Path(args.out)
    chunks = out / "chunks"
    chunks.mkdir(parents=True, exist_ok=True)

    # 1. sampling, a chunk of floors at a time (each chunk with its own seed: a resumed run samples the same rooms)
    sources = generate_layouts(room, args.num_scenes, seed=recipe.data_seed)
    starts = range(0, len(sources), CHUNK)
    todo = [k for k in starts if not (chunks / f"{k // CHUNK:04d}.json").exists()]
    if len(todo) < len(starts):
        print(f"{len(starts) - len(todo)} of {len(starts)} chunks already sampled in {chunks}")
    for k in tqdm(todo, desc=f"sampling with {args.adapter}", unit="chunk"):
        part = sources[k:k + CHUNK]
        batch = policy.sample([r.floor for r in part],
                              generator=torch.Generator().manual_seed(args.seed * 1_000_003 + k))
        rooms = []
        for lay, src in zip(batch.to_layouts(), part):
            t = lay.translations.copy()  # back to the floor plan's own frame
            t[:, 0::2] += src.floor.centre
            rooms.append(replace(lay, id=f"{src.id}:augmented", floor=src.floor, translations=t,
                                 ceiling_height=src.ceiling_height))
        save_layouts(rooms, chunks / f"{k // CHUNK:04d}.json")
    layouts = [lay for k in starts for lay in load_layouts(chunks / f"{k // CHUNK:04d}.json", room)]
    scenes = save_layouts(layouts, out / "scenes.json", generator="iarcs augment", adapter=args.adapter,
                          seed=args.seed, floors=f"procedural seed {recipe.data_seed} (the prior's training floors)")
    save_layouts(layouts, out / "atiss")
    print(f"{len(layouts)} {room}s sampled with {args.adapter}: {scenes}, {out / 'atiss'}")

    # 2. the prior fine-tuned on its data plus the sampled rooms; its control on the data alone
    import yaml

    from agents.config import resolve_device

    device = resolve_device(args.device or "auto")
    weight = args.weight if args.weight is not None else len(layouts) / (recipe.num_scenes - recipe.val_scenes)
    cfg = replace(recipe, **FINETUNE, init_from="default", out=str(out / "prior"), device=str(device),
                  extra_datasets=[{"dataset": str(scenes.resolve()), "weight": float(weight)}],
                  precision="fp32" if device.type == "cpu" else recipe.precision, compile=False, num_threads=0)
    command = f"iarcs augment --room {room} --num-scenes {args.num_scenes} --adapter {args.adapter} --seed {args.seed}"
    (out / "finetune.yaml").write_text(f"# {command}: the shipped prior fine-tuned on its data plus these rooms\n"
                                       + yaml.safe_dump(asdict(cfg), sort_keys=False))
    control = replace(cfg, extra_datasets=[], out=str(out / "control"))
    (out / "control.yaml").write_text(f"# {command}: the control, the same fine-tune on the prior's data alone\n"
                                      + yaml.safe_dump(asdict(control), sort_keys=False))
    if args.minutes == 0:
        print(f"fine-tune later, the augmented prior and its control for as many steps:\n"
              f"  iarcs pretrain --config {out / 'finetune.yaml'} --stop-at STEPS\n"
              f"  iarcs pretrain --config {out / 'control.yaml'} --stop-at STEPS")
        return 0
    print(f"fine-tuning the {room} prior on its data plus these rooms (weight {weight:.3f}) for {args.minutes:g} "
          f"minutes: {out / 'finetune.yaml'}")
    result = train(cfg, time_budget=args.minutes * 60)
    prior = out / "prior" / "prior.pt"
    print(f"step {result.step} in {result.seconds:.0f} s; the augmented prior: {prior}\n"
          f"its control, the data alone for as many steps: iarcs pretrain --config {out / 'control.yaml'} --stop-at "
          f"{result.step}\n"
          f"compare them with the shipped one on held-out floors: iarcs sample --room {room} --checkpoint {prior} "
          f"--floors FLOORS.json --out A.json; iarcs evaluate --scenes A.json --reference FLOORS.json")
    return 0
