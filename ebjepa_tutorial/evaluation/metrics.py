"""Detection average precision (AP) for the Moving MNIST probe, without sklearn.

The probe scores every cell of an 8x8 grid in every frame; a cell is a
positive if it holds a digit centre. We rank *all* cells of *all* clips of the
evaluation set together, for one prediction horizon at a time, and summarise
the ranking by its average precision:

    AP = sum_k (R_k - R_{k-1}) P_k

where ``k`` runs over the distinct score thresholds from highest to lowest,
``P_k`` and ``R_k`` are the precision and recall of "score >= threshold k",
and ``R_0 = 0``. This is the step-wise area under the precision-recall curve
(no interpolation), the definition of sklearn's ``average_precision_score``.
Tied scores form one threshold: they enter the ranking together, so the
order of tied cells cannot change the AP.

The reference code averages AP over batches; an AP of a batch depends on
what else happens to be in it, so we compute it over the whole set instead.
:func:`wilson_interval` gives the confidence interval of a success rate.
"""

from __future__ import annotations

import torch


def _check_scores_targets(scores: torch.Tensor, targets: torch.Tensor) -> None:
    if not isinstance(scores, torch.Tensor) or not isinstance(targets, torch.Tensor):
        raise TypeError("scores and targets must be tensors")
    if scores.shape != targets.shape:
        raise ValueError(
            f"scores {tuple(scores.shape)} and targets {tuple(targets.shape)} differ in shape"
        )
    if scores.numel() == 0:
        raise ValueError("scores is empty: AP needs at least one scored cell")
    if not torch.isfinite(scores).all():
        raise ValueError("scores contain NaN or infinity; check the model's outputs")
    if not ((targets == 0) | (targets == 1)).all():
        raise ValueError("targets must be binary (0/1 or bool), e.g. from centres_to_grid")
    if not targets.any():
        raise ValueError("targets hold no positive cell, so recall and AP are undefined; "
                         "evaluate on clips that contain digits")


def average_precision(scores: torch.Tensor, targets: torch.Tensor) -> float:
    """``AP = sum_k (R_k - R_{k-1}) P_k`` over all cells of ``scores`` / ``targets``.

    Shapes are any, equal; everything is ranked together. Perfect ranking
    gives 1; a random ranking gives about the fraction of positive cells.
    """
    _check_scores_targets(scores, targets)
    scores, order = torch.sort(scores.detach().flatten().cpu(), descending=True, stable=True)
    targets = targets.detach().flatten().double().cpu()[order]
    true_pos = targets.cumsum(0)
    seen = torch.arange(1, len(scores) + 1, dtype=torch.float64)
    # The last cell of each run of tied scores closes a threshold: all ties count together.
    last_of_tie = torch.ones(len(scores), dtype=torch.bool)
    last_of_tie[:-1] = scores[1:] != scores[:-1]
    true_pos, seen = true_pos[last_of_tie], seen[last_of_tie]
    precision, recall = true_pos / seen, true_pos / targets.sum()  # P_k, R_k
    recall_step = torch.diff(recall, prepend=recall.new_zeros(1))
    return float((recall_step * precision).sum())


def wilson_interval(successes: int, n: int) -> tuple[float, float]:
    """The 95% Wilson score interval of a success rate ``successes / n``.

    ``(p + z^2/2n +- z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)`` with ``z = 1.96``:
    unlike the textbook ``p +- z sqrt(p(1-p)/n)`` it stays inside [0, 1] and does not
    shrink to a point at 0% or 100%.
    """
    if not 0 <= successes <= n or n < 1:
        raise ValueError(f"need 0 <= successes <= n and n >= 1, got {successes} of {n}")
    p, z = successes / n, 1.96
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z * (p * (1 - p) / n + z**2 / (4 * n**2)) ** 0.5 / (1 + z**2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)
