"""``iarcs evaluate``: the paper's metrics for a layout file, as JSON and as a Markdown table.

    iarcs evaluate --scenes generated.json [--reference real.json] --out report.json \\
        [--render-issues DIR] [--features cnn | clip:PATH | none] [--task NAME ... | --task all]

Writes ``report.json`` (``Col_obj``, ``Col_scene``, ``R_out``, ``R_reach``, ``R_walkable`` as fractions in
[0, 1], counts, and with ``--reference`` the class-frequency KL, the object-count distance and FID / KID /
SCA on top-down renders, naming the feature extractor) and ``report.md`` next to it (a table in the style
of the paper's Table 2). ``--render-issues DIR`` writes a PNG per scene with a problem: colliding objects
outlined red, out-of-bound objects magenta, unreachable free floor hatched orange. ``--task NAME``
(repeatable, or ``all``) adds ``task_success_<name>``, the fraction of scenes passing the paper task's
hand-written checker (:mod:`iarcs_env.tasks`), to both reports, and each scene's pass/fail to ``per_scene``.

Both reports also have a ``relations`` section (:mod:`iarcs_env.relation_fidelity`; definitions in
``docs/design.md``, "Relations"): per relation of the room type, the rooms with its co-occurrence, the rate at
which it holds given the co-occurrence and over all rooms, with ``--reference`` side by side with the
reference's and their ratio (relation recall); ``per_scene`` says, for each relation whose objects a scene has,
whether it holds.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

from experiments.cli import finite_float

HEADLINE_HELP = "Col_obj, Col_scene, R_out, R_reach, R_walkable"


def register(sub) -> None:
    p = sub.add_parser("evaluate", help=f"metrics of a layout file ({HEADLINE_HELP}, FID/KID/SCA)",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", required=True, help="layouts to evaluate: neutral .json or an ATISS folder")
    p.add_argument("--reference", help="real layouts (.json or ATISS folder) for KL, count distance, FID, KID, SCA")
    p.add_argument("--out", required=True, help="report .json (a .md table is written next to it)")
    p.add_argument("--render-issues", metavar="DIR", help="write a marked render of each scene with an issue")
    p.add_argument("--max-renders", type=int, default=100, help="at most this many issue renders (default 100)")
    p.add_argument("--features", default="cnn",
                   help="feature extractor for FID/KID with --reference: 'cnn' (the project's CNN trained on "
                        "the reference renders; default), 'clip:PATH' (a local CLIP checkpoint) or 'none'")
    p.add_argument("--task", action="append", default=[], metavar="NAME",
                   help="also report the success rate of this paper task (repeatable, or 'all'): "
                        "reach_1m, tv_from_bed, study_zone, two_nightstands, wheelchair")
    p.add_argument("--room", help="evaluate only this room type (when the file mixes several)")
    p.add_argument("--name", help="row name in the Markdown table (default: the scenes file name)")
    p.add_argument("--cell", type=finite_float, default=0.05, help="walkable grid cell in metres (default 0.05)")
    p.add_argument("--agent-radius", type=finite_float, default=0.3, help="agent radius in metres (default 0.3)")
    p.add_argument("--render-size", type=int, default=64, help="render size for FID/KID/SCA (default 64)")
    p.add_argument("--seed", type=int, default=0, help="seed of the feature CNN and the SCA classifier")
    p.set_defaults(func=cmd_evaluate)


def _load(path: str, room: str | None, what: str):
    from experiments.cli import CLIError
    from iarcs_env.datasets import load_layouts
    from iarcs_env.rooms import get_room

    if not Path(path).exists():
        raise CLIError(f"{what} file {path} does not exist")
    layouts = load_layouts(path, room)
    if room:
        layouts = [lay for lay in layouts if get_room(lay.room_type).name == get_room(room).name]
    if not layouts:
        raise CLIError(f"{what} file {path} holds no {room + ' ' if room else ''}scenes")
    kinds = sorted({get_room(lay.room_type).name for lay in layouts})
    if len(kinds) > 1:
        raise CLIError(f"{what} file {path} mixes room types ({', '.join(kinds)}); choose one with --room")
    return layouts


def cmd_evaluate(args) -> int:
    from experiments.cli import CLIError
    from iarcs_env.metrics import evaluate_layouts

    if args.cell <= 0 or args.agent_radius < 0:
        raise CLIError("--cell must be positive and --agent-radius not negative")
    features = None if args.features in ("none", "", None) else args.features
    if features and features != "cnn" and not features.startswith("clip:"):
        raise CLIError(f"--features must be 'cnn', 'clip:PATH' or 'none', not {args.features!r}")
    tasks = _tasks(args.task)
    layouts = _load(args.scenes, args.room, "--scenes")
    reference = _load(args.reference, args.room or layouts[0].room_type, "--reference") if args.reference else None
    out = Path(args.out)
    if out.suffix.lower() != ".json":
        raise CLIError(f"--out must name a .json file, got {out}")

    result = evaluate_layouts(layouts, reference=reference, cell=args.cell, agent_radius=args.agent_radius,
                              keep_scenes=True, keep_masks=bool(args.render_issues), progress=True,
                              features=features if reference is not None else None,
                              distribution_kwargs={"size": args.render_size, "seed": args.seed})
    scenes = result.pop("scenes")
    relation_flags, result["relations"] = relations_report(layouts, reference)
    passed = {}
    if tasks:
        from iarcs_env.tasks import task_results

        for name in tasks:
            passed[name] = task_results(name, layouts)
            result[f"task_success_{name}"] = float(passed[name].mean())
    if reference is None:
        result["feature_extractor"] = "none (no --reference: no FID/KID/SCA)"
    elif not features:
        result["feature_extractor"] = "none (--features none)"
    result["scenes_file"] = str(args.scenes)
    result["reference_file"] = str(args.reference) if args.reference else None
    result["command"] = "iarcs " + " ".join(_quote(a) for a in sys.argv[1:]) if _is_cli() else None
    result["per_scene"] = [
        {"id": s.id, "objects": s.n_objects, "ground_objects": s.n_ground, "colliding": s.colliding, "out_of_bound": s.out_of_bound,
         "unreachable_objects": s.unreachable_objects, "R_walkable": round(s.walkable, 6),
         "penetration_m3": round(s.penetration, 6), "out_area_m2": round(s.out_area, 6),
         **({"tasks": {name: bool(ok[i]) for name, ok in passed.items()}} if passed else {}),
         "relations": {name: bool(holds[i]) for name, (co, holds) in relation_flags.items() if co[i]}}
        for i, s in enumerate(scenes)]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    md = out.with_suffix(".md")
    md.write_text(markdown_report(result, args.name or Path(args.scenes).stem))
    print(markdown_table(result, args.name or Path(args.scenes).stem))
    if tasks:
        print("\n" + task_table(result))
    print("\n" + relations_table(result))
    print(f"\nfeature extractor: {result['feature_extractor']}")
    print(f"report: {out}\ntable: {md}")
    if args.render_issues:
        n = render_issues(layouts, scenes, Path(args.render_issues), args.max_renders)
        print(f"issue renders: {n} in {args.render_issues}")
    return 0


def relations_report(layouts, reference) -> tuple[dict, dict]:
    """(per-scene flags of the scenes, the report's ``relations`` section): per relation its definition, the
    scenes' rates, and with a reference the reference's rates and the relation recall."""
    from iarcs_env.relation_fidelity import compare_relations, rates_of, relation_flags, relation_rates, room_relations

    flags = relation_flags(layouts)
    section = compare_relations({name: rates_of(*f) for name, f in flags.items()},
                                relation_rates(reference) if reference is not None else None)
    for r in room_relations(layouts[0].room_type):
        section[r.name] = {"definition": {"co_occurrence": r.co_occurrence, "holds": r.holds}, **section[r.name]}
    return flags, section


def relations_table(result: dict) -> str:
    """The Markdown table of the report's ``relations`` section."""
    from iarcs_env.relation_fidelity import relation_table

    return relation_table(result["relations"])


def _tasks(names: list[str]) -> list[str]:
    """Task names from ``--task`` values ('all', or names, possibly comma-separated), in order, unique."""
    from experiments.cli import CLIError
    from iarcs_env.tasks import TASKS, get_task

    out: list[str] = []
    for value in names:
        for name in filter(None, (n.strip() for n in value.split(","))):
            try:
                picked = list(TASKS) if name.lower() == "all" else [get_task(name).name]
            except ValueError as err:
                raise CLIError(f"--task: {err}") from None
            out += [n for n in picked if n not in out]
    return out


def task_table(result: dict) -> str:
    """Task success rates (%) of the ``task_success_<name>`` entries, one column per task."""
    names = [k[len("task_success_"):] for k in result if k.startswith("task_success_")]
    return "\n".join(["| Task success % ↑ | " + " | ".join(names) + " |", "|---|" + "---|" * len(names),
                      "| | " + " | ".join(f"{100 * result['task_success_' + n]:.1f}" for n in names) + " |"])


def _is_cli() -> bool:
    return Path(sys.argv[0]).name in ("iarcs", "cli.py") or sys.argv[0].endswith("experiments.cli")


def _quote(arg: str) -> str:
    return arg if re.fullmatch(r"[\w./:=+-]+", arg) else "'" + arg.replace("'", "'\\''") + "'"


def _pct(v) -> str:
    return "–" if v is None else f"{100 * v:.2f}"


def markdown_table(result: dict, name: str) -> str:
    """One-row table in the style of the paper's Table 2 (percentages for the fractions)."""
    cols = [("FID ↓", lambda r: f"{r['FID']:.2f}" if "FID" in r else "–"),
            ("KID×0.001 ↓", lambda r: f"{r['KID'] * 1000:.2f}" if "KID" in r else "–"),
            ("SCA % (50 best)", lambda r: f"{100 * r['SCA']:.1f}" if "SCA" in r else "–"),
            ("KL_class ↓", lambda r: f"{r['KL_class']:.4f}" if "KL_class" in r else "–"),
            ("Col_obj % ↓", lambda r: _pct(r["Col_obj"])),
            ("Col_scene % ↓", lambda r: _pct(r["Col_scene"])),
            ("R_out % ↓", lambda r: _pct(r["R_out"])),
            ("R_reach % ↑", lambda r: _pct(r["R_reach"])),
            ("R_walkable ↑", lambda r: f"{r['R_walkable']:.3f}"),
            ("R_off_floor % ↓", lambda r: _pct(r.get("R_off_floor"))),
            ("R_misaligned % ↓", lambda r: _pct(r.get("R_misaligned")))]
    head = "| Method | " + " | ".join(c for c, _ in cols) + " |"
    rule = "|---|" + "---|" * len(cols)
    row = f"| {name} | " + " | ".join(f(result) for _, f in cols) + " |"
    return "\n".join([head, rule, row])


def markdown_report(result: dict, name: str) -> str:
    lines = [f"# Evaluation: {name}", "", markdown_table(result, name), "",
             f"- scenes: {result['n_scenes']} {result['room_type']}s from `{result.get('scenes_file')}`, "
             f"{result['n_objects']} objects ({result['n_ground_objects']} ground objects), "
             f"{result['mean_objects']:.2f} per scene"]
    if result.get("reference_file"):
        lines.append(f"- reference: {result['n_reference_scenes']} scenes from `{result['reference_file']}` "
                     f"({result['reference_mean_objects']:.2f} objects per scene); object-count distance "
                     f"(earth mover's) {result['count_distance']:.3f}")
        if "footprint_change" in result:
            by_class = list(result["footprint_change_by_class"].items())[:4]  # the most frequent classes
            lines.append(f"- footprints against the reference's objects of the same classes: "
                         f"{100 * result['footprint_change']:+.1f}% (geometric mean; "
                         + ", ".join(f"{c} {100 * v:+.1f}%" for c, v in by_class) + ")")
    if any(k.startswith("task_success_") for k in result):
        lines[4:4] = [task_table(result), ""]
    lines.append(f"- feature extractor: {result['feature_extractor']}")
    if "render_size" in result:
        lines.append(f"- renders for FID/KID/SCA: {result['render_size']} px, fixed view of "
                     f"±{result['render_extent']} m")
    lines.append(f"- walkable grid: {result['cell']} m cells, agent radius {result['agent_radius']} m")
    if result.get("command"):
        lines.append(f"- command: `{result['command']}`")
    lines += ["", "Definitions (iarcs_env/metrics.py): ground objects exclude ceiling and pendant lamps; a collision is a 3D "
              "box overlap > 1e-6 m³ between ground objects; an object is out of bound when its footprint, shrunk "
              "by 0.05 m per side, has > 1e-5 m² outside the floor; R_walkable = largest 4-connected free region "
              "/ free cells; R_reach = ground objects whose inflated footprint touches that region; R_off_floor (our "
              "addition) = ground objects whose bottom is more than 0.05 m above or below the floor; R_misaligned (our "
              "addition) = ground objects turned more than 10° away from every wall direction.", ""]
    if result.get("relations"):
        lines += ["## Relations", "", relations_table(result), "",
                  "Per relation: rooms with its co-occurrence (the objects it needs), the rate at which it holds given "
                  "the co-occurrence, and over all rooms"
                  + ("; recall = the scenes' rate over all rooms / the reference's (– where the reference's is 0)"
                     if result.get("reference_file") else "")
                  + ". Definitions: `docs/design.md`, section Relations:", ""]
        lines += [f"- {name}: co-occurrence {v['definition']['co_occurrence']}; holds: {v['definition']['holds']}"
                  for name, v in result["relations"].items()] + [""]
    if any(k.startswith("task_success_") for k in result):
        lines += ["Task success: the fraction of scenes passing the task's hand-written checker (definitions in "
                  "`iarcs_env/tasks.py`).", ""]
    return "\n".join(lines)


def render_issues(layouts, scenes, folder: Path, limit: int) -> int:
    """PNG renders of the scenes with issues, marked with :class:`iarcs_env.render.Overlays`."""
    from tqdm import tqdm

    from iarcs_env.render import render_layout, save_image

    folder.mkdir(parents=True, exist_ok=True)
    todo = [(i, s) for i, s in enumerate(scenes) if s.has_issue or (s.unreachable is not None and s.unreachable[0].any())]
    todo = todo[:limit]
    for i, s in tqdm(todo, desc="render issues", unit="scene"):
        lay = layouts[i].centred()
        unreachable = ",".join(lay.labels[k] for k in s.unreachable_objects)
        title = (f"{len(s.colliding)} colliding (red), {len(s.out_of_bound)} out (magenta), walkable {s.walkable:.2f}"
                 + (f"; unreachable: {unreachable}" if unreachable else ""))
        img = render_layout(lay, size=320, overlays=s.overlays(), legend=True, title=title[:75])
        safe = re.sub(r"[^\w.-]+", "_", s.id)[:60] or f"scene_{i:05d}"
        save_image(img, folder / f"{i:05d}_{safe}.png")
    return len(todo)
