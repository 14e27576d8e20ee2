"""Data parallelism under ``torchrun --nproc_per_node=W``: each of W ranks holds the model and
1/W of every batch; batch statistics see the global batch through collectives that autograd goes
through, and gradients are averaged over ranks. Everything here is a no-op in one process."""

from __future__ import annotations

import warnings

import torch
import torch.distributed as dist
import torch.distributed.nn.functional as collective  # collectives that autograd goes through
from torch import nn

from .losses import vicreg

# torch 2.14 deprecates these for a private module; they work, and the gloo tests check them
warnings.filterwarnings("ignore", r"torch\.distributed\.nn\.functional\.", FutureWarning)


def running() -> bool:
    """Whether this process belongs to an initialised process group (of any size)."""
    return dist.is_available() and dist.is_initialized()


def world_size() -> int:
    """How many ranks share each batch: 1 outside a process group."""
    return dist.get_world_size() if running() else 1


def is_main() -> bool:
    """Whether this is rank 0, the one that prints, shows progress and writes files."""
    return not running() or dist.get_rank() == 0


def per_rank_batch(global_batch: int) -> int:
    """The rule: global batch = per-rank batch x world size, at least 2 samples per rank."""
    world = world_size()
    if global_batch % world or global_batch // world < 2:
        raise ValueError(f"the global batch of {global_batch} cannot be split evenly over {world} "
                         f"processes with at least 2 samples each: make batch_size a multiple of "
                         f"the world size {world}, at least {2 * world}")
    return global_batch // world


def local_rows(x: torch.Tensor) -> torch.Tensor:
    """This rank's share of a global batch: rows ``r b .. (r+1) b`` of ``(W b, ...)``."""
    if world_size() == 1:
        return x
    share, rank = per_rank_batch(x.shape[0]), dist.get_rank()
    return x[rank * share:(rank + 1) * share]


def rand_rows(rows: int, *size: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """``torch.rand(rows, *size)`` for this rank: its rows of one process's draw of
    ``(W rows, *size)``, the generator seeded alike on every rank."""
    return local_rows(torch.rand(rows * world_size(), *size, generator=generator))


def from_main(compute):
    """``compute()`` on rank 0 only (file reads), its result (picklable) sent to every rank.
    An exception on rank 0 is raised on every rank, so none waits for a result."""
    if world_size() == 1:
        return compute()
    box = [None]
    if is_main():
        try:
            box = [("ok", compute())]
        except Exception as error:
            box = [("error", f"rank 0 failed: {type(error).__name__}: {error}")]
            dist.broadcast_object_list(box, src=0)
            raise
    dist.broadcast_object_list(box, src=0)
    status, result = box[0]
    if status == "error":
        raise RuntimeError(result)
    return result


def mean_of_floats(values: list[float]) -> list[float]:
    """The mean over ranks of each number in ``values`` (for logging)."""
    if world_size() == 1:
        return list(values)
    device = "cuda" if dist.get_backend() == "nccl" else "cpu"  # nccl moves CUDA tensors only
    packed = torch.tensor(values, dtype=torch.float64, device=device)
    dist.all_reduce(packed)
    return (packed / world_size()).tolist()


def average_gradients(parameters) -> None:
    """Average each parameter's ``.grad`` over the ranks, in place (what DDP does in backward)."""
    if world_size() == 1:
        return
    for p in parameters:
        if p.grad is not None:
            dist.all_reduce(p.grad)
            p.grad /= world_size()


def gather_rows(x: torch.Tensor) -> torch.Tensor:
    """Every rank's ``x (b, ...)`` in rank order, ``(W b, ...)``; gradients reach each rank."""
    return x if world_size() == 1 else torch.cat(collective.all_gather(x))


def variance_and_covariance(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """VICReg's ``v(Z)`` and ``c(Z)`` (0-d tensors) of the global batch ``(W b, D)`` from each
    rank's ``(b, D)``, by all-reducing the mean and the scatter."""
    if world_size() == 1:
        return vicreg.variance_term(z), vicreg.covariance_term(z)
    world = world_size()
    mean = collective.all_reduce(z.mean(dim=0)) / world  # (D,): the global mean
    centred = z - mean
    scatter = collective.all_reduce(centred.T @ centred) / world  # (D, D): 1/W of the sum
    cov = scatter * (world / (world * z.shape[0] - 1))  # sample covariance
    variance = torch.relu(1.0 - torch.sqrt(torch.diagonal(cov) + 1e-4)).mean()  # gamma, eps
    return variance, vicreg.off_diagonal_term(cov)


def data_parallel(module: nn.Module, device: torch.device | str) -> nn.Module:
    """``module`` wrapped in DDP inside a process group, ``module`` itself outside one."""
    device = torch.device(device)
    ids = [device.index] if device.type == "cuda" else None
    return nn.parallel.DistributedDataParallel(module, device_ids=ids) if running() else module
