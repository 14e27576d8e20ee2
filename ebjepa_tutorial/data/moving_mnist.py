"""Moving MNIST (Srivastava et al., 2015): digits bouncing in a 64x64 frame at a fixed speed,
overlaps combined by maximum, every digit's position known exactly."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..utils import as_generator

FRAME_SIZE = 64
DEFAULT_SPEED = 3.6  # px per frame: 0.1 of the free range 64 - 28 = 36
GRID = 8  # the detection targets' cells per side: 8 px each
CHUNK = 128  # clips pasted at a time: bounds the index memory


@dataclass
class MovingMNISTBatch:
    """``N`` clips of ``T`` frames ``S x S``, ``K`` digits each, and where every digit is, in
    pixel units (pixel ``i`` covers ``[i, i + 1)``; MNIST digits are not centred in their patch)."""

    clips: torch.Tensor  # uint8 (N, T, 1, S, S)
    centres: torch.Tensor  # float32 (N, T, K, 2): (x, y) centre of the ink box
    boxes: torch.Tensor  # int64 (N, T, K, 4): tight box (x0, y0, x1, y1) of the ink, ends excluded
    offsets: torch.Tensor  # int64 (N, T, K, 2): (x, y) top-left corner of the pasted patch
    velocities: torch.Tensor  # float32 (N, T, K, 2): velocity leaving frame t, before a bounce
    digit_ids: torch.Tensor  # int64 (N, K): which row of digits each digit is


def split_digits(digits, n_train: int = 8000) -> tuple[torch.Tensor, torch.Tensor]:
    """Digits ``(N, ...)`` -> ``n_train`` training and ``N - n_train`` held-out digits, by a
    permutation seeded with 0 (the MNIST test file's halves come from different writers)."""
    order = torch.randperm(len(digits), generator=as_generator(0))
    return digits[order[:n_train]], digits[order[n_train:]]


def ink_boxes(digits: torch.Tensor) -> torch.Tensor:
    """Tight box ``(x0, y0, x1, y1)`` around each digit's ink, in its own patch, ends exclusive:
    ``(N, H, W)`` -> int64 ``(N, 4)``. A blank digit gets the whole patch ``(0, 0, W, H)``."""
    ink, boxes = digits > 0, []
    for any_ink in (ink.any(dim=1), ink.any(dim=2)):  # (N, W) columns, then (N, H) rows
        # argmax gives the first True, or 0 if there is none: a blank digit spans the patch
        first = any_ink.int().argmax(dim=1)
        boxes.append((first, any_ink.shape[1] - any_ink.flip(1).int().argmax(dim=1)))
    (x0, x1), (y0, y1) = boxes
    return torch.stack([x0, y0, x1, y1], dim=1).long()


def bounce_trajectories(start: torch.Tensor, velocity: torch.Tensor, n_frames: int,
                        limit: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Points moving in straight lines inside ``[0, limit]``, reflected at the edges (a step
    crosses at most one edge per axis, as ``|velocity| <= limit``): ``start``, ``velocity``
    ``(..., 2)`` -> ``positions``, ``velocities``, each ``(n_frames, ..., 2)``."""
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


def paste_clips(digits: torch.Tensor, digit_ids: torch.Tensor,
                offsets: torch.Tensor) -> torch.Tensor:
    """uint8 clips ``(N, T, 1, 64, 64)``: digit ``digit_ids[n, k]`` ``(N, K)`` of ``digits``
    ``(D, h, w)`` with its top-left corner at ``offsets[n, t, k]`` ``(N, T, K, 2)`` ``(x, y)``,
    overlaps combined by maximum (``scatter_reduce`` at flat index ``(y + i) * 64 + x + j``)."""
    (n_clips, n_frames, n_digits, _), (h, w) = offsets.shape, digits.shape[1:]
    clips = torch.zeros(n_clips, n_frames, 1, FRAME_SIZE, FRAME_SIZE, dtype=torch.uint8)
    rows, cols = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    pixel = (rows * FRAME_SIZE + cols).reshape(1, 1, h * w)
    for lo in range(0, n_clips, CHUNK):
        hi = min(lo + CHUNK, n_clips)
        patches = digits[digit_ids[lo:hi]].unsqueeze(1).expand(-1, n_frames, -1, -1, -1)
        corner = offsets[lo:hi, ..., 1] * FRAME_SIZE + offsets[lo:hi, ..., 0]  # (n, T, K)
        index = (corner.reshape(-1, n_digits, 1) + pixel).reshape(-1, n_digits * h * w)
        flat = clips[lo:hi].view(-1, FRAME_SIZE * FRAME_SIZE)  # a view: the scatter writes clips
        flat.scatter_reduce_(1, index, patches.reshape(-1, n_digits * h * w), reduce="amax")
    return clips


def generate_moving_mnist(digits, n_clips: int, n_frames: int = 10, n_digits: int = 2,
                          speed: float = DEFAULT_SPEED,
                          seed: int | torch.Generator = 0) -> MovingMNISTBatch:
    """``n_clips`` clips of ``n_frames`` frames, each showing ``n_digits`` of ``digits``
    (uint8 ``(D, 1, h, w)`` or ``(D, h, w)``, drawn with replacement) moving at ``speed``
    px/frame; ``seed``: an int or a ``torch.Generator``."""
    digits = torch.as_tensor(digits)  # numpy digits too
    digits = digits[:, 0] if digits.ndim == 4 and digits.shape[1] == 1 else digits  # (D, h, h)
    if digits.ndim != 3 or len(digits) == 0 or not digits.shape[1] == digits.shape[2] <= 64:
        raise ValueError(f"digits must be square, (N, 1, H, W) or (N, H, W) with N >= 1 and H "
                         f"<= 64, got {tuple(digits.shape)}; pass the images from load_mnist")
    if digits.dtype != torch.uint8:
        raise TypeError(f"digits must be uint8 in 0..255, got {digits.dtype}; convert floats "
                        "in [0, 1] with (x * 255).round().to(torch.uint8), and 0..255 values "
                        "with x.round().to(torch.uint8)")
    limit = float(FRAME_SIZE - digits.shape[1])  # the free range of a digit's top-left corner
    if not 0 <= speed <= limit:  # faster, a step could cross both edges of an axis
        raise ValueError(f"speed must be in [0, {limit}] px/frame (the free range), got {speed}")
    generator = as_generator(seed)
    digit_ids = torch.randint(len(digits), (n_clips, n_digits), generator=generator)
    start = torch.rand(n_clips, n_digits, 2, generator=generator) * limit  # top-left corners
    angle = torch.rand(n_clips, n_digits, generator=generator) * (2 * math.pi)
    velocity = speed * torch.stack([angle.cos(), angle.sin()], dim=-1)
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
    """Detection targets, the cells of a ``GRID x GRID`` (8 x 8) tiling that hold a digit centre:
    ``centres`` ``(..., K, 2)``, ``(x, y)`` pixels in a 64 x 64 frame -> float32 ``(..., GRID,
    GRID)`` of 0/1, indexed ``[y cell, x cell]``."""
    cell = torch.div(centres, FRAME_SIZE / GRID, rounding_mode="floor").long().clamp(0, GRID - 1)
    flat = cell[..., 1] * GRID + cell[..., 0]  # (..., K)
    target = torch.zeros(*flat.shape[:-1], GRID * GRID, device=centres.device)
    target.scatter_(-1, flat, 1.0)
    return target.view(*flat.shape[:-1], GRID, GRID)
