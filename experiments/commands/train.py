"""``iarcs train``: RL fine-tuning of a scene prior's LoRA adapter from a YAML config (resumes)."""

from __future__ import annotations

from experiments.cli import add_device_option


def register(sub) -> None:
    p = sub.add_parser("train", help="fine-tune a LoRA adapter of the prior with RL (DDPO); resumes a stopped run")
    p.add_argument("--config", required=True, help="YAML config, e.g. experiments/stage1_bedroom_quick.yaml")
    p.add_argument("--out", default=None, help="run folder (default: the config's 'out')")
    p.add_argument("--epochs", type=int, default=None, help="total epochs (default: the config's)")
    add_device_option(p, "the policy")
    p.set_defaults(func=cmd_train)


def cmd_train(args) -> int:
    from agents import distributed
    from agents.train import load_train_config, run
    from experiments.cli import CLIError

    if args.epochs is not None and args.epochs <= 0:
        raise CLIError(f"--epochs must be positive, got {args.epochs}")
    cfg = load_train_config(args.config, out=args.out, epochs=args.epochs, device=args.device)
    try:
        algo = run(cfg)
        main, processes = distributed.is_main(), distributed.world_size()
    finally:
        distributed.cleanup()
    if main:  # under torchrun, rank 0 reports
        each = f" in each of {processes} processes" if processes > 1 else ""
        print(f"{algo.name}: {algo.epoch} epochs, {algo.num_timesteps} environment steps{each}; run folder {cfg.out}")
    return 0
