"""``iarcs generate``: the whole pipeline for a user. A constraint in words becomes a reward program (the
reward-synthesis agent), a stage-2 LoRA adapter (trained from the shipped stage-1 adapter, or reused from
the adapter library when one was trained for the same room and constraint), and then N scenes written as
neutral JSON and ATISS folders, with top-down renders and a metrics report.

The adapter library is ``$IARCS_HOME/adapters/<room>/<constraint slug>-<hash>/`` (``IARCS_HOME`` defaults to
``~/.iarcs``; the hash covers the constraint and the shipped weights the adapter was trained on): ``adapter/``
(peft), ``reward/`` (program and proposal), ``constraint.txt``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from pathlib import Path

from experiments.cli import add_device_option

from .reward import add_agent_options

TEMPLATE = Path(__file__).resolve().parents[1] / "task_two_nightstands.yaml"
#: At most this many scenes go into the prior / stage 1 / adapter comparison of the report.
COMPARED_SCENES = 500


def register(sub) -> None:
    p = sub.add_parser("generate", help="constraint in words -> reward -> stage-2 adapter -> scenes, renders, report")
    p.add_argument("--room", default="bedroom", help="bedroom, livingroom or diningroom (default bedroom)")
    p.add_argument("--constraint", required=True, help='e.g. "A wheelchair-accessible bedroom"')
    p.add_argument("--num-scenes", type=int, default=64, help="scenes to generate (default 64)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0, help="seed of the floor plans and the sampler")
    p.add_argument("--floors", default=None, help="layout file whose floor plans to use (default: procedural)")
    p.add_argument("--task", default=None,
                   help="task checker to report success with (reach_1m, tv_from_bed, study_zone, two_nightstands, "
                        "wheelchair); default: the paper task whose prompt equals the constraint, if any")
    p.add_argument("--epochs", type=int, default=100, help="stage-2 training epochs when no adapter exists (default 100)")
    p.add_argument("--retrain", action="store_true", help="train a new adapter even if one is shipped for this paper task or the library has one")
    p.add_argument("--only-satisfying", action="store_true",
                   help="write only scenes that pass the task's checker (needs a paper task: --task or its prompt as "
                        "the constraint): each floor plan is sampled again until one passes, at most --max-draws "
                        "times; the report's table still measures the adapter's own samples")
    p.add_argument("--max-draws", type=int, default=50, help="draws per floor plan with --only-satisfying (default 50)")
    add_agent_options(p)
    add_device_option(p, "training and sampling")
    p.set_defaults(func=cmd_generate)


def library_root() -> Path:
    """The adapter library: ``$IARCS_HOME/adapters`` (``IARCS_HOME`` defaults to ``~/.iarcs``)."""
    return Path(os.environ.get("IARCS_HOME", Path.home() / ".iarcs")).expanduser() / "adapters"


def library_dir(room: str, constraint: str) -> Path:
    """Where the adapter for (room, constraint) lives: a readable slug plus a hash of the normalised text and of
    the weights it was trained on (the shipped prior and stage-1 adapter: an adapter belongs to them, so a new
    prior or stage-1 adapter trains anew instead of reusing one that no longer fits)."""
    norm = " ".join(constraint.lower().split())
    slug = re.sub(r"[^a-z0-9]+", "_", norm).strip("_")[:40]
    digest = hashlib.sha1(f"{room}|{norm}|{shipped_weights_id(room)}".encode()).hexdigest()[:8]
    return library_root() / room / f"{slug}-{digest}"


def shipped_weights_id(room: str) -> str:
    """A digest of the shipped prior and stage-1 adapter files of ``room`` (those that exist)."""
    from agents.denoiser import ScenePrior
    from agents.train import stage1_adapter_path

    files = [ScenePrior.default_path(room), stage1_adapter_path(room) / "adapter_model.safetensors"]
    digest = hashlib.sha256()
    for path in files:
        if path.exists():
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def matching_task(constraint: str) -> str | None:
    """The paper task whose prompt is this constraint (case and spacing ignored)."""
    from iarcs_env.tasks import TASKS

    norm = " ".join(constraint.lower().split())
    return next((name for name, t in TASKS.items() if " ".join(t.prompt.lower().split()) == norm), None)


def train_adapter(args, room: str, task: str | None, run_dir: Path) -> Path:
    """Stage 2 for the constraint (the quick task config with this constraint); returns the run folder. With a
    paper task's checker the adapter is the best evaluation's (a reward redefined by reflection cannot rank
    evaluations against each other, so without one it is the last epoch's)."""
    from agents.train import load_train_config, run

    agent = {"model": args.model or "", "api_base": args.api_base or "", "allow_partial": args.allow_partial}
    if args.model:
        agent["llm"] = {"timeout": args.timeout, "max_seconds": args.max_seconds}
    cfg = load_train_config(TEMPLATE, room=room, out=str(run_dir), epochs=args.epochs, adapter="task",
                            export="best" if task else "last", device=args.device,
                            task={"constraint": args.constraint, "checker": task or "", "reflect_every": 10, **agent})
    run(cfg)
    return run_dir


def cmd_generate(args) -> int:
    import torch

    from agents.config import resolve_device
    from agents.denoiser import ScenePrior
    from agents.policy import DiffusionPolicy
    from agents.train import ADAPTERS_DIR, shipped_task_dir, stage1_adapter_path
    from experiments.cli import CLIError
    from iarcs_env.datasets import save_layouts
    from iarcs_env.datasets.atiss import write_atiss_folder
    from iarcs_env.rooms import get_room
    from iarcs_env.tasks import get_task, sample_satisfying

    from .prior import satisfying_info, satisfying_summary

    room = get_room(args.room).name
    if args.num_scenes < 1 or args.epochs < 1 or args.max_draws < 1:
        raise CLIError("--num-scenes, --epochs and --max-draws must be positive")
    if not args.constraint.strip():
        raise CLIError('--constraint is empty; e.g. --constraint "A wheelchair-accessible bedroom"')
    device = resolve_device(args.device or "auto")  # a clear error before any work
    task = args.task or matching_task(args.constraint)
    if task:
        checker = get_task(task)  # a clear error for an unknown name
        if checker.room != room:
            raise CLIError(f"--task {checker.name} is a {checker.room} task but --room is {room}")
    elif args.only_satisfying:
        raise CLIError("--only-satisfying needs a task checker, and this constraint is not a paper task's prompt; "
                       "name the checker with --task (reach_1m, tv_from_bed, study_zone, two_nightstands, wheelchair)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lib = library_dir(room, args.constraint)
    shipped = shipped_task_dir(room, task) if task and task == matching_task(args.constraint) else None
    if shipped and (shipped / "adapter" / "adapter_config.json").exists() and not args.retrain:
        lib = shipped
        print(f"1/3 using the adapter shipped for this paper task ({task}): {lib}")
    elif (lib / "adapter" / "adapter_config.json").exists() and not args.retrain:
        print(f"1/3 reusing the adapter trained for this constraint: {lib}")
    else:
        print(f"1/3 training a stage-2 adapter for {args.constraint!r} ({args.epochs} epochs) ...")
        run_dir = train_adapter(args, room, task, out / "train")
        shutil.rmtree(lib, ignore_errors=True)
        lib.mkdir(parents=True)
        shutil.copytree(run_dir / ADAPTERS_DIR / "task", lib / "adapter")
        shutil.copytree(run_dir / "reward", lib / "reward")
        (lib / "constraint.txt").write_text(args.constraint + "\n")
        print(f"   adapter saved to the library: {lib}")
    print(f"2/3 sampling {args.num_scenes} scenes, and comparing with the prior and stage 1 ...")
    policy = DiffusionPolicy(ScenePrior.load_default(room), adapter="scratch")
    variants = [("prior", None)]
    if (stage1_adapter_path(room) / "adapter_config.json").exists():
        policy.load_adapter(stage1_adapter_path(room), "stage1")
        variants.append(("stage 1", "stage1"))
    policy.load_adapter(lib / "adapter", "task")
    policy.to(device)
    variants.append(("with the task adapter", "task"))
    floors = generation_floors(room, args.num_scenes, args.seed, args.floors)
    shown = floors[:COMPARED_SCENES]  # the comparison; every scene is sampled with the adapter
    rows = compare_variants(policy, shown, args.seed, variants, task)
    meta, filtered = {}, []
    if args.only_satisfying:
        policy.set_adapter("task")
        gen = torch.Generator().manual_seed(args.seed + 1)  # not the comparison's draws again
        sampled, drawn, passed = sample_satisfying(
            lambda idx: policy.sample([floors[i] for i in idx], generator=gen).to_layouts(), len(floors), task,
            args.max_draws)
        layouts = [l for l in sampled if l is not None]
        meta["satisfying"] = satisfying_info(task, args.max_draws, sampled, drawn, passed)
        filtered = ["", f"scenes.json holds only scenes that pass the {task} checker. "
                    + satisfying_summary(meta["satisfying"]) + "."]
        print(filtered[-1])
        if not layouts:
            raise CLIError(f"no scene passed {task} in {args.max_draws} draws on any of the {len(floors)} floor plans; "
                           "nothing written (raise --max-draws, or train the adapter longer: --retrain --epochs N)")
    elif len(floors) > len(shown):
        policy.set_adapter("task")
        layouts = policy.sample(floors, generator=torch.Generator().manual_seed(args.seed)).to_layouts()
    else:
        layouts = rows[-1]["layouts"]
    save_layouts(layouts, out / "scenes.json", generator="iarcs generate", constraint=args.constraint, seed=args.seed,
                 **meta)
    write_atiss_folder(layouts, out / "atiss")
    table, pictures = write_comparison(out, rows, task)
    proposal = json.loads((lib / "reward" / "proposal.json").read_text())
    report = [f"# iarcs generate: {args.constraint}", "", *table, *filtered, "", picture_table(rows, pictures), "",
              *program_section(proposal)]
    (out / "report.md").write_text("\n".join(report))
    print("3/3 results\n" + "\n".join(table))
    print(f"scenes: {out / 'scenes.json'}, {out / 'atiss'}; renders: {out}/renders_*.png; report: {out / 'report.md'}")
    return 0


def generation_floors(room: str, count: int, seed: int, floors_file: str | None = None):
    """Floor plans of a layout file, or held-out procedural ones: seed 777 (+ ``seed``), the floors of the stage
    evaluation scripts, used neither by the prior (0), nor by RL training (1000), nor by the training
    evaluations that pick a run's best adapter (12345)."""
    from iarcs_env.datasets import load_layouts
    from iarcs_env.env import default_floors

    if not floors_file:
        return default_floors(room, count=count, seed=777 + seed)
    floors = [l.centred().floor for l in load_layouts(floors_file, room)][:count]
    if len(floors) < count:
        raise ValueError(f"{floors_file} has {len(floors)} {room} floor plans; --num-scenes asks for {count}")
    return floors


def compare_variants(policy, floors, seed: int, variants, task: str | None = None) -> list[dict]:
    """Sample the same floors with the same seed for each ``(name, adapter)`` (None: the prior alone) and
    evaluate: ``[{"name", "layouts", "result", "seconds"}]`` (``result`` with ``task_success`` when a task
    checker is named)."""
    import contextlib
    import time

    import numpy as np
    import torch

    from iarcs_env.metrics import evaluate_layouts
    from iarcs_env.tasks import get_task

    rows = []
    for name, adapter in variants:
        if adapter is not None:
            policy.set_adapter(adapter)
        t0 = time.perf_counter()
        with policy.base_policy() if adapter is None else contextlib.nullcontext():
            scenes = policy.sample(floors, generator=torch.Generator().manual_seed(seed))
        seconds = time.perf_counter() - t0
        layouts = scenes.to_layouts()
        result = evaluate_layouts(layouts, keep_scenes=True, keep_masks=True)
        if task:
            result["task_success"] = float(np.mean(get_task(task).check(scenes)))
        rows.append({"name": name, "layouts": layouts, "result": result, "seconds": seconds})
    return rows


def write_comparison(out: Path, rows: list[dict], task: str | None = None, n_show: int = 16):
    """Renders (issues marked) per row as ``renders_<i>.png``, ``metrics.json``; returns the Markdown table
    lines and the picture paths."""
    from iarcs_env.render import image_grid, render_layout, save_image

    pictures, metrics = [], {}
    lines = ["| scenes | " + ("task success % | " if task else "") + "Col_obj % | Col_scene % | R_out % | "
             "R_reach % | R_walkable | R_off_floor % | R_misaligned % | objects / room |",
             "|---|" + ("---|" if task else "") + "---|---|---|---|---|---|---|---|"]
    for i, row in enumerate(rows):
        res, layouts = row["result"], row["layouts"]
        shown = range(min(n_show, len(layouts)))
        grid = image_grid([render_layout(layouts[j], overlays=res["scenes"][j].overlays()) for j in shown], cols=4,
                          titles=[f"{row['name']} {j}" for j in shown])
        pictures.append(save_image(grid, out / f"renders_{i}.png"))
        per_room = sum(len(l) for l in layouts) / max(len(layouts), 1)
        lines.append(f"| {row['name']} | " + (f"{100 * res['task_success']:.1f} | " if task else "")
                     + f"{100 * res['Col_obj']:.2f} | {100 * res['Col_scene']:.2f} | {100 * res['R_out']:.2f} | "
                     f"{100 * res['R_reach']:.2f} | {res['R_walkable']:.3f} | {100 * res['R_off_floor']:.2f} | "
                     f"{100 * res['R_misaligned']:.2f} | "
                     f"{per_room:.2f} |")
        metrics[row["name"]] = {k: v for k, v in res.items() if isinstance(v, (int, float))}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    lines += ["", comparison_viewer(out / "viewer.html", rows)]
    return lines, pictures


def comparison_viewer(path: Path, rows: list[dict], per_row: int = 4) -> str:
    """The first rooms of each row in one 3D viewer page (same overlays); the report's line about it."""
    from iarcs_env.scene3d import layout_scene
    from iarcs_env.viewer import ViewerNotBuilt, write_viewer

    scenes = [(f"{row['name']} {j}", layout_scene(row["layouts"][j], row["result"]["scenes"][j]))
              for row in rows for j in range(min(per_row, len(row["layouts"])))]
    try:
        write_viewer(scenes, path, title="prior and adapters, the same floors")
    except ViewerNotBuilt as e:
        return f"No 3D viewer: {e}."
    return (f"In 3D: [{path.name}]({path.name}), the first {per_row} rooms of each row (orbit and top views, "
            "the same overlays).")


def picture_table(rows: list[dict], pictures: list[Path]) -> str:
    return "\n".join(["| " + " | ".join(r["name"] for r in rows) + " |", "|" + "---|" * len(rows),
                      "| " + " | ".join(f"![{r['name']}]({p.name})" for r, p in zip(rows, pictures)) + " |", "",
                      "Red: colliding objects; magenta: out of bound; blue diagonals: more than 5 cm off the floor; "
                      "orange: floor an agent (radius 0.3 m) cannot reach from the largest free region."])


def program_section(proposal: dict) -> list[str]:
    """The reward program with its reasoning and decomposition, as Markdown lines."""
    author = "the offline planner" if proposal["source"] == "offline" else proposal["source"]
    lines = ["## Reward program", "", f"Written by {author}; weight {proposal['weight']:g} next to the "
             "universal rewards (the run may fix another: see its config).", "", proposal["reasoning"], "", "Decomposition:",
             *[f"- {d}" for d in proposal["decomposition"]]]
    if proposal.get("not_understood"):
        lines += ["", "Not understood (ignored): " + ", ".join(proposal["not_understood"])]
    return lines + ["", "```python", proposal["code"].rstrip(), "```", ""]
