"""Checker of chapter 03: the paper's K-step loss, ``parallel_rollout_loss(predictor, z,
context=2, steps=4, detach_later=False)`` -> a 0-d tensor, on toy predictors."""

from collections.abc import Callable
from functools import partial

import torch

from ...losses.rollout import parallel_rollout_loss, rollout_loss
from .common import Case, Exercise

# toy predictors (N, context, C, H, W) -> (N, C, H, W) with unrolls easy to follow; weight is
# the mixer's (context, C, C)
_PREDICTORS = {
    "shift": lambda window, weight: window[:, -1] + 0.5,
    "velocity": lambda window, weight: 2 * window[:, -1] - window[:, -2],  # exact on lines
    "mean": lambda window, weight: window.mean(dim=1) + 0.1,  # the whole window, however long
    "mixer": lambda window, weight: torch.tanh(torch.einsum("nkchw,kcd->ndhw", window, weight)),
}


def _toy(window: torch.Tensor, kind: str, weight: torch.Tensor) -> torch.Tensor:
    """The toy predictor ``kind`` on ``window``, refusing another rank as the course's does."""
    if window.dim() != 5:  # a toy would broadcast an unflattened batch and hide the slip
        raise ValueError(f"the predictor takes windows (N, context, C, S, S), got "
                         f"{tuple(window.shape)}: put every window of every clip on one axis")
    return _PREDICTORS[kind](window, weight)


def _call(loss_fn: Callable) -> Callable:
    """``loss_fn`` on a case of :func:`_cases`, called positionally as the training step does; a
    ``z`` it changes in place shows as a change of ``z`` (the case's latents but the last)."""
    def run(kind, weight, z, z_last, context, steps, detach_later):
        whole = torch.cat([z, z_last[:, None]], dim=1)
        given = whole.detach().clone()
        loss = loss_fn(partial(_toy, kind=kind, weight=weight), whole, context, steps,
                       detach_later)
        if not torch.equal(whole.detach(), given):  # the step would project what it overwrote
            with torch.no_grad():
                z.add_(1.0)
        return loss
    return run


def _slip(**slip) -> Callable:
    """The notebook's parallel unroll with one mistake, named by a keyword of ``slip``."""
    error = slip.get("error", lambda d: d.pow(2).mean())
    shift, mode = slip.get("early", 0), slip.get("detach", "right")  # how steps 2..K are cut

    def errors(predictor, z, inputs, targets, context, steps, cut):
        out, sequence = [], inputs
        for k in range(steps):
            n = sequence.shape[1] - context
            windows = torch.stack([sequence[:, j:j + n] for j in range(context)], dim=2)
            predictions = predictor(windows.flatten(0, 1)).unflatten(0, windows.shape[:2])
            whole = torch.cat([inputs[:, :context], predictions], dim=1)
            out.append(error(whole - targets) if slip.get("with_context") else
                       error(predictions - targets[:, context - shift:z.shape[1] - shift]))
            if cut and mode == "predictions":
                predictions = predictions.detach()
            sequence = inputs if slip.get("teacher_forcing") else torch.cat(
                [inputs[:, :context], predictions], dim=1)
            if cut and mode == "continued" and k == 0:  # steps 2..K go on from step 1's, detached
                sequence, targets = sequence.detach(), targets.detach()
        return out

    def parallel_rollout_loss(predictor, z, context=2, steps=4, detach_later=False):
        context = slip.get("context", context)
        z = z.transpose(0, 1) if slip.get("batch_axis") else z
        targets = z.detach() if slip.get("detach_targets") else z
        cut = detach_later and steps > 1 and mode != "ignored"
        if not cut or mode in ("predictions", "continued"):
            found = errors(predictor, z, z, targets, context, steps, cut)
        else:  # step 1 on z, steps 2..K again from the detached latents
            found = errors(predictor, z, z, targets, context, 1, False) + errors(
                predictor, z, z.detach(), z.detach() if mode == "right" else targets,
                context, steps, False)[1:]
        return found[-1] if slip.get("last_only") else torch.stack(found).mean()
    return parallel_rollout_loss


def _cases() -> list[Case]:
    """The predictor, its weights, the latents split into all frames but the last and the last
    (only ever a target: its gradient is checked on its own), and the options."""
    g, cases = torch.Generator().manual_seed(7), []
    drift = torch.arange(7.0)[None, :, None, None, None] * torch.randn(1, 1, 2, 3, 3, generator=g)
    table = [  # what, predictor, latents (None: drift), context, K, detach_later, weights' seed
        ("the predictor 'last latent + 0.5'", "shift", (4, 9, 5, 4, 4), 2, 3, False, 0),
        ("a constant-velocity predictor on lines (loss 0)", "velocity", None, 2, 4, False, 0),
        ("a nonlinear predictor", "mixer", (3, 10, 4, 4, 4), 2, 4, False, 0),
        ("a predictor averaging its window", "mean", (2, 7, 2, 3, 3), 3, 2, False, 0),
        ("one step", "mixer", (4, 5, 2, 2, 2), 2, 1, False, 0),
        ("a batch as long as the clips", "mixer", (6, 6, 2, 3, 3), 2, 3, False, 2),
        ("the shortest clip, T = context + K", "velocity", (2, 5, 2, 3, 3), 2, 3, False, 0),
        ("a nonlinear predictor (the course's runs)", "mixer", (2, 8, 3, 3, 3), 2, 4, True, 1),
        ("a predictor averaging its window", "mean", (2, 8, 2, 3, 3), 3, 3, True, 0),
        ("one step (nothing to detach)", "mixer", (2, 6, 2, 3, 3), 2, 1, True, 0)]
    for what, kind, shape, context, steps, detach_later, seed in table:
        z = drift if shape is None else torch.randn(shape, generator=g)
        weight = torch.randn(context, z.shape[2], z.shape[2],
                             generator=torch.Generator().manual_seed(seed)) / z.shape[2] ** 0.5
        cases.append(Case(f"{what}, latents {tuple(z.shape)}, context {context}, K {steps}"
                          + (", detach_later=True" if detach_later else ""),
                          (kind, weight, z[:, :-1], z[:, -1], context, steps, detach_later),
                          sizes={"K": steps}))
    return cases


check_parallel_rollout_loss = Exercise(
    "parallel_rollout_loss", parallel_rollout_loss, dict(  # gradient-only slips first
        detach_ignored=_slip(detach="ignored"), targets_not_detached=_slip(detach="inputs"),
        predictions_detached=(_slip(detach="predictions"), _slip(detach="continued")),
        targets_detached=_slip(detach_targets=True), teacher_forcing=_slip(teacher_forcing=True),
        off_by_one=_slip(early=1), context_averaged=_slip(with_context=True),
        last_step_only=_slip(last_only=True), batch_axis=_slip(batch_axis=True),
        context_ignored=_slip(context=2),
        summed_elements=_slip(error=lambda d: d.pow(2).flatten(2).sum(2).mean()),
        unsquared=_slip(error=lambda d: d.pow(2).mean().sqrt()),
        absolute=_slip(error=lambda d: d.abs().mean()), autoregressive=rollout_loss),
    _cases, adapt=_call, grad=[(1, "the predictor's weights"), (2, "the other latents z[:, :-1]"),
                               (3, "the last latent z[:, -1] (only ever a target)")])
