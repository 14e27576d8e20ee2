"""Chapter 07's shipped fits on a frozen world model: a cost head and a coarse model, by name.

``python -m research.fit_beyond`` made them (checkpoints/README.md); the course loads them.
"""

from __future__ import annotations

from pathlib import Path

from torch import nn

from .checkpoints import SHIPPED_DIR, CheckpointError, load_checkpoint


def load_fit(kind: str, world: str, module: nn.Module, base: dict,
             folder: str | Path = SHIPPED_DIR) -> nn.Module:
    """``module`` (on the CPU) with the weights of ``<folder>/<kind>_<world>_class.pt``, in eval
    mode. ``kind``: ``"cost_head"`` or ``"coarse"``; ``world``: ``"two_rooms"`` or
    ``"three_rooms"``; ``base``: the identity of the world model it was fitted on, which the
    file stores (``training.world.identity``)."""
    path = Path(folder) / f"{kind}_{world}_class.pt"
    remedy = (f"Make it with `python -m research.fit_beyond --world {world} --fits {kind} "
              f"--out-dir {folder}` (from the repository's root).")
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing. {remedy}")
    try:
        state = load_checkpoint(path)
    except CheckpointError as err:  # damaged, or holding more than weights
        raise type(err)(f"{err}\n{remedy}") from None
    stored = state.get("config") if isinstance(state, dict) else None
    if not isinstance(stored, dict) or stored.get("base") != base:
        raise CheckpointError(f"{path} was not fitted on the world model loaded here (the "
                              f"identity it stores differs). {remedy}")
    try:
        module.load_state_dict(state["model"])
    except (KeyError, RuntimeError) as err:
        reason = str(err).splitlines()[0][:160]
        raise CheckpointError(f"{path} holds no {type(module).__name__} of this shape "
                              f"({reason}). {remedy}") from None
    return module.eval()
