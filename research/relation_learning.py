"""Can the scene prior learn a relation between objects, and from how many rooms? A controlled experiment sized
for 2 CPU cores: relation rates of samples from noise against rooms seen in training, one design variant a run.

The reduced setting (:func:`reduced_rooms`): procedural bedrooms with a rectangular floor (4 vertices), holding
only their bed, nightstands and wardrobes, every room with exactly one bed; ``--train-rooms`` (6,000) of seed 0 to
train on and ``--heldout`` (400) of seed 777, whose floors the priors are sampled on. A variant (``--variant``,
below) trains the small preset with ``--layers`` (4) layers, batch 128, a constant learning rate 5e-4 after 100
warm-up steps and EMA 0.999, until each of the cumulative training times ``--minutes`` (in stages:
``agents.pretrain.train(..., time_budget=...)`` resumes the run); at each the EMA prior is kept
(``OUT/prior_<minutes>min.pt``), sampled from noise on the held-out floors (20-step DDIM, eta 1; a
``classes_given`` prior with the held-out rooms' classes), and a row is written to ``--json`` (rewritten after
every budget, so a stopped run keeps its rows): minutes, steps, rooms seen (steps x batch), the last training loss,
and for the samples and the held-out data (:func:`figures`) the beds-per-room histogram (with the samples'
total-variation distance to the data's), objects and nightstands per room, rooms with a bed and >= 2 nightstands,
two_nightstands given that and over all rooms (:mod:`iarcs_env.relation_fidelity`), and wardrobe_back_to_wall
given a wardrobe (a relation to the walls, for comparison).

Variants (:data:`VARIANTS`; combine them with ``+``, e.g. ``slot_identity+min_snr``):

* ``present``: the design as shipped: exchangeable slots with permutation augmentation, classes as +-1 features
  diffused with the geometry, room-frame translations, epsilon prediction, uniform timesteps;
* ``slot_identity``: a learned per-slot embedding, the rooms' objects in a canonical order (by class index, empty
  slots last) and no permutation augmentation;
* ``classes_given``: the network is given each slot's clean class at every t (loss on geometry only) and samples
  with the held-out rooms' classes: can it place objects relative to each other when it need not choose them?
* ``x0``, ``v``: x0 or v prediction instead of epsilon;
* ``min_snr``: min-SNR-5 timestep weighting (more weight on the mid-noise steps).

    .venv/bin/python research/relation_learning.py --variant present --minutes 2.5 5 10 20 40 60
    .venv/bin/python research/relation_learning.py --plot out/relation_learning/*.json \\
        --png out/relation_learning/curves.png
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.denoiser import ScenePrior  # noqa: E402
from agents.pretrain import STATE_FILE, PretrainConfig, train  # noqa: E402
from agents.pretrain_data import SceneTensors  # noqa: E402
from iarcs_env.datasets.procedural import generate_room  # noqa: E402
from iarcs_env.relation_fidelity import relation_rates  # noqa: E402
from iarcs_env.relations import BEDS, class_mask  # noqa: E402
from iarcs_env.rooms import get_room  # noqa: E402
from iarcs_env.scene import Layout, SceneBatch  # noqa: E402

ROOM = get_room("bedroom")
KEPT = BEDS + ("nightstand", "wardrobe")
OUT = Path("out/relation_learning")

#: Variant name -> PretrainConfig fields (``model``: DenoiserConfig overrides).
VARIANTS: dict[str, dict] = {
    "present": {},
    "slot_identity": {"model": {"slot_embedding": True}, "canonical_order": True, "permutation_augment": False},
    "classes_given": {"classes_given": True},
    "x0": {"prediction_type": "sample"},
    "v": {"prediction_type": "v_prediction"},
    "min_snr": {"loss_weighting": "min_snr"},
}


def variant_options(name: str) -> dict:
    """The PretrainConfig fields of a variant, or of variants joined by ``+`` (later ones win)."""
    options: dict = {"model": {}}
    for part in name.split("+"):
        if part not in VARIANTS:
            raise ValueError(f"unknown variant {part!r}; choose from {', '.join(VARIANTS)} (join them with +)")
        fields = dict(VARIANTS[part])
        options["model"].update(fields.pop("model", {}))
        options.update(fields)
    return options


def reduced_rooms(count: int, seed: int) -> list[Layout]:
    """The first ``count`` procedural bedrooms of ``seed`` with a rectangular floor and exactly one bed, each with
    only its bed, nightstands and wardrobes."""
    rooms, index = [], 0
    while len(rooms) < count:
        lay = generate_room(ROOM.name, index, seed)
        index += 1
        keep = [i for i, label in enumerate(lay.labels) if label in KEPT]
        if len(lay.floor.vertices) == 4 and sum(lay.labels[i] in BEDS for i in keep) == 1:
            rooms.append(replace(lay, labels=[lay.labels[i] for i in keep], translations=lay.translations[keep],
                                 half_sizes=lay.half_sizes[keep], yaws=lay.yaws[keep],
                                 extras=[lay.extras[i] for i in keep]))
    return rooms


def histogram(counts: torch.Tensor) -> dict[str, float]:
    """{count: share of the rooms} of per-room counts (B,)."""
    values, n = torch.unique(counts, return_counts=True)
    return {str(int(v)): float(k) / len(counts) for v, k in zip(values, n)}


def total_variation(p: dict[str, float], q: dict[str, float]) -> float:
    return 0.5 * sum(abs(p.get(k, 0.0) - q.get(k, 0.0)) for k in set(p) | set(q))


def figures(scenes: SceneBatch | list[Layout]) -> dict:
    """The experiment's figures of a set of rooms (layouts in float64, or a decoded batch of samples)."""
    batch = scenes if isinstance(scenes, SceneBatch) else SceneBatch.from_layouts(scenes, num_slots=ROOM.max_objects)
    beds = class_mask(batch.labels, ROOM.classes, ["bed"]).sum(1)
    nightstands = class_mask(batch.labels, ROOM.classes, ["nightstand"]).sum(1)
    rates = relation_rates(scenes)
    two, wardrobe = rates["two_nightstands"], rates["wardrobe_back_to_wall"]
    return {"rooms": len(batch), "beds_per_room": histogram(beds), "one_bed": float((beds == 1).float().mean()),
            "objects_per_room": float(batch.mask.sum(1).float().mean()),
            "nightstands_per_room": float(nightstands.float().mean()),
            "bed_and_2_nightstands": two["co_occurrence_rate"],
            "two_nightstands_given": two["rate_given_co_occurrence"], "two_nightstands": two["rate"],
            "wardrobe_back_to_wall_given": wardrobe["rate_given_co_occurrence"]}


def sample_figures(prior: ScenePrior, heldout: list[Layout], cfg: PretrainConfig, seed: int, batch_size: int) -> dict:
    """:func:`figures` of the prior's samples from noise on the held-out floors (20-step DDIM, eta 1), a
    ``classes_given`` prior given the held-out rooms' classes (in the slot order it was trained with)."""
    classes = None
    if cfg.classes_given:
        classes = SceneTensors.from_layouts(heldout, ROOM.max_objects, canonical_order=cfg.canonical_order).labels
    scenes = prior.sample([lay.floor for lay in heldout], num_steps=20, eta=1.0,
                          generator=torch.Generator().manual_seed(seed), batch_size=batch_size, classes=classes)
    return figures(scenes)


def run(args) -> list[dict]:
    """Train one variant in stages and write a row per budget (module docstring)."""
    torch.set_num_threads(args.threads)
    options = variant_options(args.variant)
    out = Path(args.out or OUT / args.variant)
    json_path = Path(args.json or OUT / f"{args.variant}.json")
    if (out / STATE_FILE).exists():
        raise SystemExit(f"{out} holds a run already: remove it, or give another --out")
    t0 = time.perf_counter()
    train_rooms, heldout = reduced_rooms(args.train_rooms, args.seed), reduced_rooms(args.heldout, args.heldout_seed)
    data = figures(heldout)
    print(f"{len(train_rooms)} training rooms, {len(heldout)} held-out rooms in {time.perf_counter() - t0:.0f} s; "
          f"held-out data: {summary(data)}")
    record = {k: v for k, v in options.items() if k != "model" or v}
    cfg = PretrainConfig(
        room=ROOM.name, num_scenes=len(train_rooms), data_seed=args.seed, val_scenes=0, preset=args.preset,
        model={"num_layers": args.layers, **options.pop("model")}, steps=10**9, batch_size=args.batch_size,
        lr=args.lr, lr_schedule="constant", warmup_steps=args.warmup_steps, checkpoint_every=10**9, log_every=50,
        eval_every=10**9, out=str(out), seed=args.seed, num_threads=args.threads, device=args.device,
        tensorboard=False, **options)
    log = print if not args.quiet else (lambda *a, **k: None)
    rows, seconds = [], 0.0
    for minutes in sorted(args.minutes):
        result = train(cfg, layouts=train_rooms, time_budget=max(60 * minutes - seconds, 0.0), progress=not args.quiet,
                       log=log)
        seconds += result.seconds
        kept = out / f"prior_{minutes:g}min.pt"
        shutil.copyfile(result.prior_path, kept)
        t1 = time.perf_counter()
        samples = sample_figures(ScenePrior.load(kept), heldout, cfg, args.seed, args.sample_batch)
        rows.append({"variant": args.variant, "options": record, "budget_minutes": minutes,
                     "train_minutes": seconds / 60, "steps": result.step, "rooms_seen": result.step * cfg.batch_size,
                     "train_rooms": len(train_rooms), "loss": result.losses[-1][1] if result.losses else None,
                     "prior": str(kept), "beds_per_room_tv": total_variation(samples["beds_per_room"],
                                                                             data["beds_per_room"]),
                     "samples": samples, "data": data, "threads": args.threads, "device": args.device})
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(rows, indent=1))
        print(f"{args.variant} {minutes:g} min: {result.step} steps, {result.step * cfg.batch_size} rooms seen; "
              f"samples ({time.perf_counter() - t1:.0f} s): {summary(samples)}")
    return rows


def summary(f: dict) -> str:
    pct = lambda v: "-" if v is None else f"{100 * v:.1f}%"  # noqa: E731
    beds = " ".join(f"{k}:{100 * v:.0f}%" for k, v in sorted(f["beds_per_room"].items(), key=lambda kv: int(kv[0])))
    return (f"beds/room {{{beds}}}, objects/room {f['objects_per_room']:.2f}, bed+2 nightstands "
            f"{pct(f['bed_and_2_nightstands'])}, two_nightstands given it {pct(f['two_nightstands_given'])}, "
            f"over all {pct(f['two_nightstands'])}")


# --- the curves -------------------------------------------------------------------------------------------
PANELS = (  # title, figure key, scale
    ("two_nightstands, all rooms (%)", "two_nightstands", 100),
    ("two_nightstands given bed + 2 nightstands (%)", "two_nightstands_given", 100),
    ("rooms with a bed and >= 2 nightstands (%)", "bed_and_2_nightstands", 100),
    ("rooms with exactly one bed (%)", "one_bed", 100),
    ("objects per room", "objects_per_room", 1),
)
COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
           "#17becf"]


def plot(files: list[str], png: str) -> Path:
    """Curves of every variant in ``files`` (rows of :func:`run`) against rooms seen (log scale), one panel per
    figure of :data:`PANELS`, the held-out data's value dashed; drawn with Pillow."""
    from PIL import Image, ImageDraw, ImageFont

    rows = [row for f in files for row in json.loads(Path(f).read_text())]
    if not rows:
        raise SystemExit("no rows to plot")
    variants = list(dict.fromkeys(row["variant"] for row in rows))
    try:
        font = ImageFont.load_default(size=13)
    except TypeError:  # an old Pillow: the bitmap font
        font = ImageFont.load_default()
    w, h, left, top, bottom = 440, 300, 50, 28, 36
    image = Image.new("RGB", (3 * w, 2 * h), "white")
    draw = ImageDraw.Draw(image)
    seen = np.log10([row["rooms_seen"] for row in rows if row["rooms_seen"] > 0] or [1.0])
    x_lo, x_hi = seen.min() - 0.1, seen.max() + 0.1
    for p, (title, key, scale) in enumerate(PANELS):
        ox, oy = (p % 3) * w, (p // 3) * h
        pw, ph = w - left - 15, h - top - bottom
        value = lambda f: None if f[key] is None else f[key] * scale  # noqa: E731
        ys = [value(r["samples"]) for r in rows] + [value(rows[0]["data"])]
        y_max = max([v for v in ys if v is not None] + [1e-9])
        step = next(m * 10 ** np.floor(np.log10(y_max / 4)) for m in (1, 2, 5, 10)
                    if m * 10 ** np.floor(np.log10(y_max / 4)) >= y_max / 4)  # 1, 2 or 5 x 10^k
        y_hi = step * np.ceil(y_max * 1.02 / step)
        if scale == 100:  # a percentage: at most 100
            y_hi = min(y_hi, step * np.ceil(100 / step))
        to_xy = lambda x, y: (ox + left + (np.log10(x) - x_lo) / (x_hi - x_lo) * pw,  # noqa: E731
                              oy + top + ph - y / y_hi * ph)
        draw.text((ox + left, oy + 6), title, fill="black", font=font)
        draw.rectangle([ox + left, oy + top, ox + left + pw, oy + top + ph], outline="black")
        for k in range(int(round(y_hi / step)) + 1):  # y ticks
            y = k * step
            _, py = to_xy(10 ** x_lo, y)
            draw.line([ox + left - 4, py, ox + left, py], fill="black")
            draw.text((ox + 4, py - 7), f"{y:.3g}", fill="black", font=font)
        for e in range(int(np.floor(x_lo)), int(np.ceil(x_hi)) + 1):  # x ticks at 1, 2, 5 x 10^e
            for m in (1, 2, 5):
                if x_lo <= np.log10(m * 10 ** e) <= x_hi:
                    px, _ = to_xy(m * 10 ** e, 0)
                    draw.line([px, oy + top + ph, px, oy + top + ph + 4], fill="black")
                    draw.text((px - 10, oy + top + ph + 5), rooms_label(m * 10 ** e), fill="black", font=font)
        data = value(rows[0]["data"])
        if data is not None:
            _, py = to_xy(10 ** x_lo, data)
            for x in range(ox + left, ox + left + pw, 12):
                draw.line([x, py, min(x + 6, ox + left + pw), py], fill="black", width=2)
        for v, name in enumerate(variants):
            pts = sorted((r["rooms_seen"], value(r["samples"])) for r in rows
                         if r["variant"] == name and r["rooms_seen"] > 0 and value(r["samples"]) is not None)
            xy = [to_xy(x, y) for x, y in pts]
            colour = COLOURS[v % len(COLOURS)]
            if len(xy) > 1:
                draw.line(xy, fill=colour, width=2)
            for px, py in xy:
                draw.ellipse([px - 3, py - 3, px + 3, py + 3], fill=colour)
        draw.text((ox + left + pw // 2 - 30, oy + h - 15), "rooms seen", fill="black", font=font)
    ox, oy = 2 * w + 20, h + 20  # the legend, in the sixth cell
    for v, name in enumerate(variants + ["held-out data"]):
        y = oy + 20 * v
        if v < len(variants):
            draw.line([ox, y + 7, ox + 30, y + 7], fill=COLOURS[v % len(COLOURS)], width=3)
        else:
            draw.line([ox, y + 7, ox + 12, y + 7], fill="black", width=2)
            draw.line([ox + 18, y + 7, ox + 30, y + 7], fill="black", width=2)
        draw.text((ox + 38, y), name, fill="black", font=font)
    out = Path(png)
    out.parent.mkdir(parents=True, exist_ok=True)
    image.save(out)
    return out


def rooms_label(n: float) -> str:
    return f"{n / 1e6:g}M" if n >= 1e6 else f"{n / 1e3:g}k" if n >= 1e3 else f"{n:g}"


def table(files: list[str]) -> str:
    """The rows of ``files`` as a Markdown table (the data's figures last; "-" where a rate has no rooms)."""
    pct = lambda v, digits=1: "-" if v is None else f"{v:.{digits}%}"  # noqa: E731
    lines = ["| variant | minutes | rooms seen | exactly one bed | beds/room TVD | objects/room | bed + >= 2 nightstands "
             "| two_nightstands given it | wardrobe against a wall given it |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    data = None
    for path in files:
        for r in json.loads(Path(path).read_text()):
            s, data = r["samples"], r["data"]
            lines.append(f"| {r['variant']} | {r['budget_minutes']:g} | {r['rooms_seen']:,} | {pct(s['one_bed'], 0)} | "
                         f"{r['beds_per_room_tv']:.2f} | {s['objects_per_room']:.2f} | {pct(s['bed_and_2_nightstands'])} | "
                         f"{pct(s['two_nightstands_given'])} | {pct(s['wardrobe_back_to_wall_given'], 0)} |")
    if data is not None:
        lines.append(f"| held-out data ({data['rooms']} rooms) | | | {pct(data['one_bed'], 0)} | 0 | "
                     f"{data['objects_per_room']:.2f} | {pct(data['bed_and_2_nightstands'])} | "
                     f"{pct(data['two_nightstands_given'])} | {pct(data['wardrobe_back_to_wall_given'], 0)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variant", default="present", help=f"one of {', '.join(VARIANTS)}, or several joined by +")
    ap.add_argument("--minutes", type=float, nargs="+", default=[2.5, 5, 10, 20],
                    help="cumulative training times (minutes) at which the prior is sampled")
    ap.add_argument("--json", help="the rows (default out/relation_learning/VARIANT.json)")
    ap.add_argument("--out", help="the training run's folder (default out/relation_learning/VARIANT)")
    ap.add_argument("--train-rooms", type=int, default=6000)
    ap.add_argument("--heldout", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0, help="seed of the training rooms, the training run and sampling")
    ap.add_argument("--heldout-seed", type=int, default=777)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--layers", type=int, default=4)
    ap.add_argument("--batch-size", type=int, default=128)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--warmup-steps", type=int, default=100)
    ap.add_argument("--sample-batch", type=int, default=100, help="floors sampled together")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1: two variants side by side on 2 cores)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quiet", action="store_true", help="no progress bar or training log")
    ap.add_argument("--plot", nargs="+", metavar="JSON",
                    help="draw the curves of these row files instead, and print them as a Markdown table")
    ap.add_argument("--png", default=str(OUT / "curves.png"), help="where --plot writes")
    args = ap.parse_args(argv)
    if args.plot:
        print(f"wrote {plot(args.plot, args.png)}")
        print(table(args.plot))
    else:
        variant_options(args.variant)  # an unknown name fails before the data is generated
        run(args)


if __name__ == "__main__":
    main()
