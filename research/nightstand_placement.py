"""Where the nightstands stand against their room's one bed, in scene files side by side: why removing collisions
costs the two_nightstands relation.

    .venv/bin/python research/nightstand_placement.py data=FLOORS.json prior=PRIOR.json stage1=STAGE1.json

For every nightstand of a room with exactly one bed, in the bed's frame (``iarcs_env.relations.local_offset``):
where the two_nightstands checker puts it (``ok``: along the head half, centre 0-0.5 m out from the side; ``inside``:
centre within the bed's width; ``far``: more than 0.5 m out; ``ahead`` / ``behind``: outside the head half), the
share whose box overlaps the bed's (the Col_obj test, > 1e-6 m^3), and the lateral gap between their boxes
(bed side to nightstand side, m; negative: they overlap) at the 5th, 25th, 50th, 75th and 95th percentiles.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def placements(path: str) -> dict:
    import numpy as np
    import torch

    from iarcs_env import geometry as geo
    from iarcs_env import relations as rel
    from iarcs_env.datasets import load_layouts
    from iarcs_env.scene import SceneBatch
    from iarcs_env.tasks import EPS, _geometry, _mask

    batch = SceneBatch.from_layouts(load_layouts(path, "bedroom"), "bedroom")
    t, h, y = _geometry(batch)
    offset = rel.local_offset(t[..., 0:3:2], y)  # [b, i, j]: j in i's frame
    overlap = geo.box_overlap_volumes(batch.translations, batch.half_sizes, batch.yaws, batch.ground_mask)
    beds, nightstands = _mask(batch, "bed"), _mask(batch, "nightstand")
    where = dict(ok=0, inside=0, far=0, ahead=0, behind=0)
    gaps, overlapping = [], 0
    for s in torch.nonzero(beds.sum(1) == 1).flatten().tolist():
        i = int(torch.nonzero(beds[s])[0])
        half_w, half_d = float(h[s, i, 0]), float(h[s, i, 2])
        for j in torch.nonzero(nightstands[s]).flatten().tolist():
            lateral, ahead = abs(float(offset[s, i, j, 0])), float(offset[s, i, j, 1])
            place = ("ahead" if ahead > EPS else "behind" if ahead < -half_d - EPS else "inside" if lateral <= half_w
                     else "far" if lateral > half_w + 0.5 + EPS else "ok")
            where[place] += 1
            overlapping += bool(overlap[s, i, j] > geo.COLLISION_VOLUME)
            turned = abs(math.remainder(float(y[s, j] - y[s, i]), math.pi)) > math.pi / 4  # its depth faces the bed
            gaps.append(lateral - half_w - float(h[s, j, 2] if turned else h[s, j, 0]))
    n = max(len(gaps), 1)
    return {"nightstands": len(gaps), **{k: v / n for k, v in where.items()}, "overlap_bed": overlapping / n,
            "gap_percentiles": np.percentile(gaps, [5, 25, 50, 75, 95]).tolist() if gaps else []}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="+", help="NAME=FILE (or FILE): neutral-JSON bedroom scene files")
    args = parser.parse_args()
    print("| file | nightstands | ok | inside | far | ahead | behind | overlap the bed | lateral gap (m): p5 p25 p50 p75 p95 |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for arg in args.files:
        name, _, path = arg.rpartition("=")
        r = placements(path)
        shares = " | ".join(f"{100 * r[k]:.1f}%" for k in ("ok", "inside", "far", "ahead", "behind", "overlap_bed"))
        gaps = " ".join(f"{g:+.3f}" for g in r["gap_percentiles"])
        print(f"| {name or Path(path).stem} | {r['nightstands']} | {shares} | {gaps} |")


if __name__ == "__main__":
    main()
