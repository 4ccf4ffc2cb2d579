"""``iarcs info``: what this installation has and where it will run: versions, the device ``auto`` picks
(and every CUDA GPU torch sees), the shipped priors and adapters, the adapter library, and which reward
agent ``iarcs generate`` will use. The first thing to run when something does not work as expected."""

from __future__ import annotations

import json
import os
import platform
import sys
from importlib import metadata

PACKAGES = ["torch", "numpy", "gymnasium", "torchrl", "tensordict", "peft", "shapely", "tensorboard", "litellm"]
KEY_VARIABLES = ["GEMINI_API_KEY", "OPENAI_API_KEY", "ANTHROPIC_API_KEY", "OPENAI_API_BASE"]


def register(sub) -> None:
    p = sub.add_parser("info", help="versions, the device training would use, shipped models and LLM keys")
    p.add_argument("--json", action="store_true", help="print the facts as JSON")
    p.set_defaults(func=cmd_info)


def installation_facts() -> dict:
    """Everything ``iarcs info`` reports, as plain data."""
    import torch
    import torch.distributed as dist

    from agents.config import resolve_device
    from agents.denoiser import CHECKPOINT_DIR
    from agents.train import stage1_adapter_path
    from experiments.commands.generate import library_root
    from iarcs_env.rooms import ROOMS

    def version(name: str) -> str:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            return "not installed"

    gpus = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())] if torch.cuda.is_available() else []
    priors = {}
    for room in ROOMS:
        path = CHECKPOINT_DIR / f"{room}_small.pt"
        stage1 = stage1_adapter_path(room)
        priors[room] = {"prior": str(path) if path.exists() else None,
                        "stage1_adapter": str(stage1) if (stage1 / "adapter_config.json").exists() else None}
    library = library_root()
    adapters = sorted(str(p.parent.relative_to(library)) for p in library.glob("*/*/adapter")) if library.exists() else []
    return {
        "iarcs": version("iarcs"), "python": sys.version.split()[0], "platform": platform.platform(),
        "packages": {name: torch.__version__ if name == "torch" else version(name) for name in PACKAGES},  # with
        # its build tag (+cpu, +cu130): the installed torch, also where it is not pip's (a GPU machine's image)
        "device": {"auto": str(resolve_device("auto")), "cuda_build": torch.version.cuda, "gpus": gpus,
                   "cpu_threads": torch.get_num_threads(),
                   "distributed_backends": [b for b in ("gloo", "nccl") if dist.is_available()
                                            and getattr(dist, f"is_{b}_available")()]},
        "shipped": priors,
        "adapter_library": {"path": str(library), "adapters": adapters},
        "llm_keys_set": [k for k in KEY_VARIABLES if os.environ.get(k)],
    }


def cmd_info(args) -> int:
    facts = installation_facts()
    if args.json:
        print(json.dumps(facts, indent=1))
        return 0
    dev = facts["device"]
    where = (f"{len(dev['gpus'])} CUDA GPU(s): " + ", ".join(f"cuda:{i} {n}" for i, n in enumerate(dev["gpus"]))
             if dev["gpus"] else "no CUDA GPU" + (" (torch is a CPU build)" if dev["cuda_build"] is None else
                                                  " (a CUDA build of torch, but no GPU or driver is visible)"))
    lines = [f"iarcs {facts['iarcs']}, Python {facts['python']}, {facts['platform']}",
             "packages: " + ", ".join(f"{k} {v}" for k, v in facts["packages"].items()),
             f"device: {where}; `device: auto` trains on {dev['auto']} ({dev['cpu_threads']} CPU threads); "
             f"torchrun backends: {', '.join(dev['distributed_backends']) or 'none'}"]
    for room, shipped in facts["shipped"].items():
        lines.append(f"{room}: prior {shipped['prior'] or 'not shipped'}; stage-1 adapter "
                     f"{shipped['stage1_adapter'] or 'not shipped'}")
    lib = facts["adapter_library"]
    lines.append(f"adapter library ({lib['path']}): " + (", ".join(lib["adapters"]) or "empty"))
    keys = facts["llm_keys_set"]
    lines.append("reward agent: " + (f"LLM keys set: {', '.join(keys)} (pass --model to use one)" if keys else
                                     "no LLM key set; the offline planner writes the reward programs"))
    print("\n".join(lines))
    return 0
