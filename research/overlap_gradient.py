"""Where the x0-hat overlap loss of pretraining pushes the chairs: on a batch of the prior's training rooms, noised
to t in each band below the loss's ``overlap_max_timestep``, the prior's x0_hat (data boxes at its predicted floor
positions, as :func:`agents.x0_losses.overlap_excess`) and the loss's pull on every chair (minus its gradient with
respect to the chair's centre, metres), split by the class of the partner that is charged (chair, dining table or
other) and projected on the chair's outward direction from its table (the dining table nearest it in the data).
A positive outward pull draws chairs away from their tables; the tangential part slides them along the table.

    .venv/bin/python research/overlap_gradient.py --config experiments/pretrain_livingroom_slots_cpu_overlap.yaml \
        --prior out/pretrain/livingroom_slots_cpu/prior.pt [--spare-contact] [--batch 256]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.denoiser import ScenePrior  # noqa: E402
from agents.pretrain import draw_batch, load_config  # noqa: E402
from agents.pretrain_data import training_data  # noqa: E402
from agents.x0_losses import excess_overlap_volume  # noqa: E402
from iarcs_env.geometry import bounds_overlaps  # noqa: E402
from iarcs_env.relation_fidelity import CHAIRS  # noqa: E402
from iarcs_env.rooms import get_room  # noqa: E402
from iarcs_env.scene import decode_geometry  # noqa: E402

PARTNERS = ("chair", "dining table", "other")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--prior", required=True)
    ap.add_argument("--spare-contact", action="store_true", help="leave out the pairs that overlap in the data")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--bands", type=int, nargs="+", default=[0, 25, 50, 100, 150])
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = load_config(args.config)
    cfg.cond_drop_prob = 0.0  # every room with its floor
    spec = get_room(cfg.room)
    prior = ScenePrior.load(args.prior)
    stats = prior.stats
    data, _, _ = training_data(cfg, log=lambda *a: None, progress=False, with_stats=False)
    chair_ids = torch.tensor([spec.classes.index(c) for c in CHAIRS if c in spec.classes])
    table_id = spec.classes.index("dining_table")
    gen = torch.Generator().manual_seed(0)
    print(f"{args.prior}: {args.batch} rooms a band, spare_contact={args.spare_contact}; per scene: overlap "
          "excess (m^3) by partner; per chair with a table: mean pull (m^2: m^3 of charge per m), outward | along")
    for lo, hi in zip(args.bands[:-1], args.bands[1:]):
        batch = draw_batch(data, cfg, spec, stats, gen, args.batch)
        t = torch.randint(lo, hi, (args.batch,), generator=gen)
        x_t = prior.schedule.q_sample(batch.x0, t, batch.noise)
        with torch.no_grad():
            out = prior.denoiser(x_t, t, batch.floor)
        x0_hat = prior.schedule.predict_x0(x_t, t, out)
        labels = batch.x0[..., 8:].argmax(-1)
        objects = labels != spec.empty_index
        chair = torch.isin(labels, chair_ids) & objects
        table = (labels == table_id) & objects
        trans, half, yaws = decode_geometry(torch.cat([x0_hat[..., :3], batch.x0[..., 3:]], -1), stats, batch.extents)
        d_trans, _, _ = decode_geometry(batch.x0, stats, batch.extents)
        trans = trans.detach().requires_grad_(True)
        data_ov = bounds_overlaps(d_trans, half, yaws)
        pairs = objects[:, :, None] & objects[:, None] & ~torch.eye(objects.shape[1], dtype=torch.bool)
        if args.spare_contact:
            pairs = pairs & (data_ov[..., 0] * data_ov[..., 2] == 0)
        excess_volume = excess_overlap_volume(bounds_overlaps(trans, half, yaws), data_ov)  # the loss's, per pair
        # outward unit vector of each chair from the nearest dining table (data positions), 0 without a table
        dist = (d_trans[:, :, None, 0:3:2] - d_trans[:, None, :, 0:3:2]).norm(dim=-1)
        dist = torch.where(table[:, None, :], dist, torch.full_like(dist, float("inf")))
        nearest = dist.argmin(-1)
        has_table = chair & table.any(1, keepdim=True)
        centre = torch.gather(d_trans[..., 0:3:2], 1, nearest[..., None].expand(-1, -1, 2))
        outward = d_trans[..., 0:3:2] - centre
        outward = outward / outward.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        along = torch.stack([-outward[..., 1], outward[..., 0]], -1)
        rows = []
        for name, partner in zip(PARTNERS, (chair, table, objects & ~chair & ~table)):
            sel = pairs & (chair[:, :, None] & partner[:, None] | partner[:, :, None] & chair[:, None])
            if name == "other":  # the rest of the charge: pairs without a chair too
                sel = pairs & ~(chair[:, :, None] | chair[:, None]) | sel
            excess = (excess_volume * sel).sum() / 2  # each pair i<j once
            (grad,) = torch.autograd.grad(excess, trans, retain_graph=True)
            pull = -grad[..., 0:3:2][has_table]  # m^3 per m
            out_pull = (pull * outward[has_table]).sum(-1).mean()
            along_pull = (pull * along[has_table]).sum(-1).abs().mean()
            rows.append(f"{name} {excess.item() / args.batch:.4f} m^3, pull {out_pull:+.3f} | {along_pull:.3f}")
        print(f"t {lo:3d}-{hi - 1:3d}: " + "; ".join(rows))


if __name__ == "__main__":
    main()
