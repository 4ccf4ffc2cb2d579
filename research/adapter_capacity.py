"""Is the task adapter too small to hold the searched rooms? ``search_sft.py``'s fine-tune (its config's adapter,
a copy of stage 1's LoRA, x0_hat regressed onto ``--cache`` files of searched rooms) with more room to learn:
``--rank R --targets REGEX`` grows the copy to rank R on the layers REGEX matches (stage 1's weights in its first
ranks, zero elsewhere, so it starts as stage 1), ``--full`` trains the denoiser's own weights beside it. Then the
success on ``--held-out`` floors of seed 4242 and ``restore_probe.py``'s restoration of the first ``--probe`` rooms,
which the fine-tune saw. Writes a run folder that ``iarcs sample --checkpoint`` reads (not with ``--full``: its
denoiser is not saved).

    .venv/bin/python research/adapter_capacity.py experiments/ablations/task_wheelchair_gradient.yaml ROOMS.pt \\
        [MORE.pt ...] --task wheelchair (--rank 16 --targets REGEX | --full) [--lr 1e-3] [--out RUN]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from peft import LoraConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from descent_offline import build_with_targets  # noqa: E402
from restore_probe import figures, ground_move, restore  # noqa: E402
from search_sft import (HELD_OUT_SEED, cached_rooms, cat, fine_tune, held_out_report, procedural_floors,  # noqa: E402
                        save_run, success)
from agents.train import load_train_config  # noqa: E402


def grow(policy, name: str, source: str, rank: int, targets: str) -> None:
    """Replace adapter ``name`` by a rank-``rank`` LoRA on ``targets`` holding ``source``'s weights in its first
    ranks (zero B elsewhere), so that the policy samples as before."""
    model = policy.model
    model.delete_adapter(name)
    model.add_adapter(name, LoraConfig(r=rank, lora_alpha=rank, target_modules=targets, lora_dropout=0.0))
    state, grown = model.state_dict(), {}
    for key, value in state.items():
        old = state.get(key.replace(f".{name}.", f".{source}."))
        if f".{name}." in key and old is not None and ("lora_A" in key or "lora_B" in key):
            new = value.clone()
            if "lora_A" in key:
                new[:old.shape[0]] = old
            else:
                new[:, :old.shape[1]] = old
            grown[key] = new
    model.load_state_dict(grown, strict=False)
    policy.set_adapter(name)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="a task training config (as search_sft.py's)")
    parser.add_argument("rooms", nargs="+", help="search_sft.py --cache files of searched rooms (together)")
    parser.add_argument("--task", required=True)
    parser.add_argument("--rank", type=int, help="grow the adapter to this LoRA rank (with --targets)")
    parser.add_argument("--targets", help="a regular expression of the layers the grown LoRA adapts")
    parser.add_argument("--full", action="store_true", help="train the denoiser's own weights too")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--held-out", type=int, default=64, help="held-out floors (seed 4242) to measure success on")
    parser.add_argument("--probe", type=int, default=256, help="rooms to restore after the fine-tune")
    parser.add_argument("--out", help="write a run folder with the adapter")
    args = parser.parse_args(argv)
    if bool(args.rank) == args.full or bool(args.rank) != bool(args.targets):
        parser.error("give either --rank with --targets, or --full")
    torch.set_num_threads(1)
    cfg = load_train_config(args.config)
    _, policy = build_with_targets(cfg)
    if args.rank:
        grow(policy, cfg.adapter, "init", args.rank, args.targets)
    for key, p in policy.model.named_parameters():
        p.requires_grad_(f".{cfg.adapter}." in key or (args.full and "lora_" not in key))
    params = [p for p in policy.model.parameters() if p.requires_grad]
    print(f"{sum(p.numel() for p in params):,} parameters trained")
    prior = policy.prior
    caches = [cached_rooms(path, prior.spec, cfg) for path in args.rooms]
    rooms = caches[0] if len(caches) == 1 else cat(caches)
    other = procedural_floors(cfg.room, args.held_out, HELD_OUT_SEED)
    print(f"step 0: {args.task} on {len(other)} other floors {success(policy, other, args.task):.1%}", flush=True)
    fine_tune(policy, rooms, params, args.steps, args.lr, torch.Generator().manual_seed(cfg.seed), 250,
              held_out_report(policy, cfg, args.task, other))
    if args.out and not args.full:
        save_run(policy, cfg, args.out)
    probe = rooms[:args.probe]
    print(f"{len(probe)} of its rooms as handed: {figures(probe, args.task)}")
    for start in (0, 50, 100, 200):
        out = restore(policy, probe, start, cfg.num_steps, cfg.eta)
        print(f"restored from t = {start}: {figures(out, args.task)}, ground objects moved "
              f"{ground_move(probe, out):.3f} m (median)", flush=True)


if __name__ == "__main__":
    main()
