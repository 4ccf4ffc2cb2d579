"""Data-parallel training over processes started by ``torchrun`` (one per GPU, or several on a CPU).

``torchrun --nproc_per_node=P -m experiments.cli train --config ...`` runs P copies of the RL trainer. Each
process (rank) collects its own ``num_envs`` scenes per rollout batch with its own random streams, so one
update sees P x ``num_envs`` scenes; advantages are standardised over the scenes of every rank (the same
floor plan drawn on two ranks is one group); the LoRA gradients are averaged across ranks after every
backward pass, so every rank holds the same adapter; only rank 0 writes (checkpoints, TensorBoard,
evaluations, the exported adapter). ``iarcs pretrain`` under ``torchrun`` splits each batch over the ranks
and averages the denoiser's gradients the same way. GPUs talk through NCCL, CPU processes through gloo.

Without ``torchrun`` (no ``WORLD_SIZE`` in the environment) every function here is the single-process
identity, so the trainer's code reads the same either way.
"""

from __future__ import annotations

import os

import torch
import torch.distributed as dist

from .config import resolve_device


def world_size() -> int:
    """P: the number of training processes (1 without ``torchrun``)."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def rank() -> int:
    """This process's rank in [0, P) (0 without ``torchrun``)."""
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def is_main() -> bool:
    """Whether this process writes files and logs (rank 0)."""
    return rank() == 0


def rank_seed(seed: int) -> int:
    """The seed of this rank's random streams: ``seed`` on rank 0 (a one-process run is unchanged), spread
    apart on the others."""
    return seed + 7919 * rank()


def launched_by_torchrun() -> bool:
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def setup(device: str = "auto") -> torch.device:
    """This process's device; under ``torchrun`` also joins the process group (once). On GPUs each rank takes
    ``cuda:LOCAL_RANK`` unless ``device`` names an index."""
    where = resolve_device(device)
    if not launched_by_torchrun():
        return where
    if where.type == "cuda" and where.index is None:
        local = int(os.environ.get("LOCAL_RANK", "0"))
        if local >= torch.cuda.device_count():
            raise ValueError(f"torchrun started local rank {local} but torch sees {torch.cuda.device_count()} GPU(s); "
                             "start at most one process per GPU (--nproc_per_node), or use device cpu")
        where = torch.device("cuda", local)
    if where.type == "cuda":
        torch.cuda.set_device(where)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if where.type == "cuda" else "gloo")
    return where


def _wire_device() -> torch.device:
    """Where tensors must be for the process group's collectives (NCCL: the rank's GPU)."""
    return torch.device("cuda", torch.cuda.current_device()) if dist.get_backend() == "nccl" else torch.device("cpu")


def all_gather(tensor: torch.Tensor) -> torch.Tensor:
    """Every rank's ``tensor`` (the same shape on each) concatenated along dim 0 in rank order, on the
    tensor's device."""
    if world_size() == 1:
        return tensor
    wire = tensor.detach().to(_wire_device()).contiguous()
    parts = [torch.empty_like(wire) for _ in range(world_size())]
    dist.all_gather(parts, wire)
    return torch.cat(parts).to(tensor.device)


def local_part(gathered: torch.Tensor) -> torch.Tensor:
    """This rank's rows of a tensor made by :func:`all_gather`."""
    n = gathered.shape[0] // world_size()
    return gathered[rank() * n:(rank() + 1) * n]


def average_gradients(params) -> None:
    """Replace each parameter's gradient with its mean over the ranks (one all-reduce for all of them)."""
    if world_size() == 1:
        return
    params = [p for p in params if p.grad is not None]
    flat = torch.cat([p.grad.reshape(-1) for p in params]).to(_wire_device())
    dist.all_reduce(flat)
    flat /= world_size()
    offset = 0
    for p in params:
        n = p.grad.numel()
        p.grad.copy_(flat[offset:offset + n].view_as(p.grad))
        offset += n


@torch.no_grad()
def broadcast_parameters(params) -> None:
    """Copy rank 0's values of ``params`` to every rank (the same adapter to start from)."""
    if world_size() == 1:
        return
    for p in params:
        wire = p.data.to(_wire_device())
        dist.broadcast(wire, src=0)
        p.data.copy_(wire)


def broadcast_object(obj):
    """Rank 0's ``obj`` (picklable) on every rank."""
    if world_size() == 1:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=0, device=_wire_device())
    return box[0]


def cleanup() -> None:
    """Leave the process group (end of a ``torchrun`` run)."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


__all__ = ["all_gather", "average_gradients", "broadcast_object", "broadcast_parameters", "cleanup", "is_main",
           "launched_by_torchrun", "local_part", "rank", "rank_seed", "setup", "world_size"]
