"""``iarcs data``: generate, convert, render and summarise layout datasets."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
from tqdm import tqdm

from experiments.cli import finite_float
from iarcs_env.datasets import is_atiss_folder, load_layouts, save_layouts
from iarcs_env.render import image_grid, render_layout, save_image
from iarcs_env.rooms import get_room


def register(sub) -> None:
    data = sub.add_parser("data", help="generate, convert, render and summarise layout datasets")
    dsub = data.add_subparsers(dest="data_command", metavar="ACTION")
    dsub.required = True

    p = dsub.add_parser("generate", help="procedural ('synthetic 3D-FRONT') rooms as neutral JSON")
    p.add_argument("--room", required=True, help="bedroom, livingroom or diningroom")
    p.add_argument("--num-scenes", type=int, default=500)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--flaw-rate", type=finite_float, default=1.0,
                   help="0: no deliberate collisions or wall crossings; 1: flaw rates like real 3D-FRONT")
    p.add_argument("--out", required=True, help="output .json (or a folder for ATISS format)")
    p.set_defaults(func=cmd_generate)

    p = dsub.add_parser("convert", help="neutral JSON <-> ATISS preprocessed folder (by what the paths are)")
    p.add_argument("--in", dest="src", required=True, help=".json file or ATISS folder")
    p.add_argument("--out", required=True, help="ATISS folder (when --in is JSON) or .json file")
    p.add_argument("--room", help="keep only this room type")
    p.set_defaults(func=cmd_convert)

    p = dsub.add_parser("render", help="top-down PNG renders of a layout file")
    p.add_argument("--in", dest="src", required=True, help=".json file or ATISS folder")
    p.add_argument("--out", required=True, help="folder for the PNG files")
    p.add_argument("--limit", type=int, default=None, help="render only the first K scenes")
    p.add_argument("--size", type=int, default=256, help="image size in pixels (default 256)")
    p.set_defaults(func=cmd_render)

    p = dsub.add_parser("export", help="rooms as 3D files (glTF binary or OBJ) and a 3D viewer page")
    p.add_argument("--in", dest="src", required=True, help=".json file or ATISS folder")
    p.add_argument("--out", required=True, help="folder for one file per room and viewer.html")
    p.add_argument("--format", choices=("glb", "obj"), default="glb", help="glb (default; keeps metadata) or obj (+ .mtl)")
    p.add_argument("--limit", type=int, default=None, help="export only the first K scenes")
    p.add_argument("--future-dir", help="your 3D-FUTURE-model folder: objects shown with their furniture models "
                   "(by jid, else the closest model of the class by size)")
    p.set_defaults(func=cmd_export)

    p = dsub.add_parser("stats", help="counts, class frequencies, sizes and room areas of a layout file")
    p.add_argument("--in", dest="src", required=True, help=".json file or ATISS folder")
    p.add_argument("--json", dest="as_json", action="store_true", help="print JSON instead of tables")
    p.set_defaults(func=cmd_stats)


def _positive(value: int | None, name: str) -> None:
    from experiments.cli import CLIError

    if value is not None and value <= 0:
        raise CLIError(f"{name} must be a positive number, got {value}")


def cmd_generate(args) -> int:
    from iarcs_env.datasets.procedural import generate_layouts

    _positive(args.num_scenes, "--num-scenes")
    room = get_room(args.room)
    layouts = generate_layouts(room.name, args.num_scenes, seed=args.seed, flaw_rate=args.flaw_rate, progress=True)
    out = save_layouts(layouts, args.out, generator="iarcs procedural", seed=args.seed, flaw_rate=args.flaw_rate)
    print(f"wrote {len(layouts)} {room.name}s to {out}")
    return 0


def cmd_convert(args) -> int:
    from experiments.cli import CLIError

    src, out = Path(args.src), Path(args.out)
    if src.suffix.lower() == ".json" and out.suffix.lower() == ".json":
        raise CLIError("--in and --out are both .json: give a folder as --out to write ATISS format")
    if src.is_dir() and not is_atiss_folder(src):
        raise CLIError(f"{src} is a folder but not an ATISS preprocessed folder (no */boxes.npz)")
    layouts = load_layouts(src, args.room)
    if not layouts:
        raise CLIError(f"{src} holds no scenes" + (f" of room type {args.room}" if args.room else ""))
    rooms = sorted({lay.room_type for lay in layouts})
    if out.suffix.lower() != ".json" and len(rooms) > 1:
        raise CLIError(f"an ATISS folder holds one room type; {src} has {', '.join(rooms)}: pick one with --room")
    save_layouts(layouts, out)
    kind = "neutral JSON" if out.suffix.lower() == ".json" else "an ATISS folder"
    print(f"wrote {len(layouts)} scenes as {kind} to {out}")
    return 0


def cmd_render(args) -> int:
    _positive(args.limit, "--limit")
    layouts = load_layouts(args.src)[: args.limit]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    images = []
    for i, lay in enumerate(tqdm(layouts, desc="rendering", unit="scene")):
        img = render_layout(lay, size=args.size, legend=True, title=lay.id[-40:])
        save_image(img, out / f"{i:05d}.png")
        if len(images) < 16:
            images.append(render_layout(lay, size=args.size))
    if images:
        save_image(image_grid(images, cols=4, titles=[lay.id[-24:] for lay in layouts[:16]]), out / "overview.png")
    print(f"wrote {len(layouts)} renders to {out}/ (first 16 tiled in {out / 'overview.png'})")
    return 0


def cmd_export(args) -> int:
    from experiments.cli import CLIError
    from iarcs_env.future import FutureModels
    from iarcs_env.scene3d import file_stem, layout_scene, scene_flags, write_scene
    from iarcs_env.viewer import VIEWER_ROOMS, ViewerNotBuilt, write_viewer

    _positive(args.limit, "--limit")
    models = FutureModels(args.future_dir) if args.future_dir else None
    layouts = load_layouts(args.src)[: args.limit]
    if not layouts:
        raise CLIError(f"{args.src} holds no scenes")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    flags = scene_flags(layouts)
    shown = []
    for i, (lay, flag) in enumerate(tqdm(list(zip(layouts, flags)), desc="exporting", unit="room")):
        scene = layout_scene(lay, flag, models)
        write_scene(scene, out / file_stem(i, lay), args.format)
        if len(shown) < VIEWER_ROOMS:
            shown.append((f"{i}: {lay.id}", scene))
    print(f"wrote {len(layouts)} rooms as .{args.format} to {out}/")
    if models is not None:
        print("3D-FUTURE: " + ", ".join(f"{n} {what}" for what, n in sorted(models.report.items())))
    try:
        page = write_viewer(shown, out / "viewer.html", title=f"{Path(args.src).name}: {len(shown)} rooms")
        print(f"3D viewer: {page}" + (f" (the first {len(shown)} rooms)" if len(shown) < len(layouts) else ""))
    except ViewerNotBuilt as e:
        print(f"no 3D viewer written: {e}")
    return 0


def dataset_summary(layouts) -> dict:
    """Counts, class frequencies, object sizes (full extents, metres) and room areas of layouts."""
    counts = np.array([len(l) for l in layouts])
    areas = np.array([l.floor.area for l in layouts])
    labels = Counter(lbl for l in layouts for lbl in l.labels)
    total = max(sum(labels.values()), 1)
    sizes: dict[str, list] = {}
    for l in layouts:
        for lbl, h in zip(l.labels, l.half_sizes):
            sizes.setdefault(lbl, []).append(2 * h)
    return {
        "scenes": len(layouts),
        "room_types": dict(Counter(l.room_type for l in layouts)),
        "objects": int(counts.sum()),
        "objects_per_scene": {"mean": float(counts.mean()), "min": int(counts.min()), "max": int(counts.max()),
                              "histogram": np.bincount(counts).tolist()},
        "class_frequencies": {k: v / total for k, v in labels.most_common()},
        "class_sizes_m": {k: {"mean_xyz": np.mean(v, 0).round(3).tolist(), "min_xyz": np.min(v, 0).round(3).tolist(),
                              "max_xyz": np.max(v, 0).round(3).tolist()} for k, v in sizes.items()},
        "room_area_m2": {"median": float(np.median(areas)), "p10": float(np.percentile(areas, 10)),
                         "p90": float(np.percentile(areas, 90)), "mean": float(areas.mean())},
        "non_rectangular_fraction": float(np.mean([not l.floor.is_rectangle for l in layouts])),
    }


def cmd_stats(args) -> int:
    from experiments.cli import CLIError

    layouts = load_layouts(args.src)
    if not layouts:
        raise CLIError(f"{args.src} holds no scenes")
    s = dataset_summary(layouts)
    if args.as_json:
        print(json.dumps(s, indent=1))
        return 0
    o = s["objects_per_scene"]
    a = s["room_area_m2"]
    print(f"{args.src}: {s['scenes']} scenes ({', '.join(f'{v} {k}' for k, v in s['room_types'].items())}), "
          f"{s['objects']} objects")
    print(f"objects per scene: mean {o['mean']:.2f}, min {o['min']}, max {o['max']}; histogram {o['histogram']}")
    print(f"room area (m^2): median {a['median']:.1f}, 10-90% {a['p10']:.1f}-{a['p90']:.1f}; "
          f"non-rectangular {100 * s['non_rectangular_fraction']:.0f}%")
    print(f"\n{'class':<20} {'freq':>6}  {'mean size x/y/z (m)':>22}")
    for k, f in s["class_frequencies"].items():
        m = s["class_sizes_m"][k]["mean_xyz"]
        print(f"{k:<20} {100 * f:5.1f}%  {m[0]:6.2f} {m[1]:6.2f} {m[2]:6.2f}")
    return 0
