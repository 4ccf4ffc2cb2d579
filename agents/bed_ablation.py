"""Does the prior's denoiser use the bed? (issue 37: a figure every prior shows.) Rooms with one bed and a
nightstand are noised to t and restored in one step (x0_hat) twice, with the same noise: as they are, and with
the bed's slot emptied before noising. For the nightstands (those still decoded as nightstands both times)
:func:`bed_ablation` gives the median error to the truth each way, how far removing the bed moves them, and the
quartiles of how far out from the true bed's side they land. A network that places nightstands by their bed does
worse without it.

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


def bed_ablation(prior: ScenePrior, rooms: list, timesteps, seed: int = 0) -> dict:
    """{t: figures} for the rooms of ``rooms`` with exactly one bed and at least one nightstand (module doc):
    ``rooms`` (with one bed and a nightstand), ``nightstands`` in them, ``kept`` (decoded as nightstands both ways),
    the median errors to the truth with and without the bed and how far removing it moves them
    (``error_with_bed_m``, ``error_without_bed_m``, ``moved_by_removing_bed_m``), and the quartiles of how far out
    from the true bed's side the nightstands are (``out_from_side_truth``, ``_with_bed``, ``_without_bed``; m,
    negative within its width). ``seed`` seeds the noise, the same for both restorations."""
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
    bed_slot = bed.float().argmax(1)
    rows = torch.arange(len(bed_slot))
    bed_xz, bed_half, bed_yaw = (clean.translations[rows, bed_slot][:, [0, 2]], clean.half_sizes[rows, bed_slot],
                                 clean.yaws[rows, bed_slot])
    out = {}
    for t in timesteps:
        noise = torch.randn(x0.shape, generator=torch.Generator().manual_seed(seed))
        tt = torch.full((x0.shape[0],), int(t))
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

        def out_from_side(p):  # metres out from the true bed's side, in its frame (negative: within its width)
            lateral = rel.local_offset(torch.stack([bed_xz[scene], p], 1), torch.stack([bed_yaw[scene]] * 2, 1))[:, 0, 1, 0]
            return (lateral.abs() - bed_half[scene, 0]).numpy()

        quartiles = lambda v: [float(q) for q in np.quantile(v, [0.25, 0.5, 0.75])] if len(v) else [np.nan] * 3
        out[int(t)] = {"rooms": int(keep.sum()), "nightstands": int(nightstand.sum()), "kept": int(sel.sum()),
                       "error_with_bed_m": float((with_bed - truth).norm(dim=-1).median()),
                       "error_without_bed_m": float((without - truth).norm(dim=-1).median()),
                       "moved_by_removing_bed_m": float((with_bed - without).norm(dim=-1).median()),
                       "out_from_side_truth": quartiles(out_from_side(truth)),
                       "out_from_side_with_bed": quartiles(out_from_side(with_bed)),
                       "out_from_side_without_bed": quartiles(out_from_side(without))}
    return out


__all__ = ["bed_ablation"]
