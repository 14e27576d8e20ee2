"""Several processes, one model: what DistributedDataParallel training needs beyond DDP itself.

``torchrun --nproc_per_node=W`` starts W processes (the *ranks*, one per device) and tells each
who it is through environment variables (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``,
``MASTER_ADDR``, ``MASTER_PORT``). Each rank holds a copy of the model and an equal share of
every batch; DistributedDataParallel (DDP) averages the gradients over the ranks in
``backward``, so the copies stay equal.

Averaging gradients is right for a loss that is an average of per-sample terms (VICReg's
invariance). VICReg's variance and covariance and SIGReg's characteristic function are
statistics of the whole batch: on one rank's share they would be other, noisier quantities.
Two collectives that autograd can differentiate compute them on the global batch instead:

- :func:`gather_rows`: every rank's embeddings, ``(b, D) -> (W b, D)`` (VICReg);
- :func:`mean_across_ranks`: the mean over ranks of a per-rank mean (SIGReg's ECF, and the
  sums behind a covariance when gathering the rows would move too much).

DDP pairs each forward call with one backward: a loss that calls several methods of a
model (encode, predict, ...) runs inside one forward call of :class:`Forward`.

Why their backward sums over ranks: DDP minimises the mean of the ranks' losses,
``J = (1/W) sum_r L_r``, by averaging each rank's own gradient. Through a collective, every
rank's loss depends on rank s's tensor ``x_s``, so ``dJ/dx_s = (1/W) sum_r dL_r/dx_s``: the
backward all-reduces (sums) the incoming gradients before rank s keeps its part, and DDP's
average supplies the 1/W. Keeping only the local gradient, a common mistake, makes the
gradient of every batch statistic W times too small.

Everything here is a no-op in a single process (torch.distributed not initialised, or a world
of one): the single-device path computes exactly what it computed before.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Mapping
from typing import Any

import torch
import torch.distributed as dist
from torch import nn

TORCHRUN_ENV = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


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


def launched_by_torchrun(environ: Mapping[str, str] | None = None) -> bool:
    """Whether torchrun (or another launcher of its kind) started this process."""
    environ = os.environ if environ is None else environ
    return "RANK" in environ or "WORLD_SIZE" in environ


def init_from_env(environ: Mapping[str, str] | None = None,
                  command: str = "ebjepa_tutorial.commands.train_image") -> torch.device:
    """Join the process group that torchrun described in the environment; return our device.

    Backend ``nccl`` with one GPU per process (``cuda:LOCAL_RANK``) when CUDA is available,
    else ``gloo`` on the CPU. Raises RuntimeError, naming what is missing and how to start
    ``command`` (a module) under torchrun, when the process was not started by torchrun,
    rather than waiting for peers that will never come.
    ``environ`` (default ``os.environ``) is what is checked; torch itself reads ``os.environ``.
    """
    environ = os.environ if environ is None else environ
    missing = [name for name in TORCHRUN_ENV if not environ.get(name)]
    if missing:
        raise RuntimeError(
            f"distributed training needs torchrun's environment, and {', '.join(missing)} "
            f"{'is' if len(missing) == 1 else 'are'} not set. Start it with "
            f"`torchrun --nproc_per_node=N -m {command} ...`, or "
            "drop --ddp to train in one process.")
    if running():
        raise RuntimeError("torch.distributed is already initialised in this process")
    if not torch.cuda.is_available():
        dist.init_process_group("gloo")
        return torch.device("cpu")
    local = int(environ["LOCAL_RANK"])
    if local >= torch.cuda.device_count():
        raise RuntimeError(f"LOCAL_RANK {local} but only {torch.cuda.device_count()} GPU(s): "
                           "start at most one process per GPU (--nproc_per_node)")
    device = torch.device("cuda", local)
    torch.cuda.set_device(device)
    dist.init_process_group("nccl")
    return device


def shutdown() -> None:
    """Leave the process group, if this process is in one."""
    if running():
        dist.destroy_process_group()


def per_rank_batch(global_batch: int, world: int | None = None) -> int:
    """The rule: global batch = per-rank batch x world size. Raises ValueError if W does not
    divide the global batch, or if a rank would get fewer than 2 samples."""
    world = world_size() if world is None else world
    if global_batch % world:
        raise ValueError(
            f"the global batch of {global_batch} cannot be split evenly over {world} "
            f"processes: choose a batch_size that is a multiple of the world size {world}")
    if global_batch // world < 2:
        raise ValueError(f"a global batch of {global_batch} over {world} processes leaves "
                         f"each fewer than 2 samples (batch norm needs 2)")
    return global_batch // world


def local_rows(x: torch.Tensor) -> torch.Tensor:
    """This rank's share of a global batch: rows ``r b .. (r+1) b`` of ``(W b, ...)``;
    ``x`` itself in a single process."""
    if world_size() == 1:
        return x
    share = per_rank_batch(x.shape[0])
    return x[rank() * share:(rank() + 1) * share]


def _collective_device() -> torch.device:
    # nccl moves CUDA tensors only; gloo, CPU tensors
    if dist.get_backend() == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def fingerprint(value: Any) -> str:
    """A short hash of plain data (a config as a dict), the same in every process."""
    text = json.dumps(value, sort_keys=True, default=repr)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def check_same_on_all_ranks(value: Any, what: str = "config") -> None:
    """Raise RuntimeError on every rank if the ranks hold different ``value`` (plain data).

    Call once at start-up: ranks that disagree on the config would train different models and
    usually wait forever in a collective of another shape.
    """
    if world_size() == 1:
        return
    prints: list[Any] = [None] * world_size()
    dist.all_gather_object(prints, fingerprint(value))
    if len(set(prints)) > 1:
        listed = ", ".join(f"rank {r}: {p}" for r, p in enumerate(prints))
        raise RuntimeError(f"the processes were started with different {what}s ({listed}); "
                           "start every rank with the same arguments")


def from_main(compute: Callable[[], Any]) -> Any:
    """``compute()`` on rank 0 only (file reads and moves), its result sent to every rank.

    The result must pickle; keep tensors on the CPU. An exception on rank 0 is raised on every
    rank, so none waits for a result that will not come.
    """
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
    """The mean over ranks of each number in ``values`` (for logging): as is in one process."""
    if world_size() == 1:
        return list(values)
    packed = torch.tensor(values, dtype=torch.float64, device=_collective_device())
    dist.all_reduce(packed)
    return (packed / world_size()).tolist()


def average_gradients(parameters) -> None:
    """Average each parameter's ``.grad`` over the ranks, in place (what DDP does in backward),
    for updates made outside DDP's wrapper. A no-op in one process."""
    if world_size() == 1:
        return
    for p in parameters:
        if p.grad is not None:
            dist.all_reduce(p.grad)
            p.grad /= world_size()


class _GatherRows(torch.autograd.Function):
    """All-gather along dim 0: ``(b, D) -> (W b, D)``, rank r's rows at ``r b .. (r+1) b``."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        x = x.contiguous()
        parts = [torch.empty_like(x) for _ in range(world_size())]
        dist.all_gather(parts, x)
        return torch.cat(parts)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        # grad (W b, D) is dL_r/d(all rows) on rank r; our rows feed every rank's loss, so sum
        # over ranks (see the module docstring), then keep our rows: (b, D)
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
        # d/dx_s of sum_r L_r(mean) = sum_r grad_r / W; DDP's average adds the other 1/W
        total = grad.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(total)
        return total / world_size()


def gather_rows(*tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Every rank's rows of each ``(b, D_i)`` tensor, in rank order: ``(W b, D_i)`` each.

    Gradients flow back to each rank's own rows (summed over ranks' losses). One collective
    for all tensors; every rank must hold the same ``b``. Returns ``tensors`` unchanged in a
    single process.
    """
    if world_size() == 1:
        return tensors
    widths = [t.shape[1] for t in tensors]
    return _GatherRows.apply(torch.cat(tensors, dim=1)).split(widths, dim=1)


def mean_across_ranks(*tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The mean over ranks of each tensor (same shapes on every rank), differentiably.

    The mean of per-rank means is the global mean when every rank holds as many samples.
    One collective for all tensors; returns ``tensors`` unchanged in a single process.
    """
    if world_size() == 1:
        return tensors
    flat = _MeanAcrossRanks.apply(torch.cat([t.reshape(-1) for t in tensors]))
    pieces = flat.split([t.numel() for t in tensors])
    return tuple(p.view_as(t) for p, t in zip(pieces, tensors))


class Forward(nn.Module):
    """``fn(module, *args, **kwargs)`` as the one forward call of a wrapper around ``module``.

    DistributedDataParallel pairs each forward call with one backward, so a loss that calls
    several methods of a model (encode, predict, project, ...) must run inside a single
    forward: wrap ``Forward(model, loss_fn)`` in DDP. The parameters are ``model``'s; save
    ``model`` itself (the wrapper's state dict keys start with ``module.``).
    """

    def __init__(self, module: nn.Module, fn: Callable[..., Any]):
        super().__init__()
        self.module, self.fn = module, fn

    def forward(self, *args, **kwargs):
        return self.fn(self.module, *args, **kwargs)


def data_parallel(module: nn.Module, device: torch.device | str,
                  sync_batchnorm: bool = False) -> nn.Module:
    """``module`` wrapped in DDP inside a process group; ``module`` itself outside one.

    ``sync_batchnorm`` (off by default) turns its batch norms into SyncBatchNorm, which
    normalises over the global batch instead of each rank's share; torch runs it on GPUs only.
    The conversion replaces the layers inside ``module`` and keeps their parameters, so build
    the optimiser afterwards or before: it holds the same tensors. State dict keys do not change.
    """
    device = torch.device(device)
    if not running():
        if sync_batchnorm:
            raise ValueError("sync_batchnorm needs a process group (start with torchrun)")
        return module
    if sync_batchnorm:
        if device.type != "cuda":
            raise ValueError("SyncBatchNorm runs on CUDA devices only in torch; on the CPU "
                             "(gloo) each rank normalises over its own share of the batch")
        module = nn.SyncBatchNorm.convert_sync_batchnorm(module)
    ids = [device.index] if device.type == "cuda" else None
    return nn.parallel.DistributedDataParallel(module, device_ids=ids)
