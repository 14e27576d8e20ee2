"""What the training commands share to run under torchrun: the ``--ddp`` and ``--sync-bn``
flags, and joining the process group, where a bad set-up is a usage error on every rank
(not a hang): no torchrun environment, a world size that does not divide the global batch,
or ranks started with different arguments.
"""

from __future__ import annotations

import argparse
from typing import Any

import torch

from ebjepa_tutorial import distributed
from ebjepa_tutorial.utils import get_device


def add_flags(parser: argparse.ArgumentParser, sync_bn: bool = True) -> None:
    """Add ``--ddp`` and, for models with batch norm, ``--sync-bn`` to ``parser``."""
    parser.add_argument("--ddp", action="store_true",
                        help="train with DistributedDataParallel and fail if torchrun did not "
                             "start this process (default: on whenever torchrun started it)")
    if sync_bn:
        parser.add_argument("--sync-bn", action="store_true",
                            help="with several processes, batch norm over the global batch "
                                 "(SyncBatchNorm, GPUs only); default off: each process "
                                 "normalises over its own share of the batch")


def join(parser: argparse.ArgumentParser, args: argparse.Namespace, batch_size: int,
         run: Any, command: str) -> torch.device:
    """Join torchrun's process group and check the set-up; return this process's device.

    Without torchrun (and without ``--ddp``), the best device of this machine. Under it,
    checks that the world size divides ``batch_size`` (the global batch) and that every rank
    holds the same ``args`` and ``run`` (plain data: the runs' identities); ``command`` (a
    module) is named in the error when torchrun's environment is missing.
    """
    if not (args.ddp or distributed.launched_by_torchrun()):
        if getattr(args, "sync_bn", False):
            parser.error("--sync-bn needs several processes: start with torchrun")
        return get_device()  # the best device there is: the full scale is sized for a GPU
    try:
        device = distributed.init_from_env(command=command)
        distributed.per_rank_batch(batch_size)
        distributed.check_same_on_all_ranks({"args": vars(args), "run": run}, "arguments")
    except (RuntimeError, ValueError) as error:
        distributed.shutdown()
        parser.error(str(error))
    return device
