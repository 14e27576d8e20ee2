"""Checker of chapter 03: the K-step rollout loss, its value and its gradients, and its hints."""

from __future__ import annotations

import inspect
from collections.abc import Callable

import torch

from ...losses.rollout import Predictor, parallel_rollout_loss, rollout, rollout_loss
from .common import Case, compare, exercise


def _toy_predictor(kind: str, weight: torch.Tensor) -> Predictor:
    """Toy predictors ``(N, context, C, H, W) -> (N, C, H, W)`` with rollouts easy to follow."""
    if kind == "shift":  # the last latent plus 0.5: order k of a rollout is z_last + 0.5 k
        return lambda window: window[:, -1] + 0.5
    if kind == "velocity":  # constant velocity: exact on latents that move in straight lines
        return lambda window: 2 * window[:, -1] - window[:, -2]
    if kind == "mean":  # uses the whole window, however long
        return lambda window: window.mean(dim=1) + 0.1
    # a fixed nonlinear map of the whole window, weight (context, C, C)
    return lambda window: torch.tanh(torch.einsum("nkchw,kcd->ndhw", window, weight))


def _rollout_case(description: str, kind: str, z: torch.Tensor, context: int, steps: int,
                  tbptt: int | None = None, seed: int = 0) -> Case:
    """One test input: the predictor ``kind`` with its weights, the latents ``z`` split into
    all frames but the last and the last, which is only ever a target (so that its gradient
    is checked on its own), and the loss's options."""
    weight = torch.randn(context, z.shape[2], z.shape[2],
                         generator=torch.Generator().manual_seed(seed)) / z.shape[2] ** 0.5
    return Case(description, (kind, weight, z[:, :-1], z[:, -1], context, steps, tbptt))


def _rollout_call(loss_fn: Callable) -> Callable:
    """``loss_fn`` called on one of the cases above: returns the loss."""
    def run(kind, weight, z_first, z_last, context, steps, tbptt):
        kwargs = {"context": context, "steps": steps}
        if tbptt is not None:
            kwargs["tbptt"] = tbptt
        z = torch.cat([z_first, z_last[:, None]], dim=1)
        return loss_fn(_toy_predictor(kind, weight), z, **kwargs)
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


_ROLLOUT_HINTS = (
    "From each start, give the predictor the true context, then let it run on its own "
    "predictions for K steps, as it will have to when it imagines the future. Score every "
    "prediction against the true latent of the frame it stands for; the loss is the average "
    "score over all starts and steps.",
    "For every start s from 0 to T - context - K: the window holds the true latents "
    "s, ..., s + context - 1. Step k = 0, ..., K - 1 predicts the latent of frame "
    "s + context + k from the window; then the window drops its oldest latent and takes the "
    "prediction as its newest (a window stays (B, context, C, S, S), a prediction is "
    "(B, C, S, S)). The error of one step is the mean squared difference over all its "
    "elements; the loss is the mean of the n_starts * K errors. With tbptt = m, cut the "
    "window's gradient before every step k > 0 that is a multiple of m; the targets keep "
    "their gradient.",
    "errors = []\n"
    "for s in range(n_starts):\n"
    "    window = <the true latents s .. s + context - 1, along the time axis>\n"
    "    for k in range(steps):\n"
    "        if <tbptt is set, k > 0 and k is a multiple of tbptt>: window = <window, detached>\n"
    "        z_hat = predictor(window)\n"
    "        errors.append(<the mean squared difference of z_hat and the latent of frame "
    "s + context + k>)\n"
    "        window = <the window without its oldest latent, z_hat appended as the newest>\n"
    "return <the mean of the errors, stacked into one tensor>",
)

_ROLLOUT_SLIPS = [(words, _rollout_slip(**slip)) for words, slip in [
    ("no gradient reaches the target latents: did you .detach() them? The course keeps the "
     "targets' gradient, as the paper does.", {"detach_targets": True}),
    ("you ignored tbptt: the window loses its gradient before every step k > 0 that is a "
     "multiple of tbptt.", {"ignore_tbptt": True}),
    ("an off-by-one target: step k (k = 0 .. K-1) from start s predicts the latent of frame "
     "s + context + k, the frame just after the window; you compared it with the frame "
     "before that.", {"early": 1}),
    ("teacher forcing: you gave the predictor the true latents at every step; a rollout feeds "
     "it its own predictions (the window drops its oldest latent and takes the prediction).",
     {"teacher_forcing": True}),
    ("the window never slides: every step predicts from the same true context; append each "
     "prediction and drop the oldest latent.", {"no_slide": True}),
    ("you rolled out from the first start only; roll out from every start s = 0 .. "
     "T - context - K.", {"one_start": True}),
    ("you ignored the context argument (your window always holds 2 latents).", {"context": 2}),
    ("you summed the errors instead of averaging them.", {"sum": True}),
    ("you summed the squared error over each latent's elements; the error of a step is their "
     "mean.", {"error": lambda d: d.pow(2).flatten(1).sum(1).mean()}),
    ("an unsquared distance: the loss is the mean *squared* error.",
     {"error": lambda d: d.flatten(1).norm(dim=1).mean()}),
    ("an unsquared distance: the loss is the mean *squared* error, not its square root.",
     {"error": lambda d: d.pow(2).mean().sqrt()}),
    ("you used the absolute error; the loss is the mean squared error.",
     {"error": lambda d: d.abs().mean()}),
]]


@exercise(rollout_loss, _ROLLOUT_SLIPS, name="rollout_loss", hints=_ROLLOUT_HINTS,
          answers=(parallel_rollout_loss, rollout))
def check_rollout_loss(fn: Callable) -> bool:
    """Notebook 03: ``rollout_loss(predictor, z, context=2, steps=4[, tbptt=None])`` -> 0-d tensor.

    Compares the loss and its gradients (with respect to the predictor's weights,
    the last latent, a target only, and the other latents) with :func:`rollout_loss`
    on random latents and toy predictors. The ``tbptt`` cases run only if ``fn``
    takes a ``tbptt`` argument.
    """
    g = torch.Generator().manual_seed(7)
    drift = torch.arange(7.0)[None, :, None, None, None] * torch.randn(1, 1, 2, 3, 3, generator=g)
    cases = [
        _rollout_case("the predictor 'last latent + 0.5', random latents (2, 8, 3, 4, 4), "
                      "context 2, K 3", "shift", torch.randn(2, 8, 3, 4, 4, generator=g), 2, 3),
        _rollout_case("a constant-velocity predictor on latents moving in straight lines (the "
                      "loss is 0)", "velocity", drift, 2, 4),
        _rollout_case("a constant-velocity predictor, random latents (2, 9, 2, 4, 4), K 4",
                      "velocity", torch.randn(2, 9, 2, 4, 4, generator=g), 2, 4),
        _rollout_case("a nonlinear predictor, random latents (3, 10, 4, 4, 4), K 4", "mixer",
                      torch.randn(3, 10, 4, 4, 4, generator=g), 2, 4),
        _rollout_case("a predictor averaging its window, context 3 (not 2), K 2", "mean",
                      torch.randn(2, 7, 2, 3, 3, generator=g), 3, 2),
        _rollout_case("one step (K 1), latents (4, 5, 2, 2, 2)", "mixer",
                      torch.randn(4, 5, 2, 2, 2, generator=g), 2, 1),
        _rollout_case("the shortest clip, T = context + K = 5 frames", "velocity",
                      torch.randn(2, 5, 2, 3, 3, generator=g), 2, 3),
        _rollout_case("a nonlinear predictor, random latents (2, 8, 3, 3, 3), K 4", "mixer",
                      torch.randn(2, 8, 3, 3, 3, generator=g), 2, 4, seed=1),
    ]
    if "tbptt" in inspect.signature(fn).parameters:
        z = torch.randn(2, 9, 3, 3, 3, generator=g)
        cases += [_rollout_case(f"a nonlinear predictor, K 5, tbptt={m}", "mixer", z, 2, 5,
                                tbptt=m) for m in (1, 2)]
    else:
        print("(your function has no tbptt argument: the truncation cases are skipped)")
    return compare(_rollout_call(fn), _rollout_call(rollout_loss), cases,
                   diagnoses=[(w, _rollout_call(v)) for w, v in _ROLLOUT_SLIPS],
                   labels=["the predictor", "the predictor's weights", "the latents z[:, :-1]",
                           "the last latent z[:, -1]"],
                   grad=[(1, "the predictor's weights"),
                         (3, "the last latent z[:, -1] (only ever a target)"),
                         (2, "the other latents z[:, :-1]")])
