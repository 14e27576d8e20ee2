"""Moving MNIST, generated in code: digits bouncing in a 64x64 frame.

Srivastava et al. (2015) made videos of two MNIST digits moving in straight
lines and bouncing off the edges of a 64x64 frame. We build the same videos
from any stack of digits, in a few tensor operations (no Python loop over
clips), and keep what a detection probe needs: where every digit is in every
frame, exactly.

How a clip is made:

- each digit gets a start position (top-left corner of its 28x28 patch, drawn
  uniformly in ``[0, 64 - 28] = [0, 36]``) and a velocity of fixed ``speed``
  (default 3.6 px/frame, a tenth of the free range, as in the usual script)
  in a uniformly random direction;
- positions are floats; when a digit would leave the frame its position is
  reflected at the edge and that velocity component changes sign, so the
  28x28 patch never leaves the frame;
- the patch is pasted at the rounded position; overlapping digits are
  combined by a pixel-wise maximum.

What comes back, per digit and frame (``MovingMNISTBatch``): the integer
top-left of the pasted patch (``offsets``); the *ink* bounding box, the tight
box around the digit's non-zero pixels as pasted (``boxes``, ``(x0, y0, x1,
y1)`` with exclusive ends, so ``x1 - x0`` is the width); and ``centres``, the
centre of that ink box in pixel units (pixel ``i`` covers ``[i, i + 1)``).
The ink box is used rather than the 28x28 patch because MNIST digits are
not centred in their patch, and a probe should find the digit, not its margin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..utils import as_generator, make_generator

FRAME_SIZE = 64
DEFAULT_SPEED = 3.6  # px per frame: 0.1 of the free range 64 - 28 = 36
GRID = 8  # the detection targets' cells per side: 8 px each
CHUNK = 128  # clips pasted at a time: bounds the index memory, stays in cache


@dataclass
class MovingMNISTBatch:
    """Clips and the exact position of every digit in every frame.

    ``N`` clips, ``T`` frames, ``K`` digits per clip, frames ``S x S``:

    - ``clips``: uint8 ``(N, T, 1, S, S)``
    - ``centres``: float32 ``(N, T, K, 2)``, ``(x, y)`` centre of the ink box
    - ``boxes``: int64 ``(N, T, K, 4)``, ink box ``(x0, y0, x1, y1)``, ends exclusive
    - ``offsets``: int64 ``(N, T, K, 2)``, ``(x, y)`` top-left of the pasted patch
    - ``velocities``: float32 ``(N, T, K, 2)``, velocity from frame ``t`` to ``t + 1``
    - ``digit_ids``: int64 ``(N, K)``, which row of ``digits`` each digit is
    """

    clips: torch.Tensor
    centres: torch.Tensor
    boxes: torch.Tensor
    offsets: torch.Tensor
    velocities: torch.Tensor
    digit_ids: torch.Tensor

    def __len__(self) -> int:
        return self.clips.shape[0]


def check_digits(digits) -> torch.Tensor:
    """Return uint8 ``digits`` ``(N, 1, H, W)`` (our image layout) or ``(N, H, W)`` as
    ``(N, H, W)``, or raise a clear error."""
    if not isinstance(digits, torch.Tensor):
        raise TypeError(f"digits must be a tensor, got {type(digits).__name__}")
    if digits.ndim == 4 and digits.shape[1] == 1:
        digits = digits[:, 0]
    if digits.ndim != 3 or digits.shape[0] == 0:
        raise ValueError(
            f"digits must be (N, 1, H, W) or (N, H, W) with N >= 1, got {tuple(digits.shape)}; "
            "pass the images returned by load_mnist"
        )
    if digits.dtype != torch.uint8:
        raise TypeError(
            f"digits must be uint8 in 0..255, got {digits.dtype}; convert floats in [0, 1] "
            "with (x * 255).round().to(torch.uint8)"
        )
    return digits


def split_digits(digits, n_train: int = 8000) -> tuple[torch.Tensor, torch.Tensor]:
    """Split digits ``(N, ...)`` into ``n_train`` training and ``N - n_train`` held-out digits.

    The split is a permutation seeded with 0 (the official MNIST test file is not in
    random order: its two halves come from different writers), so evaluation
    clips can be built only from digits the model never saw, the same every time.
    """
    n = len(digits)
    if not 0 < n_train < n:
        raise ValueError(f"n_train must be between 1 and {n - 1} for {n} digits, got {n_train}")
    order = torch.randperm(n, generator=make_generator(0))
    return digits[order[:n_train]], digits[order[n_train:]]


def ink_boxes(digits: torch.Tensor) -> torch.Tensor:
    """Tight box around the non-zero pixels of each digit: ``(N, H, W)`` -> int64 ``(N, 4)``.

    ``(x0, y0, x1, y1)`` in the digit's own patch, ends exclusive. A blank
    digit (no ink) gets the whole patch ``(0, 0, W, H)``.
    """
    ink = digits > 0
    n, h, w = ink.shape
    boxes = []
    for any_ink, size in ((ink.any(dim=1), w), (ink.any(dim=2), h)):  # columns, then rows
        first = any_ink.int().argmax(dim=1)
        last = size - any_ink.flip(1).int().argmax(dim=1)
        blank = ~any_ink.any(dim=1)
        boxes.append((first.masked_fill(blank, 0), last.masked_fill(blank, size)))
    (x0, x1), (y0, y1) = boxes
    return torch.stack([x0, y0, x1, y1], dim=1).long()


def bounce_trajectories(
    start: torch.Tensor, velocity: torch.Tensor, n_frames: int, limit: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Move points in straight lines inside ``[0, limit]``, reflecting at the edges.

    ``start``, ``velocity``: ``(..., 2)``. Returns ``positions`` and
    ``velocities``, each ``(n_frames, ..., 2)``: ``positions[t + 1]`` is
    ``positions[t] + velocities[t]``, reflected at 0 or ``limit`` if it
    crossed one, and ``velocities[t + 1]`` is ``velocities[t]`` with the sign
    of each reflected component flipped. Needs ``|velocity| <= limit`` so a
    step crosses at most one edge per axis. The loop runs over frames only.
    """
    if velocity.abs().max() > limit:
        raise ValueError(f"speed per axis must be at most the free range {limit}")
    position, velocity = start.clone(), velocity.clone()
    positions, velocities = [], []
    for _ in range(n_frames):
        positions.append(position.clone())
        velocities.append(velocity.clone())
        position = position + velocity
        below, above = position < 0, position > limit
        position = torch.where(below, -position, position)
        position = torch.where(above, 2 * limit - position, position)
        velocity = torch.where(below | above, -velocity, velocity)
    return torch.stack(positions), torch.stack(velocities)


def paste_digits(frames: torch.Tensor, patches: torch.Tensor, offsets: torch.Tensor) -> None:
    """Paste patches into ``frames`` in place, combining overlaps by maximum.

    ``frames``: uint8 ``(M, S, S)``, contiguous (usually zeros);
    ``patches``: uint8 ``(M, K, h, w)``; ``offsets``: int64 ``(M, K, 2)``,
    ``(x, y)`` top-left of each patch, inside the frame. One ``scatter_reduce``
    with ``amax`` writes every pixel of every patch at its flat index
    ``(y + i) * S + (x + j)``: no Python loop over frames or digits.
    """
    m, k, h, w = patches.shape
    size = frames.shape[-1]
    rows, cols = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    pixel = (rows * size + cols).reshape(1, 1, h * w)
    corner = (offsets[..., 1] * size + offsets[..., 0]).unsqueeze(-1)
    index = (corner + pixel).reshape(m, k * h * w)
    flat = frames.view(m, size * size)  # a view, so the scatter writes into frames
    flat.scatter_reduce_(1, index, patches.reshape(m, k * h * w), reduce="amax")


def _check_sizes(digits: torch.Tensor, speed: float, **counts) -> float:
    """Raise a clear error for a count < 1, a digit that does not fit, or too high a speed;
    return the free range ``64 - h`` a digit's top-left corner moves in."""
    for name, value in counts.items():
        if not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    h, w = digits.shape[1:]
    if h != w or h > FRAME_SIZE:
        raise ValueError(f"digits must be square and fit in 64x64 frames, got {h}x{w}")
    limit = float(FRAME_SIZE - h)
    if not 0 <= speed <= limit:
        raise ValueError(f"speed must be in [0, {limit}] px/frame (the free range), got {speed}")
    return limit


def random_motion(n_clips: int, n_digits: int, speed: float, limit: float,
                  generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Start corners uniform in ``[0, limit]^2`` and velocities of length ``speed`` in a
    uniform direction: each ``(n_clips, n_digits, 2)``, as ``(x, y)``."""
    start = torch.rand(n_clips, n_digits, 2, generator=generator) * limit
    angle = torch.rand(n_clips, n_digits, generator=generator) * (2 * math.pi)
    return start, speed * torch.stack([angle.cos(), angle.sin()], dim=-1)


def paste_clips(digits: torch.Tensor, digit_ids: torch.Tensor,
                offsets: torch.Tensor) -> torch.Tensor:
    """uint8 clips ``(N, T, 1, 64, 64)``: digit ``digit_ids[n, k]`` ``(N, K)`` of
    ``digits`` ``(D, h, w)`` pasted at ``offsets[n, t, k]`` ``(N, T, K, 2)``, ``CHUNK``
    clips at a time."""
    (n_clips, n_frames, n_digits, _), (h, w) = offsets.shape, digits.shape[1:]
    clips = torch.empty(n_clips, n_frames, 1, FRAME_SIZE, FRAME_SIZE, dtype=torch.uint8)
    for lo in range(0, n_clips, CHUNK):
        hi = min(lo + CHUNK, n_clips)
        clips[lo:hi].zero_()
        patches = digits[digit_ids[lo:hi]].unsqueeze(1).expand(-1, n_frames, -1, -1, -1)
        paste_digits(clips[lo:hi].view(-1, FRAME_SIZE, FRAME_SIZE),
                     patches.reshape(-1, n_digits, h, w),
                     offsets[lo:hi].reshape(-1, n_digits, 2))
    return clips


def generate_moving_mnist(
    digits,
    n_clips: int,
    n_frames: int = 10,
    n_digits: int = 2,
    speed: float = DEFAULT_SPEED,
    seed: int | torch.Generator = 0,
) -> MovingMNISTBatch:
    """Make ``n_clips`` Moving MNIST clips of ``n_frames`` frames from ``digits``.

    ``digits``: uint8 ``(D, 1, h, w)`` or ``(D, h, w)`` (for held-out
    evaluation, pass the second half of :func:`split_digits`). Each clip shows
    ``n_digits`` digits drawn with replacement. ``seed`` is an int or a
    ``torch.Generator``; the same seed gives identical clips. The module docstring
    says what each field of the returned :class:`MovingMNISTBatch` means.
    """
    digits = check_digits(digits)
    limit = _check_sizes(digits, speed, n_clips=n_clips, n_frames=n_frames, n_digits=n_digits)
    generator = as_generator(seed)
    digit_ids = torch.randint(len(digits), (n_clips, n_digits), generator=generator)
    start, velocity = random_motion(n_clips, n_digits, speed, limit, generator)
    positions, velocities = bounce_trajectories(start, velocity, n_frames, limit)
    offsets = positions.round().long().transpose(0, 1).contiguous()  # (N, T, K, 2)
    clips = paste_clips(digits, digit_ids, offsets)
    ink = ink_boxes(digits[digit_ids.flatten()]).view(n_clips, 1, n_digits, 4)  # in the patch
    boxes = ink + offsets.repeat(1, 1, 1, 2)
    centres = (boxes[..., :2] + boxes[..., 2:]).float() / 2
    return MovingMNISTBatch(clips=clips, centres=centres, boxes=boxes, offsets=offsets,
                            velocities=velocities.transpose(0, 1).contiguous(),
                            digit_ids=digit_ids)


def centres_to_grid(centres: torch.Tensor) -> torch.Tensor:
    """Detection targets: which cells of a ``GRID x GRID`` (8 x 8) tiling hold a digit centre.

    ``centres``: ``(..., K, 2)`` as ``(x, y)`` pixels in a 64 x 64 frame.
    Returns float32 ``(..., GRID, GRID)`` of 0/1, indexed ``[row, col]``
    = ``[y cell, x cell]``; a cell with two centres is still 1.
    """
    cell = torch.div(centres, FRAME_SIZE / GRID, rounding_mode="floor").long().clamp(0, GRID - 1)
    flat = cell[..., 1] * GRID + cell[..., 0]  # (..., K)
    target = torch.zeros(*flat.shape[:-1], GRID * GRID)
    target.scatter_(-1, flat, 1.0)
    return target.view(*flat.shape[:-1], GRID, GRID)
