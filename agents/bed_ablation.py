"""Does the prior's denoiser use the bed? (issue 37: a figure every prior shows.) Rooms with one bed and a
nightstand are noised to t and restored in one step (x0_hat) twice, with the same noise: as they are, and with
the bed's slot emptied before noising. For the nightstands (those still decoded as nightstands both times)
:func:`bed_ablation` gives the median error to the truth each way, how far removing the bed moves them, and the
quartiles of how far out from the true bed's side they land, pooled over a few noise draws (one draw's ratio of
the two errors moves by a tenth from draw to draw). A network that places nightstands by their bed does worse
without it. Two more figures say how far that can go: the bed's own error (with the bed, a nightstand cannot be
placed better than the bed it stands by is restored) and the nightstand's error in the restored bed's frame (how
well it follows the bed the network sees).

``experiments/gpu_run_tools.py bed-ablation`` records it for a trained prior; ``research/bed_ablation.py`` prints
it as a table for procedural bedrooms.
"""

from __future__ import annotations

import numpy as np
import torch

from agents.denoiser import ScenePrior
from agents.pretrain_data import SceneTensors, encode_batch
from iarcs_env import relations as rel
from iarcs_env.scene import SceneBatch


def bed_ablation(prior: ScenePrior, rooms: list, timesteps, seed: int = 0, noise_draws: int = 4) -> dict:
    """{t: figures} for the rooms of ``rooms`` with exactly one bed and at least one nightstand (module doc):
    ``rooms`` (with one bed and a nightstand), ``nightstands`` in them, ``kept`` (decoded as nightstands both ways,
    summed over the draws), the median errors to the truth with and without the bed and how far removing it moves
    them (``error_with_bed_m``, ``error_without_bed_m``, ``moved_by_removing_bed_m``) and the first over the second
    (``ratio``: the issue asks at most 0.5 at t = 200), the bed's own error
    (``bed_error_m``) and the nightstands' error in the restored bed's frame (``error_from_restored_bed_m``), and
    the quartiles of how far out from the true bed's side the nightstands are (``out_from_side_truth``,
    ``_with_bed``, ``_without_bed``; m, negative within its width). Medians and quartiles pool ``noise_draws``
    draws of the noise, seeded ``seed``, ``seed + 1``, ...; each the same for both restorations."""
    spec = prior.spec
    data = SceneTensors.from_layouts(rooms, prior.num_slots)
    x0, floor = encode_batch(spec, prior.stats, *data.batch(torch.arange(len(data))))
    clean = SceneBatch.decode(x0, prior.stats, [lay.centred().floor for lay in rooms])
    bed = rel.class_mask(clean.labels, spec.classes, ["bed"])
    nightstand = rel.class_mask(clean.labels, spec.classes, ["nightstand"])
    keep = (bed.sum(1) == 1) & nightstand.any(1)
    x0, floor, bed, nightstand, clean = x0[keep], floor[keep], bed[keep], nightstand[keep], clean[keep]
    empty = torch.full((spec.num_classes,), -1.0)
    empty[spec.empty_index] = 1.0
    no_bed = x0.clone()
    no_bed[bed] = torch.cat([torch.zeros(x0.shape[-1] - spec.num_classes), empty])  # an empty slot, as encoded
    fn, schedule = prior.model_fn(floor.to(prior.device)), prior.schedule
    rows = torch.arange(len(x0))
    bed_slot = bed.float().argmax(1)

    def bed_frame_offset(scenes: SceneBatch, which, points):  # (lateral, forward) of points in their bed's frame
        bed_xz, bed_yaw = scenes.translations[rows, bed_slot][which][:, [0, 2]], scenes.yaws[rows, bed_slot][which]
        return rel.local_offset(torch.stack([bed_xz, points], 1), torch.stack([bed_yaw] * 2, 1))[:, 0, 1]

    def out_from_side(which, points):  # metres out from the true bed's side (negative: within its width)
        return (bed_frame_offset(clean, which, points)[:, 0].abs() - clean.half_sizes[rows, bed_slot][which, 0]).numpy()

    out = {}
    for t in timesteps:
        tt = torch.full((x0.shape[0],), int(t))
        pooled = {k: [] for k in ("with", "without", "moved", "bed", "from_bed",
                                  "side_truth", "side_with", "side_without")}
        for draw in range(noise_draws):
            noise = torch.randn(x0.shape, generator=torch.Generator().manual_seed(seed + draw))
            restored = []
            for x in (x0, no_bed):
                x_t = schedule.q_sample(x, tt, noise)
                with torch.no_grad():
                    x0_hat = schedule.predict_x0(x_t, tt, fn(x_t.to(prior.device), tt.to(prior.device)).cpu())
                restored.append(SceneBatch.decode(x0_hat, prior.stats, clean.floors))
            sel = nightstand & (restored[0].labels == clean.labels) & (restored[1].labels == clean.labels)
            scene = torch.nonzero(sel)[:, 0]
            truth = clean.translations[..., 0:3:2][sel]
            with_bed, without = (r.translations[..., 0:3:2][sel] for r in restored)
            bed_kept = restored[0].labels[rows, bed_slot] == clean.labels[rows, bed_slot]
            pooled["with"].append((with_bed - truth).norm(dim=-1))
            pooled["without"].append((without - truth).norm(dim=-1))
            pooled["moved"].append((with_bed - without).norm(dim=-1))
            bed_moved = (restored[0].translations - clean.translations)[rows, bed_slot][:, [0, 2]]
            pooled["bed"].append(bed_moved[bed_kept].norm(dim=-1))
            pooled["from_bed"].append((bed_frame_offset(restored[0], scene, with_bed)
                                       - bed_frame_offset(clean, scene, truth)).norm(dim=-1))
            pooled["side_truth"].append(out_from_side(scene, truth))
            pooled["side_with"].append(out_from_side(scene, with_bed))
            pooled["side_without"].append(out_from_side(scene, without))

        def median(k):
            v = torch.cat(pooled[k])
            return float(v.median()) if len(v) else float("nan")

        def quartiles(k):
            v = np.concatenate(pooled[k])
            return [float(q) for q in np.quantile(v, [0.25, 0.5, 0.75])] if len(v) else [float("nan")] * 3

        error_with, error_without = median("with"), median("without")
        out[int(t)] = {"rooms": int(keep.sum()), "nightstands": int(nightstand.sum()),
                       "kept": int(sum(len(v) for v in pooled["with"])), "noise_draws": noise_draws,
                       "error_with_bed_m": error_with, "error_without_bed_m": error_without,
                       "ratio": error_with / error_without if error_without else float("nan"),
                       "moved_by_removing_bed_m": median("moved"), "bed_error_m": median("bed"),
                       "error_from_restored_bed_m": median("from_bed"),
                       "out_from_side_truth": quartiles("side_truth"), "out_from_side_with_bed": quartiles("side_with"),
                       "out_from_side_without_bed": quartiles("side_without")}
    return out


__all__ = ["bed_ablation"]
