"""Checker of chapter 03: the K-step rollout loss, its value and its gradients."""

from __future__ import annotations

import inspect
from collections.abc import Callable

import torch

from ...losses.rollout import Predictor, rollout_loss
from .common import Case, compare, exercise


def _toy_predictor(kind: str, weight: torch.Tensor | None = None) -> Predictor:
    """Toy predictors ``(N, context, C, H, W) -> (N, C, H, W)`` with rollouts easy to follow."""
    if kind == "shift":  # the last latent plus 0.5: order k of a rollout is z_last + 0.5 k
        return lambda window: window[:, -1] + 0.5
    if kind == "velocity":  # constant velocity: exact on latents that move in straight lines
        return lambda window: 2 * window[:, -1] - window[:, -2]
    if kind == "mean":  # uses the whole window, however long
        return lambda window: window.mean(dim=1) + 0.1
    # a fixed nonlinear map of the whole window, weight (context, C, C)
    return lambda window: torch.tanh(torch.einsum("nkchw,kcd->ndhw", window, weight))


def _rollout_case(what: str, kind: str, z: torch.Tensor, context: int, steps: int,
                  tbptt: int | None = None, seed: int = 0):
    """Arguments of one check: what to compare (loss ``value``, ``grad_z`` or ``grad_weight``)."""
    weight = torch.randn(context, z.shape[2], z.shape[2],
                         generator=torch.Generator().manual_seed(seed)) / z.shape[2] ** 0.5
    return (what, kind, weight, z, context, steps, tbptt)


def _run_rollout_loss(loss_fn: Callable) -> Callable:
    """Wrap a rollout loss so that one call returns the loss value or one of its gradients."""
    def run(what, kind, weight, z, context, steps, tbptt):
        weight, z = weight.clone().requires_grad_(), z.clone().requires_grad_()
        kwargs = {"context": context, "steps": steps}
        if tbptt is not None:
            kwargs["tbptt"] = tbptt
        loss = loss_fn(_toy_predictor(kind, weight), z, **kwargs)
        if what == "value" or not isinstance(loss, torch.Tensor):
            return loss
        wrt = z if what == "grad_z" else weight
        grad = torch.autograd.grad(loss, wrt, allow_unused=True)[0]
        grad = torch.zeros_like(wrt) if grad is None else grad
        return grad[:, -1] if what == "grad_z" else grad  # z's last frame is only a target
    run.__name__ = getattr(loss_fn, "__name__", "your function")
    return run


@exercise(rollout_loss)
def check_rollout_loss(fn: Callable) -> bool:
    """Notebook 03: ``rollout_loss(predictor, z, context=2, steps=4[, tbptt=None])`` -> 0-d tensor.

    Compares the loss and its gradients with :func:`rollout_loss` on random
    latents and toy predictors. The ``tbptt`` cases run only if ``fn`` takes a
    ``tbptt`` argument.
    """
    g = torch.Generator().manual_seed(7)
    drift = torch.arange(7.0)[None, :, None, None, None] * torch.randn(1, 1, 2, 3, 3, generator=g)
    cases = [
        ("the predictor 'last latent + 0.5', random latents (2, 8, 3, 4, 4), context 2, K 3",
         _rollout_case("value", "shift", torch.randn(2, 8, 3, 4, 4, generator=g), 2, 3)),
        ("a constant-velocity predictor on latents moving in straight lines (the loss is 0)",
         _rollout_case("value", "velocity", drift, 2, 4)),
        ("a constant-velocity predictor, random latents (2, 9, 2, 4, 4), K 4",
         _rollout_case("value", "velocity", torch.randn(2, 9, 2, 4, 4, generator=g), 2, 4)),
        ("a nonlinear predictor, random latents (3, 10, 4, 4, 4), K 4",
         _rollout_case("value", "mixer", torch.randn(3, 10, 4, 4, 4, generator=g), 2, 4)),
        ("a predictor averaging its window, context 3 (not 2), K 2",
         _rollout_case("value", "mean", torch.randn(2, 7, 2, 3, 3, generator=g), 3, 2)),
        ("one step (K 1), latents (4, 5, 2, 2, 2)",
         _rollout_case("value", "mixer", torch.randn(4, 5, 2, 2, 2, generator=g), 2, 1)),
        ("the shortest clip, T = context + K = 5 frames",
         _rollout_case("value", "velocity", torch.randn(2, 5, 2, 3, 3, generator=g), 2, 3)),
        ("the gradient with respect to the last latent z[:, -1], a target (keep its gradient)",
         _rollout_case("grad_z", "mixer", torch.randn(2, 8, 3, 3, 3, generator=g), 2, 4)),
        ("the gradient with respect to the predictor's weights, K 4",
         _rollout_case("grad_weight", "mixer", torch.randn(2, 8, 3, 3, 3, generator=g), 2, 4)),
    ]
    if "tbptt" in inspect.signature(fn).parameters:
        z = torch.randn(2, 9, 3, 3, 3, generator=g)
        cases += [(f"the gradient with respect to the predictor's weights, K 5, tbptt={m}",
                   _rollout_case("grad_weight", "mixer", z, 2, 5, tbptt=m)) for m in (1, 2)]
        cases.append(("the loss value with tbptt=2 (truncation must not change it)",
                      _rollout_case("value", "mixer", z, 2, 5, tbptt=2)))
    else:
        print("(your function has no tbptt argument: the truncation cases are skipped)")
    return compare(_run_rollout_loss(fn), _run_rollout_loss(rollout_loss),
                   [Case(description, args) for description, args in cases])
