"""Average precision (AP) of a detection probe, and a success rate's interval."""

import torch


def average_precision(scores: torch.Tensor, targets: torch.Tensor) -> float:
    """``AP = sum_k (R_k - R_{k-1}) P_k`` over all cells of ``scores`` / ``targets`` (any equal
    shapes), ranked together: 1 for a perfect ranking, about the fraction of positives for a
    random one. ``k`` runs over the distinct scores, highest first; ``P_k``, ``R_k``: precision
    and recall of "score >= threshold k", ``R_0 = 0`` (sklearn's ``average_precision_score``)."""
    scores, order = torch.sort(scores.detach().flatten().cpu(), descending=True, stable=True)
    targets = targets.detach().flatten().double().cpu()[order]
    if not targets.any():
        raise ValueError("AP is undefined without a positive cell: every target is 0")
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
    """The 95% Wilson score interval of a success rate ``p = successes / n``:
    ``(p + z^2/2n +- z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)`` with ``z = 1.96``."""
    if not 0 <= successes <= n or n < 1:
        raise ValueError(f"need 0 <= successes <= n and n >= 1, got {successes} of {n}")
    p, z = successes / n, 1.96
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z * (p * (1 - p) / n + z**2 / (4 * n**2)) ** 0.5 / (1 + z**2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)
