"""Chapter 07's shipped fits on a frozen world model: a cost head and a coarse model, by name.

``python -m research.fit_beyond`` made them (checkpoints/README.md); the course loads them.
"""

from __future__ import annotations

from pathlib import Path

from torch import nn

from .checkpoints import SHIPPED_DIR, CheckpointError, load_made_by


def load_fit(kind: str, world: str, module: nn.Module, base: dict,
             folder: str | Path = SHIPPED_DIR) -> nn.Module:
    """``module`` (on the CPU) with the weights of ``<folder>/<kind>_<world>_class.pt``, in eval
    mode. ``kind``: ``"cost_head"`` or ``"coarse"``; ``world``: ``"two_rooms"`` or
    ``"three_rooms"``; ``base``: the identity of the world model it was fitted on, which the
    file stores (``training.world.identity``)."""
    path = Path(folder) / f"{kind}_{world}_class.pt"
    made_by = f"python -m research.fit_beyond --world {world} --fits {kind} --out-dir {folder}"
    state = load_made_by(path, made_by)
    stored = state.get("config") if isinstance(state, dict) else None
    if not isinstance(stored, dict) or stored.get("base") != base:
        raise CheckpointError(f"{path} was not fitted on the world model loaded here (the "
                              f"identity it stores differs). It is made by: {made_by}")
    try:
        module.load_state_dict(state["model"])
    except (KeyError, RuntimeError) as err:
        raise CheckpointError(f"{path} holds no {type(module).__name__} of this shape "
                              f"({str(err).splitlines()[0][:160]}). It is made by: {made_by}"
                              ) from None
    return module.eval()
