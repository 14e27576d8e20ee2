"""Does the latent know where the agent is (a linear position probe, in pixels), and does
the predictor know the walls (the wall test)? Chapters 05-06."""

import torch
from torch import nn

from ..envs import generate_trajectories
from ..envs.two_rooms import HIGH, LOW, render, walls_of
from ..models.world import WorldModel, encode_trajectories
from .classify import LinearProbe

MIN_STOP = 0.8  # px: the wall test's steps, cut short by a wall or free, are at least this long


def _check_pair(latents: torch.Tensor, positions: torch.Tensor) -> None:
    if latents.ndim != 2 or positions.ndim != 2 or len(latents) != len(positions):
        raise ValueError(f"need latents (N, D) and positions (N, 2) with the same N, got "
                         f"{tuple(latents.shape)} and {tuple(positions.shape)}; flatten time "
                         "first: z.reshape(-1, D), positions.reshape(-1, 2)")


@torch.no_grad()
def fit_position_probe(latents: torch.Tensor, positions: torch.Tensor) -> LinearProbe:
    """Latents ``(N, D)`` -> positions ``(N, 2)`` in pixels: least squares on the standardised
    latents with an L2 penalty of 1e-3 per sample, solved exactly on their device."""
    _check_pair(latents, positions)
    if len(latents) < 2:
        raise ValueError("a probe needs at least two samples to standardise the latents")
    x = latents.detach().float()
    y = positions.detach().float().to(x.device)
    mean, std = x.mean(dim=0), x.std(dim=0).clamp_min(1e-6)
    x = (x - mean) / std
    head = nn.Linear(x.shape[1], y.shape[1]).to(x.device)
    y_mean = y.mean(dim=0)
    # Normal equations on centred data: (X^T X + N ridge I) W = X^T (Y - mean Y).
    gram = x.T @ x + len(x) * 1e-3 * torch.eye(x.shape[1], device=x.device)
    head.weight.copy_(torch.linalg.solve(gram, x.T @ (y - y_mean)).T)  # (2, D)
    head.bias.copy_(y_mean)  # x is centred, so the bias is the mean position
    return LinearProbe(mean, std, head)


@torch.no_grad()
def probe_error_px(probe: nn.Module, latents: torch.Tensor, positions: torch.Tensor) -> float:
    """Mean Euclidean error ``mean_n ||probe(z_n) - p_n||`` in pixels, on held-out rows."""
    _check_pair(latents, positions)
    read = probe(latents.float())  # (N, 2), on the probe's device
    return (read - positions.float().to(read.device)).norm(dim=1).mean().item()


def mean_baseline_px(train_positions: torch.Tensor, test_positions: torch.Tensor) -> float:
    """The error of always answering the mean train position: the score of a blind latent."""
    return (test_positions - train_positions.mean(dim=0)).norm(dim=1).mean().item()


def _wall_steps(trajectories):
    """Steps a wall cut short by more than ``MIN_STOP`` px (those whose action would leave
    the arena skipped) and free steps of at least ``MIN_STOP`` px: two ``(B, T)`` masks."""
    positions, actions = trajectories.positions, trajectories.actions
    intended = positions[:, :-1] + actions
    shortfall = (positions[:, 1:] - intended).norm(dim=-1)  # how much a wall took away
    inside = ((intended >= LOW) & (intended <= HIGH)).all(dim=-1)
    stopped = (shortfall > MIN_STOP) & inside
    if not stopped.any():
        raise ValueError(f"the walls stopped no step of these {len(positions)} "
                         f"trajectories by more than {MIN_STOP} px; use more of them")
    return stopped, (shortfall < 1e-4) & (actions.norm(dim=-1) >= MIN_STOP)


def _nearer(model, trajectories, steps, max_steps: int | None, through_wall: bool):
    """Flags ``(n,)``, and the steps' ``b``, ``t``, for the first ``max_steps`` of the mask
    ``steps``: is ``Pred(z_t, a_t)`` nearer the real ``z_{t+1}`` than the dot moved by the
    action alone, into the wall (without ``through_wall``: than ``z_t``)?"""
    positions, actions = trajectories.positions, trajectories.actions
    device = next(model.parameters()).device
    b, t = steps.nonzero()[:max_steps].unbind(1)

    def encode(where):  # latents of the dot at where in layout b
        return model.encode(render(where, trajectories.layouts[b]).to(device)).cpu()

    now = encode(positions[b, t])
    guess = model.predict(now.to(device), actions[b, t].to(device)).cpu()
    other = encode(positions[b, t] + actions[b, t]) if through_wall else now
    real = encode(positions[b, t + 1])
    return (guess - real).norm(dim=1) < (guess - other).norm(dim=1), b, t


@torch.no_grad()
def middle_wall_test(model, trajectories) -> dict:
    """``stopped``: on the first 1000 (``n_stopped``) steps a wall cut short, the fraction of
    predictions nearer the real next latent than the dot moved into the wall; ``moved``: on the
    first 1000 free steps (``n_moved``), vs z_t (a still predictor: 0 here, about 1 above)."""
    stopped_steps, moved_steps = _wall_steps(trajectories)
    stopped = _nearer(model, trajectories, stopped_steps, 1000, through_wall=True)[0]
    moved = _nearer(model, trajectories, moved_steps, 1000, through_wall=False)[0]
    return {"stopped": stopped.float().mean().item(), "moved": moved.float().mean().item(),
            "n_stopped": len(stopped), "n_moved": len(moved)}


@torch.no_grad()
def wall_test_by_door_distance(model, trajectories, edges=(0, 8, 12, 16, 24, 65)) -> list[dict]:
    """:func:`middle_wall_test`'s ``stopped`` over each bin ``[lo, hi)`` of ``edges`` of
    ``|y_t - door_y|``, the door of the wall nearest in x (the one that stopped the dot):
    a dict per bin, ``lo``, ``hi``, ``stopped`` (NaN if empty) and ``n``."""
    flags, b, t = _nearer(model, trajectories, _wall_steps(trajectories)[0], None,
                          through_wall=True)
    here = trajectories.positions[b, t]
    walls = walls_of(trajectories.layouts[b]).to(here.dtype)  # (n, W, 2)
    # (n,): the wall that stopped the dot (its step began within 4.3 px; walls are 14+ apart)
    nearest = (walls[..., 0] - here[:, None, 0]).abs().argmin(dim=1)
    along = (here[:, 1] - walls[torch.arange(len(walls)), nearest, 1]).abs()
    bins = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (along >= lo) & (along < hi)
        bins.append({"lo": lo, "hi": hi, "n": int(inside.sum()),
                     "stopped": flags[inside].float().mean().item()})
    return bins


def probe_report(model: WorldModel, n_fit: int = 1000, n_test: int = 300, seed: int = 12345,
                 test_steps: int = 16, walls: int = 1):
    """``{"probe_px", "baseline_px", "probe"}``: a position probe fitted on the frames of
    ``n_fit`` fresh trajectories (seed ``seed``), scored on ``n_test`` others (``seed + 1``)."""
    fit_trajectories = generate_trajectories(n_fit, seed=seed, walls=walls)
    test_trajectories = generate_trajectories(n_test, steps=test_steps, seed=seed + 1,
                                              walls=walls)
    z_fit, xy_fit = encode_trajectories(model, fit_trajectories)
    z_test, xy_test = encode_trajectories(model, test_trajectories)
    probe = fit_position_probe(z_fit, xy_fit)
    return {"probe_px": probe_error_px(probe, z_test, xy_test),
            "baseline_px": mean_baseline_px(xy_fit, xy_test), "probe": probe}
