"""Checker of chapter 03: the paper's K-step loss, ``parallel_rollout_loss(predictor, z,
context=2, steps=4, detach_later=False)`` -> a 0-d tensor, on toy predictors."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import torch

from ...losses.rollout import parallel_rollout_loss, rollout_loss
from .common import Case, Exercise, slips

# toy predictors (N, context, C, H, W) -> (N, C, H, W) with unrolls easy to follow; weight is
# the mixer's (context, C, C)
_PREDICTORS = {
    "shift": lambda window, weight: window[:, -1] + 0.5,
    "velocity": lambda window, weight: 2 * window[:, -1] - window[:, -2],  # exact on lines
    "mean": lambda window, weight: window.mean(dim=1) + 0.1,  # the whole window, however long
    "mixer": lambda window, weight: torch.tanh(torch.einsum("nkchw,kcd->ndhw", window, weight)),
}


def _case(description: str, kind: str, z: torch.Tensor, context: int, steps: int,
          detach_later: bool, seed: int = 0) -> Case:
    """The predictor ``kind``, its weights, the latents ``z`` split into all frames but the
    last and the last (only ever a target: its gradient is checked on its own), the options."""
    weight = torch.randn(context, z.shape[2], z.shape[2],
                         generator=torch.Generator().manual_seed(seed)) / z.shape[2] ** 0.5
    return Case(description, (kind, weight, z[:, :-1], z[:, -1], context, steps, detach_later),
                sizes={"K": steps})


def _call(loss_fn: Callable) -> Callable:
    """``loss_fn`` on one of the cases above, called positionally as the training step does."""
    def run(kind, weight, z_first, z_last, context, steps, detach_later):
        z = torch.cat([z_first, z_last[:, None]], dim=1)
        return loss_fn(partial(_PREDICTORS[kind], weight=weight), z, context, steps, detach_later)

    return run


def _slip(**slip) -> Callable:
    """The notebook's parallel unroll with one mistake, named by a keyword of ``slip``."""
    error = slip.get("error", lambda d: d.pow(2).mean())
    shift, mode = slip.get("early", 0), slip.get("detach", "right")  # how steps 2..K are cut

    def errors(predictor, z, inputs, targets, context, steps, cut):
        out, sequence = [], inputs
        for _ in range(steps):
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
        return out

    def parallel_rollout_loss(predictor, z, context=2, steps=4, detach_later=False):
        context = slip.get("context", context)
        z = z.transpose(0, 1) if slip.get("batch_axis") else z
        targets = z.detach() if slip.get("detach_targets") else z
        cut = detach_later and steps > 1 and mode != "ignored"
        if not cut or mode == "predictions":
            found = errors(predictor, z, z, targets, context, steps, cut)
        else:  # step 1 on z, steps 2..K again from the detached latents
            found = errors(predictor, z, z, targets, context, 1, False) + errors(
                predictor, z, z.detach(), z.detach() if mode == "right" else targets,
                context, steps, False)[1:]
        return found[-1] if slip.get("last_only") else torch.stack(found).mean()

    return parallel_rollout_loss


def _cases() -> list[Case]:
    g = torch.Generator().manual_seed(7)
    drift = torch.arange(7.0)[None, :, None, None, None] * torch.randn(1, 1, 2, 3, 3, generator=g)
    return [
        _case("the predictor 'last latent + 0.5', random latents (2, 8, 3, 4, 4), context 2, "
              "K 3", "shift", torch.randn(2, 8, 3, 4, 4, generator=g), 2, 3, False),
        _case("a constant-velocity predictor on latents moving in straight lines (the loss is "
              "0)", "velocity", drift, 2, 4, False),
        _case("a nonlinear predictor, random latents (3, 10, 4, 4, 4), K 4", "mixer",
              torch.randn(3, 10, 4, 4, 4, generator=g), 2, 4, False),
        _case("a predictor averaging its window, context 3 (not 2), K 2", "mean",
              torch.randn(2, 7, 2, 3, 3, generator=g), 3, 2, False),
        _case("one step (K 1), latents (4, 5, 2, 2, 2)", "mixer",
              torch.randn(4, 5, 2, 2, 2, generator=g), 2, 1, False),
        _case("a batch as long as the clips, latents (6, 6, 2, 3, 3), K 3", "mixer",
              torch.randn(6, 6, 2, 3, 3, generator=g), 2, 3, False, seed=2),
        _case("the shortest clip, T = context + K = 5 frames", "velocity",
              torch.randn(2, 5, 2, 3, 3, generator=g), 2, 3, False),
        _case("a nonlinear predictor, K 4, detach_later=True (the course's runs)", "mixer",
              torch.randn(2, 8, 3, 3, 3, generator=g), 2, 4, True, seed=1),
        _case("a predictor averaging its window, context 3, K 3, detach_later=True", "mean",
              torch.randn(2, 8, 2, 3, 3, generator=g), 3, 3, True),
        _case("one step (K 1) with detach_later=True (nothing to detach)", "mixer",
              torch.randn(2, 6, 2, 3, 3, generator=g), 2, 1, True),
    ]


_SLIPS = slips(  # gradient-only slips first
    "parallel_rollout_loss", detach_ignored=_slip(detach="ignored"),
    targets_not_detached=_slip(detach="inputs"), predictions_detached=_slip(detach="predictions"),
    targets_detached=_slip(detach_targets=True), teacher_forcing=_slip(teacher_forcing=True),
    off_by_one=_slip(early=1), context_averaged=_slip(with_context=True),
    last_step_only=_slip(last_only=True), batch_axis=_slip(batch_axis=True),
    context_ignored=_slip(context=2),
    summed_elements=_slip(error=lambda d: d.pow(2).flatten(1).sum(1).mean()),
    unsquared=_slip(error=lambda d: d.pow(2).mean().sqrt()),
    absolute=_slip(error=lambda d: d.abs().mean()), autoregressive=rollout_loss)


check_parallel_rollout_loss = Exercise(
    "parallel_rollout_loss", parallel_rollout_loss, _SLIPS, _cases, adapt=_call,
    grad=[(1, "the predictor's weights"), (2, "the other latents z[:, :-1]"),
          (3, "the last latent z[:, -1] (only ever a target)")])
