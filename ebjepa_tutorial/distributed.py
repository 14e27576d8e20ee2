"""Several processes, one model: what data-parallel training needs beyond averaging gradients.

``torchrun --nproc_per_node=W`` starts W processes (the *ranks*), each with a copy of the model
and an equal share of every batch; the gradients are averaged over the ranks (DDP, or
:func:`average_gradients`). The losses see one batch in one process: right for a mean of
per-sample terms, but VICReg's variance and covariance and SIGReg are statistics of the whole
batch, so the training code wraps the losses with :func:`gather_rows`,
:func:`variance_and_covariance` and :func:`rand_rows`.

Training minimises ``J = (1/W) sum_r L_r``. Through a collective every ``L_r`` depends on rank
s's tensor ``x_s``, so ``dJ/dx_s = (1/W) sum_r dL_r/dx_s``: the backward sums the incoming
gradients over the ranks, and the average over ranks supplies the 1/W (keeping only the local
gradient makes every batch statistic's gradient W times too small).

Everything here is a no-op in a single process.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
import torch.distributed as dist
from torch import nn

from .losses import vicreg


def running() -> bool:
    """Whether this process belongs to an initialised process group (of any size)."""
    return dist.is_available() and dist.is_initialized()


def world_size() -> int:
    """How many ranks share each batch: 1 outside a process group."""
    return dist.get_world_size() if running() else 1


def rank() -> int:
    """This process's rank, 0 .. world_size() - 1: 0 outside a process group."""
    return dist.get_rank() if running() else 0


def is_main() -> bool:
    """Whether this is rank 0, the one that prints, shows progress and writes files."""
    return rank() == 0


def per_rank_batch(global_batch: int) -> int:
    """The rule: global batch = per-rank batch x world size. Raises ValueError if W does not
    divide the global batch, or if a rank would get fewer than 2 samples."""
    world = world_size()
    if global_batch % world:
        raise ValueError(
            f"the global batch of {global_batch} cannot be split evenly over {world} "
            f"processes: choose a batch_size that is a multiple of the world size {world}")
    if global_batch // world < 2:
        raise ValueError(f"a global batch of {global_batch} over {world} processes leaves "
                         f"each fewer than 2 samples (batch norm needs 2)")
    return global_batch // world


def local_rows(x: torch.Tensor) -> torch.Tensor:
    """This rank's share of a global batch: rows ``r b .. (r+1) b`` of ``(W b, ...)``."""
    if world_size() == 1:
        return x
    share = per_rank_batch(x.shape[0])
    return x[rank() * share:(rank() + 1) * share]


def rand_rows(rows: int, *size: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """``torch.rand(rows, *size)`` for this rank's rows: the draw of ``(W rows, *size)`` (the
    generator seeded alike on every rank), cut to our rows, as one process would draw them."""
    return local_rows(torch.rand(rows * world_size(), *size, generator=generator))


def from_main(compute: Callable[[], Any]) -> Any:
    """``compute()`` on rank 0 only (file reads), its result (picklable) sent to every rank.
    An exception on rank 0 is raised on every rank, so none waits for a result."""
    if world_size() == 1:
        return compute()
    box: list[Any] = [None]
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
    device = torch.device("cuda", torch.cuda.current_device()) \
        if dist.get_backend() == "nccl" else torch.device("cpu")  # nccl moves CUDA tensors only
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


class _GatherRows(torch.autograd.Function):
    """All-gather along dim 0: ``(b, ...) -> (W b, ...)``, rank r's rows at ``r b .. (r+1) b``."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        parts = [torch.empty_like(x) for _ in range(world_size())]
        dist.all_gather(parts, x.contiguous())
        return torch.cat(parts)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        # our rows feed every rank's loss: sum the (W b, ...) gradients over ranks, keep ours
        total = grad.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(total)
        share = total.shape[0] // world_size()
        return total[rank() * share:(rank() + 1) * share]


class _MeanAcrossRanks(torch.autograd.Function):
    """``(1/W) sum_r x_r``, the same on every rank; backward: the mean of the incoming grads."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        total = x.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(total)
        return total / world_size()

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        return _MeanAcrossRanks.forward(ctx, grad)  # sum_r grad_r / W; the average adds a 1/W


def gather_rows(x: torch.Tensor) -> torch.Tensor:
    """Every rank's rows of ``x`` ``(b, ...)`` in rank order, ``(W b, ...)``, each rank holding
    the same ``b``; gradients flow back to each rank's own rows. ``x`` itself in one process."""
    return x if world_size() == 1 else _GatherRows.apply(x)


def variance_and_covariance(z: torch.Tensor, gamma: float = 1.0, eps: float = 1e-4):
    """:func:`ebjepa_tutorial.losses.variance_and_covariance` of the global batch ``(W b, D)``,
    each rank holding ``b`` rows ``(b, D)``, from per-rank sums (two all-reduces of ``D`` and
    ``D x D`` numbers, however many rows). Returns two 0-d tensors."""
    if world_size() == 1:
        return vicreg.variance_and_covariance(z, gamma, eps)
    mean = _MeanAcrossRanks.apply(z.mean(dim=0))  # (D,): the global mean
    centred = z - mean
    scatter = _MeanAcrossRanks.apply(centred.T @ centred)  # (D, D): 1/W of the global sum
    cov = scatter * (world_size() / (world_size() * z.shape[0] - 1))  # sample covariance
    variance = torch.relu(gamma - torch.sqrt(torch.diagonal(cov) + eps)).mean()
    return variance, vicreg.off_diagonal_term(cov)


def with_sync_batchnorm(module: nn.Module, device: torch.device | str) -> nn.Module:
    """``module`` with its batch norms turned into SyncBatchNorm (normalising over the global
    batch; parameters and state dict keys kept). Needs a process group and a CUDA device."""
    if not running():
        raise ValueError("sync_batchnorm needs a process group (start with torchrun)")
    if torch.device(device).type != "cuda":
        raise ValueError("SyncBatchNorm runs on CUDA devices only in torch; on the CPU "
                         "(gloo) each rank normalises over its own share of the batch")
    return nn.SyncBatchNorm.convert_sync_batchnorm(module)


def data_parallel(module: nn.Module, device: torch.device | str,
                  sync_batchnorm: bool = False) -> nn.Module:
    """``module`` wrapped in DDP inside a process group, ``module`` itself outside one; with
    ``sync_batchnorm``, its batch norms first become SyncBatchNorm."""
    device = torch.device(device)
    if sync_batchnorm:
        module = with_sync_batchnorm(module, device)
    if not running():
        return module
    ids = [device.index] if device.type == "cuda" else None
    return nn.parallel.DistributedDataParallel(module, device_ids=ids)
