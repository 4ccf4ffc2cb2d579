"""``iarcs pretrain`` (train a scene prior from a YAML config) and ``iarcs sample`` (scenes from a prior)."""

from __future__ import annotations

from pathlib import Path

from experiments.cli import add_device_option, finite_float


def register(sub) -> None:
    p = sub.add_parser("pretrain", help="pretrain a floor-conditioned scene prior (resumes an interrupted run)",
                       description="Pretrain a floor-conditioned scene prior (resumes an interrupted run). Procedural "
                                   "rooms are generated once, in one process per core, and cached with their tensors "
                                   "and statistics in out/cache/pretrain_data/ under the working directory (the "
                                   "IARCS_CACHE_DIR environment variable moves out/cache), so that the next run with "
                                   "the same data starts training within seconds.")
    p.add_argument("--config", required=True, help="YAML config, e.g. experiments/pretrain_bedroom.yaml")
    p.add_argument("--out", default=None, help="run folder (default: the config's 'out')")
    p.add_argument("--steps", type=int, default=None, help="total optimizer steps (default: the config's)")
    p.add_argument("--stop-at", type=int, default=None,
                   help="stop at this global step as if interrupted there, keeping the config's learning-rate "
                        "schedule; the run resumes later from it (default: run to --steps)")
    p.add_argument("--time-budget", type=finite_float, default=None, metavar="MINUTES",
                   help="stop cleanly when this many minutes have passed (a checkpoint and prior.pt written, the "
                        "run resumable); pair it with 'lr_schedule: constant' (default: no limit)")
    p.add_argument("--continue-from", nargs="?", const="default", default=None, metavar="PRIOR",
                   help="start a new run from these weights: a prior checkpoint (.pt), a pretraining run folder or "
                        "its train_state.pt (then its optimizer state too), or, with no value, the prior shipped "
                        "for the config's room (sets the config's init_from)")
    p.add_argument("--no-resume", action="store_true",
                   help="refuse to continue an existing run in the output folder (default: resume it)")
    add_device_option(p, "the network trains")
    p.set_defaults(func=cmd_pretrain)

    p = sub.add_parser("sample", help="sample scenes from a scene prior as neutral JSON layouts")
    p.add_argument("--room", default="bedroom", help="bedroom, livingroom or diningroom (default bedroom)")
    p.add_argument("--num-scenes", type=int, default=None,
                   help="scenes to sample (default 16, or one per room of --floors)")
    p.add_argument("--seed", type=int, default=0, help="seed of the floor plans and of the sampler")
    p.add_argument("--out", required=True, help="output .json file (or a folder for ATISS format)")
    p.add_argument("--checkpoint", default=None,
                   help="prior.pt of a pretraining run, an `iarcs train` run folder (its prior + LoRA "
                        "adapter), or a LoRA adapter folder (peft format) for the shipped prior; default: the "
                        "prior shipped for --room")
    p.add_argument("--adapter", default=None, metavar="NAME",
                   help="sample the shipped prior through one of its shipped LoRA adapters: stage1, or a paper "
                        "task's stage-2 adapter (its name, e.g. two_nightstands)")
    p.add_argument("--floors", default=None,
                   help="layout file whose floor plans to use, room for room (default: procedural floors)")
    p.add_argument("--steps", type=int, default=20, help="DDIM steps (default 20)")
    p.add_argument("--eta", type=finite_float, default=1.0, help="DDIM eta: 0 deterministic, 1 DDPM-like (default 1)")
    p.add_argument("--guidance", type=finite_float, default=1.0, help="classifier-free guidance scale (default 1: none)")
    p.add_argument("--batch-size", type=int, default=256, help="scenes per sampling batch (default 256)")
    p.add_argument("--satisfying", default=None, metavar="TASK",
                   help="keep only scenes passing this paper task's checker (reach_1m, tv_from_bed, study_zone, "
                        "two_nightstands, wheelchair): each floor plan is sampled again until one passes, at most "
                        "--max-draws times; floor plans with no passing scene are left out (default: keep all)")
    p.add_argument("--max-draws", type=int, default=50, help="draws per floor plan with --satisfying (default 50)")
    add_device_option(p, "the denoiser")
    p.set_defaults(func=cmd_sample)


def cmd_pretrain(args) -> int:
    from experiments.cli import CLIError
    from agents import distributed
    from agents.pretrain import PRIOR_FILE, STATE_FILE, load_config, train

    if args.steps is not None and args.steps <= 0:
        raise CLIError(f"--steps must be a positive number, got {args.steps}")
    if args.stop_at is not None and args.stop_at <= 0:
        raise CLIError(f"--stop-at must be a positive step, got {args.stop_at}")
    if args.time_budget is not None and args.time_budget <= 0:
        raise CLIError(f"--time-budget must be a positive number of minutes, got {args.time_budget}")
    cfg = load_config(args.config, out=args.out, steps=args.steps, device=args.device, init_from=args.continue_from)
    out = Path(cfg.out)
    if args.no_resume and (out / STATE_FILE).exists():
        raise CLIError(f"{out} already holds a run ({STATE_FILE}); drop --no-resume to continue it, or choose "
                       "another --out")
    try:
        result = train(cfg, max_steps=args.stop_at, resume=not args.no_resume,
                       time_budget=args.time_budget * 60 if args.time_budget is not None else None)
        main = distributed.is_main()
    finally:
        distributed.cleanup()
    if not main:  # under torchrun, rank 0 reports
        return 0
    last = result.losses[-1][1] if result.losses else float("nan")
    print(f"step {result.step}/{cfg.steps} in {result.seconds:.0f} s"
          + (" (the time budget is spent)" if result.stopped_by_deadline else "")
          + f"; last training loss {last:.4f}"
          + (f"; EMA validation loss {result.val_losses[-1][1]:.4f}" if result.val_losses else ""))
    print(f"prior: {out / PRIOR_FILE}\ntraining state (resumable): {out / STATE_FILE}")
    return 0


def load_sampler(checkpoint: str | None, room: str):
    """(prior, policy or None) that ``checkpoint`` names for sampling ``room``: a prior file, a LoRA adapter folder
    of the shipped prior (peft format), an ``iarcs train`` run folder, or None for the shipped prior. With an
    adapter, sample through ``policy.eps`` (its reference's on the features the adapter leaves)."""
    from experiments.cli import CLIError
    from agents.denoiser import ScenePrior

    policy = None
    if checkpoint and (Path(checkpoint) / "adapter_config.json").exists():
        from agents.policy import DiffusionPolicy

        policy = DiffusionPolicy(ScenePrior.load_default(room), adapter="scratch")
        policy.load_adapter(checkpoint, "sampled")
    elif checkpoint and Path(checkpoint).is_dir():
        from agents.train import load_trained_policy

        policy, _ = load_trained_policy(checkpoint)
    if policy is not None:
        prior = policy.prior
    elif checkpoint:
        prior = ScenePrior.load(checkpoint)
    else:
        try:
            prior = ScenePrior.load_default(room)
        except FileNotFoundError as err:
            raise CLIError(str(err)) from None
    if prior.spec.name != room:
        raise CLIError(f"{checkpoint or 'the prior'} is a {prior.spec.name} prior but --room is {room}; "
                       f"pass --room {prior.spec.name} or a {room} checkpoint")
    return prior, policy


def shipped_adapter(room: str, name: str) -> Path:
    """The folder of the shipped adapter ``name`` of ``room``'s prior, or a CLIError that lists the shipped ones."""
    from agents.train import shipped_adapter_path, shipped_adapters
    from experiments.cli import CLIError

    shipped = shipped_adapters(room)
    if name not in shipped:
        have = ", ".join(shipped) or "none"
        raise CLIError(f"--adapter {name}: no such adapter is shipped for {room} (shipped: {have}); to sample "
                       "an adapter you trained, pass its `iarcs train` run folder as --checkpoint")
    return shipped_adapter_path(room, name)


def cmd_sample(args) -> int:
    import numpy as np
    import torch
    from dataclasses import replace

    from experiments.cli import CLIError
    from agents.config import resolve_device
    from agents.denoiser import ScenePrior
    from iarcs_env.datasets import load_layouts, save_layouts
    from iarcs_env.rooms import get_room

    try:
        spec = get_room(args.room)
    except ValueError as err:
        raise CLIError(str(err)) from None
    for name, value in (("--num-scenes", args.num_scenes), ("--steps", args.steps), ("--batch-size", args.batch_size)):
        if value is not None and value <= 0:
            raise CLIError(f"{name} must be a positive number, got {value}")
    if args.steps > 1000:
        raise CLIError(f"--steps must be at most 1000 (the training timesteps), got {args.steps}")
    if args.eta < 0:
        raise CLIError(f"--eta must be >= 0, got {args.eta}")
    if args.max_draws < 1:
        raise CLIError(f"--max-draws must be a positive number, got {args.max_draws}")
    task = None
    if args.satisfying:
        from iarcs_env.tasks import get_task

        try:
            task = get_task(args.satisfying)
        except ValueError as err:
            raise CLIError(f"--satisfying: {err}") from None
        if task.room != spec.name:
            raise CLIError(f"--satisfying {task.name} is a {task.room} task but --room is {spec.name}")
    device = resolve_device(args.device or "auto")
    checkpoint = args.checkpoint
    if args.adapter:
        if checkpoint:
            raise CLIError("pass --adapter (a shipped adapter of the shipped prior) or --checkpoint, not both")
        checkpoint = str(shipped_adapter(spec.name, args.adapter))

    prior, policy = load_sampler(checkpoint, spec.name)
    prior.to(device)

    if args.floors:
        rooms = load_layouts(args.floors, spec.name)
        if not rooms:
            raise CLIError(f"{args.floors} holds no {spec.name} rooms")
        n = args.num_scenes or len(rooms)
        if n > len(rooms):
            raise CLIError(f"--num-scenes {n} asks for more scenes than {args.floors} has rooms ({len(rooms)}); "
                           f"pass --num-scenes {len(rooms)} or fewer")
        sources = rooms[:n]
    else:
        from iarcs_env.datasets.procedural import generate_layouts

        n = args.num_scenes or 16
        sources = generate_layouts(spec.name, n, seed=args.seed)
    floors = [r.floor for r in sources]
    ids = [f"{r.id or spec.name}:sample" if args.floors else f"{spec.name}_s{args.seed}_{i:05d}"
           for i, r in enumerate(sources)]
    gen = torch.Generator().manual_seed(args.seed)

    def draw(indices: list[int]):
        """One scene for each of these floor plans (centred on the floor's bounding box, as the prior works)."""
        sampler = prior if policy is None else policy  # an adapter's policy also gives its task's required objects
        return sampler.sample([floors[i] for i in indices], num_steps=args.steps, eta=args.eta, generator=gen,
                              guidance_scale=args.guidance, batch_size=args.batch_size,
                              ids=[ids[i] for i in indices]).to_layouts()

    meta = {"source": "iarcs sample", "room_type": spec.name, "checkpoint": str(checkpoint or
            ScenePrior.default_path(spec.name).name), "seed": args.seed, "ddim_steps": args.steps,
            "eta": args.eta, "guidance": args.guidance, "floors": args.floors or "procedural"}
    if task is None:
        sampled = draw(list(range(n)))
    else:
        from iarcs_env.tasks import sample_satisfying

        sampled, drawn, passed = sample_satisfying(draw, n, task, args.max_draws, batch_size=args.batch_size)
        meta["satisfying"] = satisfying_info(task.name, args.max_draws, sampled, drawn, passed)
    layouts = []
    for lay, src in zip(sampled, sources):
        if lay is None:
            continue
        # back to the floor plan's own frame
        c = src.floor.centre
        t = lay.translations.copy()
        t[:, 0] += c[0]
        t[:, 2] += c[1]
        layouts.append(replace(lay, floor=src.floor, translations=t, ceiling_height=src.ceiling_height))
    if task is not None:
        print(satisfying_summary(meta["satisfying"]))
        if not layouts:
            raise CLIError(f"no scene passed {task.name} in {args.max_draws} draws on any of the {n} floor plans; "
                           "nothing written (raise --max-draws, or sample an adapter trained for the task)")
    path = save_layouts(layouts, args.out, **meta)
    counts = np.array([len(l) for l in layouts])
    print(f"{len(layouts)} {spec.name} scenes ({counts.mean():.1f} objects on average) -> {path}")
    return 0


def satisfying_info(task: str, max_draws: int, sampled: list, drawn, passed) -> dict:
    """What a rejection-sampled file records of its sampling (:func:`iarcs_env.tasks.sample_satisfying`'s results)."""
    return {"task": task, "max_draws": max_draws, "floors": len(sampled), "kept": sum(l is not None for l in sampled),
            "drawn": int(drawn.sum()), "passed": int(passed.sum())}


def satisfying_summary(info: dict) -> str:
    """One line on a rejection-sampled file: kept floors, draws and the acceptance rate."""
    left = info["floors"] - info["kept"]
    return (f"{info['task']}: {info['kept']} of {info['floors']} floor plans have a passing scene; {info['passed']} "
            f"of the {info['drawn']} scenes drawn passed ({info['passed'] / info['drawn']:.1%})"
            + (f"; {left} floor plan(s) had none in {info['max_draws']} draws and are left out" if left else ""))
