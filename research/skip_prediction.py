"""Does a prior read its input at low noise? On a batch of its training rooms noised to each timestep t, the median
distance (m) between the objects' centres in the prior's x0_hat and in the rooms, beside the same distance for
x_t itself (the noise alone). A denoiser that carries its input through has x0_hat nearer than x_t at every t; an
x0-prediction prior that re-places every object from context has x0_hat far off even at t = 0, and its last
denoising step (which outputs x0_hat) lands objects in each other.

    .venv/bin/python research/skip_prediction.py error --config experiments/pretrain_livingroom_slots_cpu.yaml \
        --prior out/pretrain/livingroom_slots_cpu/prior.pt [--t 0 5 20 100 400]
    .venv/bin/python research/skip_prediction.py convert PRIOR.pt OUT.pt

``convert`` turns an x0-prediction prior into a v-prediction one with the same output at high noise: with the
network's head negated (F = -v), x0_hat = sqrt(abar) x_t + sqrt(1 - abar) F, EDM's skip connection for data of
unit scale; at high noise it is the old x0_hat, at low noise the input. The mid-noise steps then need training
(converted and not trained, the living-room prior's relations fall from 79.6% to 9.8% of rooms).
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
from iarcs_env.rooms import get_room  # noqa: E402
from iarcs_env.scene import decode_geometry  # noqa: E402


#: feature groups of the x0 loss (:data:`iarcs_env.scene.GEOMETRY_DIM` = 8 geometry features, then the classes)
GROUPS = {"positions": [0, 2], "elevation": [1], "sizes": [3, 4, 5], "angle": [6, 7]}


def centre_errors(prior: ScenePrior, x0: torch.Tensor, floor: torch.Tensor, extents: torch.Tensor,
                  noise: torch.Tensor, t: int) -> tuple[float, float, float, dict, dict]:
    """Median distance (m) of the objects' floor positions in x0_hat and in x_t from those in x0 at timestep t,
    the plain x0 loss (mean squared error over all features and slots), each feature group's share of it, and per
    class (of the data's objects) its objects' count and x0_hat's median distance."""
    ts = torch.full((len(x0),), t)
    x_t = prior.schedule.q_sample(x0, ts, noise)
    with torch.no_grad():
        x0_hat = prior.schedule.predict_x0(x_t, ts, prior.denoiser(x_t, ts, floor))
    objects = x0[..., 8:].argmax(-1) != prior.spec.empty_index
    truth = decode_geometry(x0, prior.stats, extents)[0][..., 0:3:2]

    def distances(x):  # the data's sizes: only the positions differ
        moved = decode_geometry(torch.cat([x[..., :3], x0[..., 3:]], -1), prior.stats, extents)[0][..., 0:3:2]
        return (moved - truth).norm(dim=-1)
    squared = (x0_hat - x0) ** 2
    groups = dict(GROUPS, classes=list(range(8, x0.shape[-1])))
    shares = {name: float(squared[..., cols].sum() / squared.sum()) for name, cols in groups.items()}
    labels, hat = x0[..., 8:].argmax(-1), distances(x0_hat)
    by_class = {prior.spec.classes[c]: (int((labels == c).sum()), float(hat[labels == c].median()))
                for c in labels[objects].unique().tolist()}
    return float(hat[objects].median()), float(distances(x_t)[objects].median()), float(squared.mean()), shares, \
        by_class


def convert(src: str, dst: str) -> None:
    state = torch.load(src, map_location="cpu", weights_only=True)
    kind = state.get("schedule_config", {}).get("prediction_type", "epsilon")
    if kind != "sample":
        raise SystemExit(f"{src} predicts {kind!r}; only an x0-prediction ('sample') prior converts to v prediction")
    for name in ("out.weight", "out.bias"):
        state["state_dict"][name] = -state["state_dict"][name]
    state["schedule_config"]["prediction_type"] = "v_prediction"
    torch.save(state, dst)
    print(f"{dst}: v prediction, from {src}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    err = sub.add_parser("error", help="x0_hat's and x_t's distance from the rooms' objects by t")
    err.add_argument("--config", required=True, help="the prior's pretraining config (its training rooms)")
    err.add_argument("--prior", required=True)
    err.add_argument("--t", type=int, nargs="+", default=[0, 20, 100, 400, 700])
    err.add_argument("--batch", type=int, default=128)
    err.add_argument("--by-class", action="store_true", help="also x0_hat's median distance per class")
    conv = sub.add_parser("convert", help="an x0-prediction prior as a v-prediction one")
    conv.add_argument("src")
    conv.add_argument("dst")
    args = ap.parse_args(argv)
    if args.command == "convert":
        return convert(args.src, args.dst)
    torch.set_num_threads(1)
    cfg = load_config(args.config)
    cfg.cond_drop_prob = 0.0  # every room with its floor
    prior = ScenePrior.load(args.prior)
    data, _, _ = training_data(cfg, log=lambda *a: None, progress=False, with_stats=False)
    batch = draw_batch(data, cfg, get_room(cfg.room), prior.stats, torch.Generator().manual_seed(0), args.batch)
    print(f"{args.prior} ({prior.schedule.config.prediction_type} prediction), {args.batch} training rooms: median "
          "distance (m) of the objects' centres from the rooms', the x0 loss and its shares")
    for t in args.t:
        hat, noisy, loss, shares, by_class = centre_errors(prior, batch.x0, batch.floor, batch.extents, batch.noise, t)
        print(f"t {t:4d}: x0_hat {hat:.3f}, x_t {noisy:.3f}; x0 loss {loss:.4f} ("
              + ", ".join(f"{name} {share:.0%}" for name, share in shares.items()) + ")")
        if args.by_class:
            for name, (count, median) in sorted(by_class.items(), key=lambda kv: -kv[1][0]):
                print(f"    {name:24s} {count:4d} objects  x0_hat {median:.3f}")


if __name__ == "__main__":
    main()
