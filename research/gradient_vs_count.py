"""What a physics-gradient run (``agents/physics_gradient.py``) changed: on the same floors and noise, the prior
(adapter off) and the run's adapter sampled alike, and for each the penalty the run follows, on x0_hat of the last
four steps and on the final scene, against Col_obj and R_reach of the final scenes. A run whose penalty falls while
Col_obj does not lowers the overlaps' size, not the number of objects that collide.

    .venv/bin/python research/gradient_vs_count.py out/train/RUN [--floors 64]
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.ddpo import DDPOConfig  # noqa: E402
from agents.denoiser import centre_floor  # noqa: E402
from agents.physics_gradient import config_penalty  # noqa: E402
from agents.train import load_trained_policy  # noqa: E402
from iarcs_env.env import default_floors  # noqa: E402
from iarcs_env.metrics import evaluate_layouts  # noqa: E402
from iarcs_env.scene import SceneBatch  # noqa: E402


def compare(run: str, num_floors: int, seed: int = 4242) -> list[dict]:
    policy, cfg = load_trained_policy(run)
    prior, ddpo = policy.prior, DDPOConfig.from_dict(cfg.ddpo)
    collision = cfg.reward.get("collision")
    contact = collision.get("contact") if isinstance(collision, dict) else None
    floors = [centre_floor(f) for f in default_floors(cfg.room, count=num_floors, seed=seed)]

    def penalty(x):  # the run's penalty as its training charged it (its floor_contact weight left out)
        return float(config_penalty(x, prior.stats, floors, ddpo, contact).mean())

    rows = []
    for name in ("prior", "adapter"):
        with (policy.base_policy() if name == "prior" else contextlib.nullcontext()), torch.no_grad():
            x0, trajectory = prior.sample_features(floors, cfg.num_steps, cfg.eta, torch.Generator().manual_seed(0),
                                                   eps_fn=policy.eps, return_trajectory=True)
            cond = prior.floor_condition(floors)
            steps = {}
            for k in range(-4, 0):
                t = int(trajectory["timesteps"][k])
                x0_hat = policy.predict_x0(trajectory["states"][k - 1], torch.full((len(floors),), t), cond)
                steps[t] = penalty(x0_hat)
        metrics = evaluate_layouts(SceneBatch.decode(x0, prior.stats, floors).to_layouts())
        rows.append({"policy": name, "x0_hat": steps, "final": penalty(x0), "Col_obj": metrics["Col_obj"],
                     "R_reach": metrics["R_reach"]})
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a physics-gradient run folder (out/train/...)")
    ap.add_argument("--floors", type=int, default=64)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = compare(args.run, args.floors)
    print("| policy | penalty on x0_hat, by t | penalty of the final scenes | Col_obj | R_reach |")
    print("|---|---|---:|---:|---:|")
    for r in rows:
        steps = ", ".join(f"{t}: {v:.3f}" for t, v in r["x0_hat"].items())
        print(f"| {r['policy']} | {steps} | {r['final']:.3f} | {r['Col_obj']:.1%} | {r['R_reach']:.1%} |")


if __name__ == "__main__":
    main()
