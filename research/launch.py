"""What the training commands share to run under torchrun: the ``--ddp`` flag, and joining the
process group, where a bad set-up (no torchrun environment, a world size that does not divide
the global batch, ranks started with different arguments) is a usage error on every rank, not
a hang.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
from collections.abc import Mapping
from typing import Any

import torch
import torch.distributed as dist

from ebjepa_tutorial import distributed
from ebjepa_tutorial.distributed import running, world_size
from ebjepa_tutorial.utils import get_device

TORCHRUN_ENV = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


def launched_by_torchrun() -> bool:
    """Whether torchrun (or another launcher of its kind) started this process."""
    return "RANK" in os.environ or "WORLD_SIZE" in os.environ


def init_from_env(environ: Mapping[str, str] | None = None,
                  command: str = "research.train_image") -> torch.device:
    """Join the process group torchrun described in the environment; return our device:
    ``nccl`` on ``cuda:LOCAL_RANK`` when CUDA is available, else ``gloo`` on the CPU. Raises
    RuntimeError naming what is missing and how to start ``command`` (a module) under torchrun.
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


def check_same_on_all_ranks(value: Any, what: str = "config") -> None:
    """Raise RuntimeError on every rank if the ranks hold different ``value`` (plain data):
    ranks that disagree would train different models, or wait forever in a collective."""
    if world_size() == 1:
        return
    digest = hashlib.sha1(json.dumps(value, sort_keys=True, default=repr).encode()).hexdigest()
    prints: list[Any] = [None] * world_size()
    dist.all_gather_object(prints, digest[:12])
    if len(set(prints)) > 1:
        listed = ", ".join(f"rank {r}: {p}" for r, p in enumerate(prints))
        raise RuntimeError(f"the processes were started with different {what}s ({listed}); "
                           "start every rank with the same arguments")


def add_flags(parser: argparse.ArgumentParser) -> None:
    """Add ``--ddp`` to ``parser``."""
    parser.add_argument("--ddp", action="store_true",
                        help="train with DistributedDataParallel and fail if torchrun did not "
                             "start this process (default: on whenever torchrun started it); "
                             "batch norm normalises over each process's share of the batch")


def join(parser: argparse.ArgumentParser, args: argparse.Namespace, batch_size: int,
         run: Any, command: str) -> torch.device:
    """This process's device: without torchrun (and ``--ddp``) the best one of this machine;
    under it, after joining the group and checking that the world size divides ``batch_size``
    (the global batch) and that every rank holds the same ``args`` and ``run`` (plain data).
    """
    if not (args.ddp or launched_by_torchrun()):
        return get_device()  # the best device there is: the full scale is sized for a GPU
    try:
        device = init_from_env(command=command)
        distributed.per_rank_batch(batch_size)
        check_same_on_all_ranks({"args": vars(args), "run": run}, "arguments")
    except (RuntimeError, ValueError) as error:
        shutdown()
        parser.error(str(error))
    return device
