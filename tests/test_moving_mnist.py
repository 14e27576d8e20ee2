"""Moving MNIST generator: bounds, bouncing, exact boxes, max-overlap, seeds, splits."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
import torch
from test_data import shared_data

from ebjepa_tutorial.data.moving_mnist import (
    bounce_trajectories,
    centres_to_grid,
    generate_moving_mnist,
    ink_boxes,
    paste_clips,
    split_digits,
)


def synthetic_digits(n: int = 40, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` 28x28 "digits", each a random rectangle of ink (1..255); returns digits, boxes."""
    rng = np.random.default_rng(seed)
    digits = np.zeros((n, 1, 28, 28), np.uint8)
    boxes = np.zeros((n, 4), np.int64)
    for i in range(n):
        x0, y0 = rng.integers(0, 10, size=2)
        x1, y1 = rng.integers(14, 29, size=2)
        digits[i, 0, y0:y1, x0:x1] = rng.integers(1, 256, size=(y1 - y0, x1 - x0))
        boxes[i] = (x0, y0, x1, y1)
    return torch.from_numpy(digits), torch.from_numpy(boxes)


def real_mnist_digits() -> torch.Tensor:
    """The official test digits, read from the IDX file here (skips the test without one)."""
    path = Path("mnist") / "t10k-images-idx3-ubyte.gz"
    folder = shared_data(lambda folder: (folder / path).is_file(), f"the MNIST file {path}")
    with gzip.open(folder / path) as f:
        raw = np.frombuffer(f.read(), np.uint8, offset=16)
    return torch.from_numpy(raw.reshape(-1, 1, 28, 28).copy())


def naive_clip(digits: torch.Tensor, offsets: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """Reference paste, one digit at a time in Python: offsets (T, K, 2), ids (K,)."""
    frames = torch.zeros(offsets.shape[0], 64, 64, dtype=torch.uint8)
    for t in range(offsets.shape[0]):
        for k, i in enumerate(ids.tolist()):
            x, y = offsets[t, k].tolist()
            region = frames[t, y : y + 28, x : x + 28]
            frames[t, y : y + 28, x : x + 28] = torch.maximum(region, digits[i, 0])
    return frames


@pytest.fixture(scope="module")
def digits_and_boxes():
    return synthetic_digits()


@pytest.fixture(scope="module")
def batch(digits_and_boxes):
    return generate_moving_mnist(digits_and_boxes[0], n_clips=64, n_frames=12, seed=3)


def test_digits_start_out_in_every_direction(batch):
    # a half-circle of directions (pi for 2 pi) would send every digit the same way in y
    first = batch.velocities[:, 0].flatten(0, 1)  # (clips x digits, 2): each digit's first step
    for axis in (0, 1):
        assert 0.35 < (first[:, axis] < 0).float().mean() < 0.65


def test_shapes_and_dtypes(batch):
    assert batch.clips.shape == (64, 12, 1, 64, 64) and batch.clips.dtype == torch.uint8
    assert batch.centres.shape == (64, 12, 2, 2) and batch.centres.dtype == torch.float32
    assert batch.boxes.shape == (64, 12, 2, 4) and batch.boxes.dtype == torch.int64
    assert batch.offsets.shape == batch.velocities.shape == (64, 12, 2, 2)
    assert batch.digit_ids.shape == (64, 2) and len(batch.clips) == 64


def test_digits_stay_in_frame_and_nothing_is_drawn_outside_the_boxes(batch):
    assert batch.offsets.min() >= 0 and batch.offsets.max() <= 64 - 28
    assert batch.boxes.min() >= 0 and batch.boxes.max() <= 64
    rows = torch.arange(64).view(1, 1, 1, 64, 1)
    cols = torch.arange(64).view(1, 1, 1, 1, 64)
    x0, y0, x1, y1 = (batch.boxes[..., i, None, None] for i in range(4))
    inside = ((cols >= x0) & (cols < x1) & (rows >= y0) & (rows < y1)).any(dim=2)
    assert (batch.clips[:, :, 0][~inside] == 0).all()
    assert (batch.clips[:, :, 0][inside] > 0).any()


def test_boxes_and_centres_are_exact(batch, digits_and_boxes):
    digits, ink = digits_and_boxes
    expected = ink[batch.digit_ids].unsqueeze(1) + batch.offsets.repeat(1, 1, 1, 2)
    assert torch.equal(batch.boxes, expected)
    assert torch.equal(batch.centres, (expected[..., :2] + expected[..., 2:]).float() / 2)
    assert torch.equal(ink_boxes(digits[:, 0]), ink)


def test_clips_match_a_naive_paste_including_overlaps(batch, digits_and_boxes):
    digits = digits_and_boxes[0]
    for n in range(len(batch.clips)):
        expected = naive_clip(digits, batch.offsets[n], batch.digit_ids[n])
        assert torch.equal(batch.clips[n, :, 0], expected)
    gap = (batch.offsets[:, :, 0] - batch.offsets[:, :, 1]).abs()
    assert ((gap < 28).all(dim=-1)).any(), "no overlapping digits: the max test checked nothing"


def test_crop_at_offset_is_the_digit_where_digits_do_not_overlap(batch, digits_and_boxes):
    digits = digits_and_boxes[0]
    apart = ((batch.offsets[:, :, 0] - batch.offsets[:, :, 1]).abs() >= 28).any(dim=-1)
    assert apart.sum() > 10
    for n, t in apart.nonzero().tolist():
        for k in range(2):
            x, y = batch.offsets[n, t, k].tolist()
            crop = batch.clips[n, t, 0, y : y + 28, x : x + 28]
            assert torch.equal(crop, digits[batch.digit_ids[n, k], 0])


def test_paste_combines_overlaps_by_maximum():
    a = torch.zeros(2, 2, dtype=torch.uint8)
    a[0, 0], a[1, 1] = 100, 7
    b = torch.full((2, 2), 50, dtype=torch.uint8)
    clips = paste_clips(torch.stack([a, b]), torch.tensor([[0, 1]]),
                        torch.tensor([[[[3, 4], [3, 4]]]]))  # both at x = 3, y = 4
    expected = torch.zeros(64, 64, dtype=torch.uint8)
    expected[4:6, 3:5] = torch.tensor([[100, 50], [50, 50]], dtype=torch.uint8)
    assert torch.equal(clips[0, 0, 0], expected)


def test_bounce_by_hand():
    positions, velocities = bounce_trajectories(
        torch.tensor([0.5, 10.0]), torch.tensor([-2.0, 3.0]), n_frames=4, limit=12.0
    )
    # x: 0.5 -> -1.5 reflects to 1.5 (v = +2) -> 3.5 -> 5.5
    # y: 10 -> 13 reflects to 11 (v = -3) -> 8 -> 5
    assert torch.allclose(positions, torch.tensor([[0.5, 10], [1.5, 11], [3.5, 8], [5.5, 5]]))
    assert torch.equal(velocities[0], torch.tensor([-2.0, 3.0]))
    assert torch.equal(velocities[1:], torch.tensor([[2.0, -3.0]] * 3))


def test_velocity_flips_only_at_the_edges():
    g = torch.Generator().manual_seed(0)
    start = torch.rand(500, 2, generator=g) * 36
    velocity = (torch.rand(500, 2, generator=g) - 0.5) * 8
    positions, velocities = bounce_trajectories(start, velocity, n_frames=30, limit=36.0)
    assert positions.min() >= 0 and positions.max() <= 36
    step = positions[:-1] + velocities[:-1]
    flipped = velocities[1:] == -velocities[:-1]
    crossed = (step < 0) | (step > 36)
    assert torch.equal(flipped & (velocities[:-1] != 0), crossed)
    assert torch.allclose(positions[1:][~crossed], step[~crossed])
    reflected = torch.where(step < 0, -step, 72 - step)
    assert torch.allclose(positions[1:][crossed], reflected[crossed])
    assert (velocities.abs() == velocity.abs()).all(), "speed per axis is constant"


def test_generated_speed_is_fixed(batch):
    speed = batch.velocities.norm(dim=-1)
    assert torch.allclose(speed, torch.full_like(speed, 3.6))


def test_the_pasted_digits_move_by_their_velocity(batch):
    # between frames without a bounce a digit's patch moves by its velocity, to within the
    # rounding of each position to whole pixels (x and y swapped, or frozen digits, would fail)
    moved = (batch.offsets[:, 1:] - batch.offsets[:, :-1]).float()  # (N, T-1, K, 2)
    velocity = batch.velocities[:, :-1]
    straight = (batch.velocities[:, 1:] == velocity).all(dim=-1)  # neither axis bounced
    assert straight.float().mean() > 0.7
    assert ((moved - velocity).abs()[straight] <= 1.0 + 1e-5).all()


def test_draws_cover_every_digit_and_the_whole_free_range(digits_and_boxes):
    """Digits are drawn with replacement from all of ``digits``, and start uniformly over the
    free range [0, 64 - 28 = 36] of their top-left corner: rounded to whole pixels, the first
    frame's corners reach both ends, 0 and 36, and average 18 (a corner truncated instead of
    rounded, or a range one short, never reaches 36)."""
    batch = generate_moving_mnist(digits_and_boxes[0], n_clips=500, n_frames=1, seed=0)
    assert batch.digit_ids.unique().tolist() == list(range(40))
    corners = batch.offsets[:, 0].flatten(0, 1)  # (clips x digits, 2)
    for axis in (0, 1):
        assert corners[:, axis].min() == 0 and corners[:, axis].max() == 36
        assert abs(corners[:, axis].float().mean() - 18) < 1.5


def test_speeds_from_0_to_the_free_range_are_allowed(digits_and_boxes):
    """``speed`` in [0, 36] px/frame, both ends included: at 0 the digits stand still, at 36
    (one edge per axis per step at most) they still bounce inside the frame."""
    digits = digits_and_boxes[0]
    still = generate_moving_mnist(digits, n_clips=3, n_frames=4, speed=0.0, seed=0)
    assert torch.equal(still.offsets, still.offsets[:, :1].expand_as(still.offsets))
    fastest = generate_moving_mnist(digits, n_clips=3, n_frames=6, speed=36.0, seed=0)
    assert torch.allclose(fastest.velocities.norm(dim=-1), torch.tensor(36.0))
    assert fastest.offsets.min() >= 0 and fastest.offsets.max() <= 36


def test_same_seed_same_clips_and_different_seed_different(digits_and_boxes):
    digits = digits_and_boxes[0]
    a = generate_moving_mnist(digits, 8, seed=11)
    b = generate_moving_mnist(digits, 8, seed=11)
    c = generate_moving_mnist(digits, 8, seed=12)
    assert torch.equal(a.clips, b.clips) and torch.equal(a.centres, b.centres)
    assert not torch.equal(a.clips, c.clips)
    g = torch.Generator().manual_seed(11)
    first = generate_moving_mnist(digits, 8, seed=g)
    second = generate_moving_mnist(digits, 8, seed=g)  # the generator has moved on
    assert torch.equal(first.clips, a.clips) and not torch.equal(second.clips, a.clips)


def test_split_digits_is_disjoint_and_deterministic():
    ids = torch.arange(100)
    train, held_out = split_digits(ids, n_train=80)
    assert len(train) == 80 and len(held_out) == 20
    assert set(train.tolist()).isdisjoint(held_out.tolist())
    assert sorted(train.tolist() + held_out.tolist()) == list(range(100))
    assert torch.equal(split_digits(ids, 80)[1], held_out)
    assert not torch.equal(held_out, torch.arange(80, 100))  # a permutation, not the last 20


def test_the_held_out_digits_are_pinned():
    """The shipped video models trained on the first 8,000 digits of this permutation of the
    10,000 MNIST test digits and are probed on the other 2,000: a changed seed or draw would
    silently put their training digits among the held-out ones."""
    train, held_out = split_digits(torch.arange(10_000))
    assert train[:6].tolist() == [6044, 2890, 9399, 1917, 4919, 1729]
    assert held_out[:6].tolist() == [8052, 366, 9079, 841, 7920, 2344]


def test_clips_from_held_out_digits_use_only_those_digits(digits_and_boxes):
    digits = digits_and_boxes[0]
    _, held_out = split_digits(digits, n_train=30)
    clips = generate_moving_mnist(held_out, 20, seed=0)
    assert clips.digit_ids.max() < len(held_out)


def test_grid_targets_by_hand():
    centres = torch.tensor([[[5.0, 60.0], [32.0, 31.9]], [[10.0, 10.0], [12.0, 15.0]]])
    grid = centres_to_grid(centres)  # two frames, two digits each
    assert grid.shape == (2, 8, 8)
    assert grid[0, 7, 0] == 1 and grid[0, 3, 4] == 1 and grid[0].sum() == 2
    assert grid[1, 1, 1] == 1 and grid[1].sum() == 1  # both centres in one cell


def test_grid_targets_of_centres_on_the_frame_edge_are_the_border_cells():
    """A centre on the frame's far edge (x or y = 64) is in the last cell of its row or
    column, not in a cell past the grid (the next row's first cell, or out of range)."""
    grid = centres_to_grid(torch.tensor([[64.0, 20.0], [0.0, 64.0]]))
    assert grid[2, 7] == 1 and grid[7, 0] == 1 and grid.sum() == 2


def test_grid_targets_from_a_batch_mark_each_centre_cell_and_nothing_else(batch):
    grid = centres_to_grid(batch.centres)
    assert grid.shape == (64, 12, 8, 8)
    expected = torch.zeros(64, 12, 8, 8)
    for (n, t, _), (x, y) in zip(torch.cartesian_prod(*map(torch.arange, (64, 12, 2))).tolist(),
                                 batch.centres.flatten(0, 2).tolist()):
        expected[n, t, int(y) // 8, int(x) // 8] = 1  # row: the y cell, column: the x cell
    assert torch.equal(grid, expected)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"digits": torch.rand(5, 1, 28, 28)}, TypeError, "uint8"),
        ({"digits": torch.zeros(5, 3, 28, 28, dtype=torch.uint8)}, ValueError, "N, 1, H, W"),
        ({"digits": torch.zeros(5, 28, 20, dtype=torch.uint8)}, ValueError, "square"),
        ({"speed": 40.0}, ValueError, "speed"),
    ],
)
def test_bad_input_gives_a_clear_error(kwargs, error, match):
    args = {"digits": synthetic_digits(3)[0], "n_clips": 2} | kwargs
    with pytest.raises(error, match=match):
        generate_moving_mnist(**args)


def test_numpy_digits_make_the_same_clips_and_float_digits_are_told_how_to_convert():
    digits = synthetic_digits(3)[0]
    clips = generate_moving_mnist(digits, n_clips=2, seed=0).clips
    assert torch.equal(generate_moving_mnist(digits.numpy(), n_clips=2, seed=0).clips, clips)
    with pytest.raises(TypeError, match=r"got torch.float64.*0..255 values with "
                                        r"x.round\(\).to\(torch.uint8\)"):
        generate_moving_mnist(digits.double(), n_clips=2)


def test_real_mnist_digits_are_pasted_exactly():
    digits = real_mnist_digits()
    batch = generate_moving_mnist(digits[:500], n_clips=32, seed=0)
    for n in range(4):
        expected = naive_clip(digits[:500], batch.offsets[n], batch.digit_ids[n])
        assert torch.equal(batch.clips[n, :, 0], expected)
    centre = batch.centres - batch.offsets  # within the 28x28 patch
    assert (centre > 4).all() and (centre < 24).all()  # MNIST ink is roughly centred
