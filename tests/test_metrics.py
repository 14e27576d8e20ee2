"""Average precision: hand-computed cases, ties, errors, the whole set ranked together; the
Wilson interval's edge cases."""

from __future__ import annotations

import pytest
import torch

from ebjepa_tutorial.evaluation.metrics import average_precision, wilson_interval


def brute_force_ap(scores: list[float], targets: list[int]) -> float:
    """AP straight from the definition: one threshold per distinct score, highest first."""
    n_pos, ap, last_recall = sum(targets), 0.0, 0.0
    for threshold in sorted(set(scores), reverse=True):
        chosen = [t for s, t in zip(scores, targets, strict=True) if s >= threshold]
        precision, recall = sum(chosen) / len(chosen), sum(chosen) / n_pos
        ap += (recall - last_recall) * precision
        last_recall = recall
    return ap


def test_ap_by_hand():
    # ranks 1..5 hit, miss, hit, miss, hit: P = 1, 1/2, 2/3, 2/4, 3/5 and R = 1/3, 1/3, 2/3, 2/3, 1
    # AP = 1/3 * 1 + 1/3 * 2/3 + 1/3 * 3/5 = 34/45
    scores = torch.tensor([0.9, 0.8, 0.7, 0.6, 0.5])
    targets = torch.tensor([1, 0, 1, 0, 1])
    assert average_precision(scores, targets) == pytest.approx(34 / 45)
    shuffled = torch.tensor([3, 0, 4, 1, 2])  # input order does not matter, only the ranking
    assert average_precision(scores[shuffled], targets[shuffled]) == pytest.approx(34 / 45)


def test_ties_enter_the_ranking_together():
    # 0.9: P 0, R 0; the tied pair at 0.5: P 1/3, R 1/2; 0.1: P 2/4, R 1 -> AP = 1/6 + 1/4
    scores = torch.tensor([0.9, 0.5, 0.5, 0.1])
    for targets in ([0, 1, 0, 1], [0, 0, 1, 1]):  # either order of the tied pair
        assert average_precision(scores, torch.tensor(targets)) == pytest.approx(5 / 12)
    # one tied group for everything: AP is the fraction of positives
    assert average_precision(torch.zeros(8), torch.tensor([1, 0, 0, 1, 0, 0, 0, 0])) == 0.25


def test_perfect_and_worst_ranking():
    targets = torch.tensor([0, 1, 0, 1, 1, 0, 0])
    assert average_precision(targets.float() * 3 - 1, targets) == 1.0
    # both positives ranked last of four: P = 1/3 then 2/4 at recall 1/2 and 1
    worst = average_precision(torch.tensor([4.0, 3.0, 2.0, 1.0]), torch.tensor([0, 0, 1, 1]))
    assert worst == pytest.approx(0.5 * 1 / 3 + 0.5 * 2 / 4)


def test_matches_the_definition_on_random_scores_with_ties():
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        scores = torch.randint(0, 6, (60,), generator=g).float() / 5  # many ties
        targets = (torch.rand(60, generator=g) < 0.3).long()
        targets[0] = 1
        expected = brute_force_ap(scores.tolist(), targets.tolist())
        assert average_precision(scores, targets) == pytest.approx(expected)


def test_bool_targets_and_any_shape():
    scores = torch.tensor([[0.9, 0.8], [0.7, 0.6]])
    targets = torch.tensor([[True, False], [False, True]])
    assert average_precision(scores, targets) == pytest.approx(0.5 * 1 + 0.5 * 2 / 4)


def test_no_positive_cell_is_an_error_not_nan():
    with pytest.raises(ValueError, match="without a positive cell"):
        average_precision(torch.rand(5), torch.zeros(5))


def test_whole_set_ap_is_not_the_mean_of_batch_aps():
    # Batch A ranks well on its own scale, batch B on a lower one; pooled, B's positive
    # falls below A's negative, which per-batch averaging would hide.
    scores_a, targets_a = torch.tensor([0.9, 0.8]), torch.tensor([1, 0])
    scores_b, targets_b = torch.tensor([0.3, 0.2]), torch.tensor([1, 0])
    ap_a, ap_b = average_precision(scores_a, targets_a), average_precision(scores_b, targets_b)
    per_batch = (ap_a + ap_b) / 2
    pooled = average_precision(torch.cat([scores_a, scores_b]), torch.cat([targets_a, targets_b]))
    assert per_batch == 1.0
    assert pooled == pytest.approx(0.5 * 1 + 0.5 * 2 / 3)


def test_wilson_interval_refuses_an_empty_count_and_stays_within_0_and_1():
    """No episode is no rate: 0 of 0 is a ValueError naming the rule, not a division by zero.
    At all or nothing the interval keeps to [0, 1], touching the end it sits at."""
    with pytest.raises(ValueError, match="n >= 1"):
        wilson_interval(0, 0)
    with pytest.raises(ValueError, match="successes <= n"):
        wilson_interval(-1, 4)
    for n in (1, 7, 100):
        low, high = wilson_interval(n, n)
        assert 0 < low < 1 and high == pytest.approx(1.0)
        low, high = wilson_interval(0, n)
        assert low == 0 and 0 < high < 1
