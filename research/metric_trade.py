"""Two metrics of several runs against each other, one labelled point per `iarcs evaluate` report, drawn with Pillow:
for a trade between them (in dining rooms, Col_obj against R_reach across stage-1 runs). A point may pool several
samplings: ``LABEL=A.json,B.json,...``, each metric weighed by what it is a share of (objects for Col_obj and R_out,
ground objects for R_reach, rooms otherwise), as ``iarcs compare`` pools them.

    .venv/bin/python research/metric_trade.py --x Col_obj --y R_reach --png docs/figures/stage1_dining_trade.png \
        data=DATA_REPORT.json prior=P_S0_report.json,P_S1_report.json "ranked=R_S0_report.json,R_S1_report.json" ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


#: what each metric is a share of, for pooling samplings (the report's count field); rooms for any other
WEIGHTS = {"Col_obj": "n_objects", "R_out": "n_objects", "R_reach": "n_ground_objects"}


def points(files: list[str], x: str, y: str) -> list[tuple[str, float, float]]:
    """(label, x, y) of each ``LABEL=REPORT.json[,REPORT.json...]`` (metrics that are fractions come out in percent;
    several reports pooled)."""
    out = []
    for arg in files:
        label, sep, paths = arg.rpartition("=")
        if not sep:
            raise SystemExit(f"expected LABEL=REPORT.json, got {arg!r}")
        reports = []
        for path in paths.split(","):
            report = json.loads(Path(path).read_text())
            missing = [m for m in (x, y) if m not in report]
            if missing:
                raise SystemExit(f"{path} has no {', '.join(missing)} (an `iarcs evaluate` report has Col_obj, "
                                 "R_reach, ...)")
            reports.append(report)
        out.append((label, *(100 * pooled(reports, m) for m in (x, y))))
    return out


def pooled(reports: list[dict], metric: str) -> float:
    """``metric`` over several reports, each weighed by its count of what the metric is a share of (one report:
    its value)."""
    if len(reports) == 1:
        return reports[0][metric]
    weights = [r[WEIGHTS.get(metric, "n_scenes")] for r in reports]
    return sum(w * r[metric] for w, r in zip(weights, reports)) / sum(weights)


def plot(pts: list[tuple[str, float, float]], x: str, y: str, png: str) -> Path:
    from PIL import Image, ImageDraw, ImageFont

    try:
        font = ImageFont.load_default(size=13)
    except TypeError:  # an old Pillow: the bitmap font
        font = ImageFont.load_default()
    w, h, left, top, right, bottom = 720, 440, 60, 40, 20, 45
    xs, ys = [p[1] for p in pts], [p[2] for p in pts]
    x_lo, x_hi = 5 * (min(xs) // 5), 5 * (max(xs) // 5 + 1)
    y_lo, y_hi = 2 * (min(ys) // 2), 2 * (max(ys) // 2 + 1)
    pw, ph = w - left - right, h - top - bottom

    def to_xy(vx, vy):
        return left + (vx - x_lo) / (x_hi - x_lo) * pw, top + ph - (vy - y_lo) / (y_hi - y_lo) * ph

    image = Image.new("RGB", (w, h), "white")
    draw = ImageDraw.Draw(image)
    draw.rectangle([left, top, left + pw, top + ph], outline="black")
    for vx in range(int(x_lo), int(x_hi) + 1, 5):
        px, _ = to_xy(vx, y_lo)
        draw.line([px, top + ph, px, top + ph + 4], fill="black")
        draw.text((px - 8, top + ph + 6), f"{vx}", fill="black", font=font)
    for vy in range(int(y_lo), int(y_hi) + 1, 2):
        _, py = to_xy(x_lo, vy)
        draw.line([left - 4, py, left, py], fill="black")
        draw.text((left - 30, py - 7), f"{vy}", fill="black", font=font)
    draw.text((left + pw // 2 - 30, h - 18), f"{x} (%)", fill="black", font=font)
    draw.text((6, 10), f"{y} (%)", fill="black", font=font)
    placed = []  # label boxes drawn so far: a label that would overlap one moves down
    for label, vx, vy in pts:
        px, py = to_xy(vx, vy)
        draw.ellipse([px - 4, py - 4, px + 4, py + 4], fill="black" if label in ("data", "prior") else "#1f77b4")
        width = draw.textlength(label, font=font)
        tx = px + 7 if px + 7 + width < w - 4 else px - 7 - width  # labels stay inside the picture
        ty = py - 7
        while any(tx < bx + bw and bx < tx + width and abs(ty - by) < 15 for bx, by, bw in placed):
            ty += 15
        placed.append((tx, ty, width))
        draw.text((tx, ty), label, fill="black", font=font)
    Path(png).parent.mkdir(parents=True, exist_ok=True)
    image.save(png)
    return Path(png)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--x", default="Col_obj")
    ap.add_argument("--y", default="R_reach")
    ap.add_argument("--png", required=True)
    ap.add_argument("files", nargs="+", help="LABEL=REPORT.json, or LABEL=A.json,B.json,... pooled")
    args = ap.parse_args(argv)
    pts = points(args.files, args.x, args.y)
    for label, vx, vy in pts:
        print(f"{label}: {args.x} {vx:.1f}%, {args.y} {vy:.1f}%")
    print(plot(pts, args.x, args.y, args.png))


if __name__ == "__main__":
    main()
