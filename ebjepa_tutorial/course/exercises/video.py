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


def _rollout_slip(**slip) -> Callable:
    """The notebook's rollout loop with one mistake, named by a keyword of ``slip``."""
    error = slip.get("error", lambda d: d.pow(2).mean())

    def rollout_loss(predictor, z, context=2, steps=4, tbptt=None):
        context = slip.get("context", context)
        tbptt = None if slip.get("ignore_tbptt") else tbptt
        targets = z.detach() if slip.get("detach_targets") else z
        errors = []
        for s in range(1 if slip.get("one_start") else z.shape[1] - context - steps + 1):
            window = z[:, s:s + context]
            for k in range(steps):
                if tbptt is not None and k > 0 and k % tbptt == 0:
                    window = window.detach()
                if slip.get("teacher_forcing"):
                    window = z[:, s + k:s + k + context]
                z_hat = predictor(window)
                errors.append(error(z_hat - targets[:, s + context + k - slip.get("early", 0)]))
                if not slip.get("no_slide"):
                    window = torch.cat([window[:, 1:], z_hat[:, None]], dim=1)
        return torch.stack(errors).sum() if slip.get("sum") else torch.stack(errors).mean()

    return rollout_loss


_ROLLOUT_SLIPS = [(words, _rollout_slip(**slip)) for words, slip in [
    ("no gradient reaches the target latents: did you .detach() them? The course keeps the "
     "targets' gradient, as the paper does.", {"detach_targets": True}),
    ("you ignored tbptt: detach the window when k > 0 and k % tbptt == 0.",
     {"ignore_tbptt": True}),
    ("an off-by-one target: step k (k = 0 .. K-1) from start s predicts z[:, s + context + k], "
     "the frame after the window; you compared it with z[:, s + context + k - 1].",
     {"early": 1}),
    ("teacher forcing: you gave the predictor the true latents at every step; a rollout feeds "
     "it its own predictions: window = torch.cat([window[:, 1:], z_hat[:, None]], dim=1).",
     {"teacher_forcing": True}),
    ("the window never slides: every step predicts from the same true context; append each "
     "prediction and drop the oldest latent.", {"no_slide": True}),
    ("you rolled out from the first start only; roll out from every start s = 0 .. "
     "T - context - K.", {"one_start": True}),
    ("you ignored the context argument (your window always holds 2 latents).", {"context": 2}),
    ("you summed the errors instead of averaging them.", {"sum": True}),
    ("you summed the squared error over each latent's elements; average over them "
     "(.pow(2).mean()).", {"error": lambda d: d.pow(2).flatten(1).sum(1).mean()}),
    ("an unsquared distance: the loss is the mean *squared* error, (z_hat - z).pow(2).mean().",
     {"error": lambda d: d.flatten(1).norm(dim=1).mean()}),
    ("an unsquared distance: the loss is the mean *squared* error, not its square root.",
     {"error": lambda d: d.pow(2).mean().sqrt()}),
    ("you used the absolute error; the loss is the mean squared error.",
     {"error": lambda d: d.abs().mean()}),
]]


@exercise(rollout_loss, _ROLLOUT_SLIPS)
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
                   [Case(description, args) for description, args in cases],
                   diagnoses=[(w, _run_rollout_loss(v)) for w, v in _ROLLOUT_SLIPS])
