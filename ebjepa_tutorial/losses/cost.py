"""The cost-to-go head's loss: temporal differences with hindsight goals (notebook 07).

The head ``d(z, g)`` should be the length of the SHORTEST path from ``z`` to
``g``; the offline data only shows random walks. Bellman's equation for the
shortest path, ``d(s, g) = min_a [c(s, a) + d(s', g)]``, has a minimum over
actions that the data cannot take. Expectile regression stands in for it: on
the data's transitions ``(s, a, s')`` the target is

    y = c(s, a) + dbar(s', g)     (0 when s is the goal)

lowered, when the goal lies later on the same trajectory, to what the
trajectory itself spent to get there (a path the data shows exists).

and the head is fitted with an asymmetric square that weights targets below
the estimate by ``1 - tau`` and those above by ``tau``. With ``tau`` small the
fit settles near the low end of the targets: the best of the data's ways on,
not their average. ``dbar`` is a slowly moving copy of the head (the target
network), so that the regression chases a fixed target between updates.
"""

from __future__ import annotations

import torch


def expectile_loss(estimate: torch.Tensor, target: torch.Tensor, tau: float) -> torch.Tensor:
    """``mean(|tau - 1[target < estimate]| * (target - estimate)^2)``, any equal shapes.

    ``tau = 0.5`` is half the mean squared error; ``tau < 0.5`` pulls the estimate
    towards the low targets (a soft minimum), ``tau > 0.5`` towards the high ones.
    """
    if estimate.shape != target.shape:
        raise ValueError(f"estimate {tuple(estimate.shape)} and target {tuple(target.shape)} "
                         "must have the same shape")
    if not 0 < tau < 1:
        raise ValueError(f"tau must be in (0, 1), got {tau}")
    error = target - estimate
    weight = torch.where(error < 0, 1 - tau, tau)
    return (weight * error.square()).mean()


def cost_to_go_targets(step_cost: torch.Tensor, next_to_go: torch.Tensor,
                       offset: torch.Tensor, spent: torch.Tensor) -> torch.Tensor:
    """TD targets ``(B,)`` for transitions ``s -> s'`` and goals ``offset`` frames after ``s``.

    ``step_cost``: ``c(s, a)``, the px the action spends; ``next_to_go``: ``dbar(s', g)``;
    ``offset``: how many frames after ``s`` the goal is in the same trajectory (0: ``s``
    is the goal; -1: a goal from elsewhere, reached only by bootstrapping); ``spent``:
    the px the trajectory spent from ``s`` to its goal (ignored where ``offset < 1``),
    which bounds the shortest path from above: the target is the smaller of the two.
    """
    bootstrap = step_cost + next_to_go
    target = torch.where(offset > 0, torch.minimum(bootstrap, spent), bootstrap)
    return torch.where(offset == 0, 0.0, target)
