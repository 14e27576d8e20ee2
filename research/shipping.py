"""What the commands that write the shipped checkpoints share."""

from __future__ import annotations

import torch


def float16_state(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    """``module``'s state on the CPU with floating tensors in float16: half the file.

    ``load_state_dict`` casts them back to the model's float32, and the rounding (about 3
    significant digits) barely moves a probe. Integer buffers (batch norm's counters) are kept.
    """
    return {name: (value.half() if value.is_floating_point() else value).cpu()
            for name, value in module.state_dict().items()}
