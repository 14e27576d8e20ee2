"""Device choice, precision, seeding and config checks, used by every notebook."""

from __future__ import annotations

import contextlib
import math
import random

import numpy as np
import torch


def get_device(prefer: str | None = None) -> torch.device:
    """Return ``prefer`` if given, else the best available: cuda, then mps, then cpu."""
    if prefer is not None:
        return torch.device(prefer)
    if torch.cuda.is_available():
        return torch.device("cuda")
    return torch.device("mps" if torch.backends.mps.is_available() else "cpu")


def network_dtype(device: torch.device | str, cpu: bool = False) -> torch.dtype:
    """bfloat16 on a CUDA GPU that has it and, with ``cpu=True``, on a CPU that computes it
    natively (AVX-512 BF16 or AMX); else float32: what :func:`mixed_precision` computes in."""
    kind = torch.device(device).type
    if kind == "cuda":
        native = torch.cuda.get_device_capability(device)[0] >= 8  # Ampere on; older: emulated
        return torch.bfloat16 if native else torch.float32
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")  # else bf16 is emulated
    cpu_bf16 = any(getattr(torch.cpu, name, lambda: False)() for name in checks)
    return torch.bfloat16 if kind == "cpu" and cpu and cpu_bf16 else torch.float32


def mixed_precision(device: torch.device | str, cpu: bool = False):
    """bfloat16 autocast where :func:`network_dtype` says so; elsewhere, nothing. Compute
    losses after it, on ``.float()`` outputs: batch statistics lose their digits in bf16."""
    dtype = network_dtype(device, cpu)
    if dtype == torch.float32:
        return contextlib.nullcontext()
    return torch.autocast(torch.device(device).type, dtype=dtype)


def at_least_float32(x: torch.Tensor) -> torch.Tensor:
    """``x`` in float32 if it is in a half precision (bf16 or fp16); float64 stays float64."""
    return x.float() if x.dtype in (torch.float16, torch.bfloat16) else x


def memory_format(device: torch.device | str) -> torch.memory_format:
    """``channels_last`` for convolutions on a CUDA GPU (faster there); the default elsewhere."""
    return torch.channels_last if torch.device(device).type == "cuda" else torch.contiguous_format


def seed_everything(seed: int) -> torch.Generator:
    """Seed Python, NumPy and torch; return a CPU ``torch.Generator`` seeded with ``seed``."""
    generator = as_generator(seed)
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    return generator


def as_generator(seed: int | torch.Generator) -> torch.Generator:
    """``seed`` itself if it is a ``torch.Generator``, else a fresh CPU one seeded with the int."""
    if isinstance(seed, torch.Generator):
        return seed
    if not isinstance(seed, int) or isinstance(seed, bool):
        hint = " (NumPy's): pass int(seed)" if type(seed).__module__ == "numpy" else ""
        raise TypeError(f"seed must be an int (or a torch.Generator), got "
                        f"{type(seed).__name__}{hint}")
    return torch.Generator().manual_seed(seed)


def is_int_at_least(least: int):
    """A predicate for :func:`check_fields`: an ``int`` (not a bool) ``>= least``."""
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= least


def is_positive(v) -> bool:
    """A finite number > 0."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0


def is_non_negative(v) -> bool:
    """A finite number >= 0."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0


def check_fields(config, rules: dict) -> None:
    """Raise ValueError naming the first field of ``config`` that breaks its rule; ``rules``
    maps a field name to ``(predicate, "what it must be"[, "what it means"])``."""
    for name, (ok, rule, *meaning) in rules.items():
        value = getattr(config, name)
        if not ok(value):
            label = f"{name} ({meaning[0]})" if meaning else name
            numpy = "; a NumPy number: pass int(...) or float(...)" if type(value).__module__ \
                == "numpy" else ""  # a config is stored as plain data (its run's identity)
            raise ValueError(f"{type(config).__name__}.{label} must be {rule}, got {value!r}"
                             f"{numpy}")


@contextlib.contextmanager
def evaluating(model: torch.nn.Module):
    """``model`` in eval mode inside the block (batch norm's running statistics), handed back
    in the mode it came in (a model scored in the middle of training trains on)."""
    was_training = model.training
    model.eval()
    try:
        yield model
    finally:
        model.train(was_training)
