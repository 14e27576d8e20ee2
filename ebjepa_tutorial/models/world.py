"""The action-conditioned world model of notebooks 04-05: encoder, predictor, inverse dynamics.

``encode`` maps Two Rooms frames ``(B, 2, 65, 65)`` (or ``(B, T, 2, 65, 65)``)
to latents ``(B, D)`` (or ``(B, T, D)``); ``predict(z, a)`` takes one step
``(B, D), (B, 2) -> (B, D)``; ``rollout(z0, actions)`` unrolls the predictor
on its own outputs, ``(B, D), (B, H, 2) -> (B, H, D)``: the one call a planner
makes to imagine ``B`` futures of ``H`` steps.

- Input scaling. The dot (channel 0) covers ~0.3% of the pixels, the walls
  (channel 1) ~10%, so on raw inputs the walls dominate every activation and a
  small encoder can settle on the static layout and lose the dot (the results
  page shows such a collapse). Each channel is standardised by its own mean
  and std, computed from data with :meth:`WorldModel.fit_input_stats` and kept
  as buffers, so every checkpoint carries them.
- Encoder: IMPALA stacks (conv 3x3 -> max-pool 3x3 stride 2 -> residual
  blocks ReLU-conv-ReLU-conv), ReLU, flatten, linear to ``D``, LayerNorm.
  ``input_size < 65`` first average-pools the frame (33 halves the
  side: ~4x cheaper, the Gaussian dot stays visible).
- Predictor: a ``GRUCell`` whose hidden state is the latent; the step is
  residual, ``z' = z + W GRU(e(a), z)`` with ``W`` zero at initialisation, so
  an untrained predictor is the identity (one step moves the dot <= 1.8 px).
  ``predictor="mlp"`` swaps it for ``z' = z + W MLP([z, e(a)])`` with two
  hidden layers: sharper where the wall ends beside the door, refitted on a
  trained model's frozen latents (:func:`~ebjepa_tutorial.training.world.refit_predictor`).
- Inverse dynamics: an MLP on ``[z_t, z_{t+1}]`` -> the action ``(2,)``.

The architecture lives in :class:`WorldConfig`, which is saved in every
``state_dict``; loading weights into a model built differently names the
mismatch (e.g. "latent_dim: the checkpoint has 64, this model has 32").
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import torch
import torch.nn.functional as F
from torch import nn

from ..envs.two_rooms import IMAGE_SIZE

PREDICTORS = ("gru", "mlp")  # the kinds of WorldConfig.predictor
CHANNELS = 2  # a Two Rooms frame's channels: the dot and the walls, (2, 65, 65)


@dataclass(frozen=True)
class WorldConfig:
    """Sizes of a :class:`WorldModel`. The default is the class-scale model."""

    widths: tuple[int, ...] = (16, 32, 32)  # channels of each IMPALA stack
    blocks: int = 1  # residual blocks per stack (IMPALA and the paper: 2)
    input_size: int = 33  # frames are average-pooled to this side (65: full resolution)
    latent_dim: int = 64  # D
    action_dim: int = 2
    action_embed_dim: int = 32  # width of the action MLP's output
    predictor: str = "gru"  # "gru" (GRUPredictor) or "mlp" (MLPPredictor)
    predictor_hidden: int = 128  # width of the MLP predictor's two hidden layers
    idm_hidden: int = 128  # hidden width of the inverse-dynamics MLP

    def __post_init__(self):
        object.__setattr__(self, "widths", tuple(int(w) for w in self.widths))
        if not self.widths or min(self.widths) < 1 or self.blocks < 0:
            raise ValueError(f"need >= 1 positive widths and blocks >= 0, got {self}")
        if not 1 <= self.input_size <= IMAGE_SIZE:
            raise ValueError(f"input_size must be in 1..{IMAGE_SIZE}, got {self.input_size}")
        if self.latent_dim < 2:
            raise ValueError(f"latent_dim must be >= 2, got {self.latent_dim}")
        if self.predictor not in PREDICTORS or self.predictor_hidden < 1:
            raise ValueError(f"predictor must be one of {PREDICTORS} with predictor_hidden >= 1, "
                             f"got {self.predictor!r} and {self.predictor_hidden}")


# ``full``: the paper's IMPALA widths 16-32-32, two blocks, full resolution. The
# paper trains it with batch 384, 12 epochs of 100,000 trajectories, AdamW lr
# 1e-3, weight decay 1e-5 (loss weights: ebjepa_tutorial.losses.world). Its
# latent is a 32-channel feature map; ours is a vector (latent_dim is our choice).
# ``class`` is sized so that training and planning fit a class period on a CPU.
WORLD_CONFIGS = {
    "ci": WorldConfig(widths=(8, 16, 16), blocks=1, latent_dim=32),
    "class": WorldConfig(),
    "full": WorldConfig(blocks=2, input_size=65, latent_dim=256, idm_hidden=256),
}


class ResidualBlock(nn.Module):
    """IMPALA residual block ``x + conv(relu(conv(relu(x))))``: ``(B, C, H, W)`` kept."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class ImpalaStack(nn.Sequential):
    """Conv 3x3, max-pool 3x3 stride 2, ``blocks`` residual blocks: side ``s -> ceil(s/2)``."""

    def __init__(self, in_channels: int, out_channels: int, blocks: int):
        super().__init__(
            nn.Conv2d(in_channels, out_channels, 3, padding=1),
            nn.MaxPool2d(3, stride=2, padding=1),
            *[ResidualBlock(out_channels) for _ in range(blocks)],
        )


class ImpalaEncoder(nn.Module):
    """Standardised frames ``(B, C, s, s)`` -> latents ``(B, latent_dim)``."""

    def __init__(self, config: WorldConfig):
        super().__init__()
        stacks, channels, side = [], CHANNELS, config.input_size
        for width in config.widths:
            stacks.append(ImpalaStack(channels, width, config.blocks))
            channels, side = width, (side + 1) // 2
        self.stacks = nn.Sequential(*stacks)
        self.linear = nn.Linear(channels * side * side, config.latent_dim)
        self.norm = nn.LayerNorm(config.latent_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm(self.linear(F.relu(self.stacks(x)).flatten(1)))


class GRUPredictor(nn.Module):
    """One step ``z' = z + W GRUCell(e, z)``: latents ``(N, D)``, action embeddings ``(N, E)``."""

    def __init__(self, latent_dim: int, action_embed_dim: int):
        super().__init__()
        self.cell = nn.GRUCell(action_embed_dim, latent_dim)
        self.out = nn.Linear(latent_dim, latent_dim)
        nn.init.zeros_(self.out.weight)  # start as the identity map
        nn.init.zeros_(self.out.bias)

    def forward(self, z: torch.Tensor, action_embedding: torch.Tensor) -> torch.Tensor:
        return z + self.out(self.cell(action_embedding, z))


class MLPPredictor(nn.Module):
    """One step ``z' = z + W MLP([z, e])``: two GELU layers of ``hidden`` on latent and action.

    Latents ``(N, D)``, action embeddings ``(N, E)`` -> ``(N, D)``. ``W`` starts
    at zero, as :class:`GRUPredictor`'s, so an untrained step is the identity.
    """

    def __init__(self, latent_dim: int, action_embed_dim: int, hidden: int):
        super().__init__()
        self.body = nn.Sequential(nn.Linear(latent_dim + action_embed_dim, hidden), nn.GELU(),
                                  nn.Linear(hidden, hidden), nn.GELU())
        self.out = nn.Linear(hidden, latent_dim)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, z: torch.Tensor, action_embedding: torch.Tensor) -> torch.Tensor:
        return z + self.out(self.body(torch.cat([z, action_embedding], dim=-1)))


def make_predictor(config: WorldConfig) -> nn.Module:
    """The one-step predictor ``config.predictor`` names."""
    if config.predictor == "mlp":
        return MLPPredictor(config.latent_dim, config.action_embed_dim, config.predictor_hidden)
    return GRUPredictor(config.latent_dim, config.action_embed_dim)


def mlp(in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    """Linear-ReLU-Linear: ``(N, in_dim) -> (N, out_dim)``."""
    return nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, out_dim))


class WorldModel(nn.Module):
    """Encoder, action encoder, predictor (GRU or MLP) and inverse-dynamics head."""

    def __init__(self, config: WorldConfig | None = None):
        super().__init__()
        self.config = config = WorldConfig() if config is None else config
        self.register_buffer("input_mean", torch.zeros(CHANNELS))
        self.register_buffer("input_std", torch.ones(CHANNELS))
        self.register_buffer("input_stats_fitted", torch.tensor(False))
        self.encoder = ImpalaEncoder(config)
        self.action_encoder = mlp(config.action_dim, config.action_embed_dim,
                                  config.action_embed_dim)
        self.predictor = make_predictor(config)
        self.inverse_dynamics = mlp(2 * config.latent_dim, config.idm_hidden, config.action_dim)

    @property
    def latent_dim(self) -> int:
        return self.config.latent_dim

    # -- input scaling -------------------------------------------------------------------
    @torch.no_grad()
    def fit_input_stats(self, frames: torch.Tensor) -> WorldModel:
        """Set the per-channel mean and std from ``frames`` ``(N, [T,] C, 65, 65)``; returns self.

        A few hundred trajectories are plenty (the statistics barely move).
        """
        frames = self._check_frames(frames)
        channels = frames.movedim(-3, 0).reshape(CHANNELS, -1).float()
        self.input_mean.copy_(channels.mean(dim=1))
        self.input_std.copy_(channels.std(dim=1).clamp_min(1e-6))
        self.input_stats_fitted.fill_(True)
        return self

    def normalize(self, frames: torch.Tensor) -> torch.Tensor:
        """Pool to ``input_size``, standardise each channel: ``(N, C, 65, 65) -> (N, C, s, s)``."""
        if self.config.input_size != IMAGE_SIZE:
            # Averaging first is cheaper and equal: the standardisation is affine per channel.
            frames = F.adaptive_avg_pool2d(frames, self.config.input_size)
        return (frames - self.input_mean[:, None, None]) / self.input_std[:, None, None]

    # -- the planner's interface ---------------------------------------------------------
    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """Frames ``(B, C, 65, 65)`` -> ``(B, D)``, or ``(B, T, C, 65, 65)`` -> ``(B, T, D)``."""
        frames = self._check_frames(frames)
        z = self.encoder(self.normalize(frames.flatten(0, frames.ndim - 4)))
        return z.view(*frames.shape[:-3], -1)

    def predict(self, z: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """One step: latents ``(B, D)`` and actions ``(B, 2)`` -> next latents ``(B, D)``."""
        self._check_latents(z)
        self._check_actions(actions, (z.shape[0], self.config.action_dim))
        return self.predictor(z, self.action_encoder(actions))  # actions embedded: (B, E)

    def rollout(self, z0: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Unroll ``H`` steps on the model's own predictions: ``(B, D), (B, H, 2) -> (B, H, D)``.

        Output ``[:, k]`` is the latent after actions ``0..k``. All action
        embeddings are computed in one batch; the loop over ``H`` is the only
        sequential part.
        """
        self._check_latents(z0, "z0")
        steps = actions.shape[1] if isinstance(actions, torch.Tensor) and actions.ndim == 3 else 0
        self._check_actions(actions, (z0.shape[0], steps or "H", self.config.action_dim))
        embeddings = self.action_encoder(actions)  # (B, H, E), E = action_embed_dim
        z, out = z0, []
        for k in range(actions.shape[1]):
            z = self.predictor(z, embeddings[:, k])
            out.append(z)
        return torch.stack(out, dim=1)

    def predict_actions(self, z: torch.Tensor, z_next: torch.Tensor) -> torch.Tensor:
        """Inverse dynamics: latents ``(..., D)`` at t and t+1 -> the action ``(..., 2)``."""
        return self.inverse_dynamics(torch.cat([z, z_next], dim=-1))

    # -- checks --------------------------------------------------------------------------
    def _check_frames(self, frames) -> torch.Tensor:
        c, s = CHANNELS, IMAGE_SIZE
        if not isinstance(frames, torch.Tensor) or frames.ndim not in (4, 5):
            got = tuple(frames.shape) if isinstance(frames, torch.Tensor) else type(frames).__name__
            raise ValueError(
                f"frames must be (batch, {c}, {s}, {s}) or (batch, time, {c}, {s}, {s}), got {got}"
            )
        if frames.shape[-3:] != (c, s, s):
            raise ValueError(
                f"each frame must be ({c}, {s}, {s}) (dot and wall channels, {s}x{s} pixels), got "
                f"{tuple(frames.shape[-3:])} in frames of shape {tuple(frames.shape)}; render "
                "them with ebjepa_tutorial.envs (Trajectories.frames) and keep channels first"
            )
        if not frames.is_floating_point():
            raise TypeError(f"frames must be float in [0, 1], got {frames.dtype}")
        return frames

    def _check_latents(self, z, name: str = "z") -> None:
        d = self.config.latent_dim
        if not isinstance(z, torch.Tensor) or z.ndim != 2 or z.shape[1] != d:
            got = tuple(z.shape) if isinstance(z, torch.Tensor) else type(z).__name__
            raise ValueError(f"{name} must be latents of shape (batch, {d}), got {got}")

    @staticmethod
    def _check_actions(actions, shape: tuple) -> None:
        if not isinstance(actions, torch.Tensor) or tuple(actions.shape) != shape:
            got = tuple(actions.shape) if isinstance(actions, torch.Tensor) else type(actions)
            raise ValueError(
                f"actions must have shape {shape} (batch, [steps,] dx-dy), got {got}; "
                "the batch must match the latents'"
            )
        if not torch.isfinite(actions).all():
            raise ValueError("actions contain NaN or infinite values; check where they come from")

    # -- checkpoints: the config travels inside every state_dict ---------------------------
    def get_extra_state(self) -> dict:
        return {"config": asdict(self.config)}

    def set_extra_state(self, state: dict) -> None:
        check_compatible(state["config"], self.config)

    @classmethod
    def from_state_dict(cls, state_dict: dict) -> WorldModel:
        """Build a model with the config saved in ``state_dict`` and load the weights.

        A saved field that the config no longer has (a file's frame size and channels, now
        :data:`CHANNELS` and the world's ``IMAGE_SIZE``; its ``layer_norm``, always on) is
        left out.
        """
        if "_extra_state" not in state_dict:
            raise KeyError("this state_dict has no saved WorldConfig (not from a WorldModel)")
        saved, known = state_dict["_extra_state"]["config"], {f.name for f in fields(WorldConfig)}
        model = cls(WorldConfig(**{name: v for name, v in saved.items() if name in known}))
        model.load_state_dict(state_dict)
        return model


def check_compatible(saved: dict, config: WorldConfig) -> None:
    """Raise a clear error if a checkpoint's config ``saved`` differs from ``config``.

    A field the checkpoint does not name (it predates the field) counts as its default.
    """
    differences = [
        f"{f.name}: the checkpoint has {saved.get(f.name, f.default)!r}, this model has "
        f"{getattr(config, f.name)!r}"
        for f in fields(config)
        if tuple_if_list(saved.get(f.name, f.default)) != getattr(config, f.name)
    ]
    if differences:
        raise ValueError(
            "this checkpoint was trained with another world model configuration ("
            + "; ".join(differences) + "). Build the model with WorldConfig(**saved config), "
            "or use WorldModel.from_state_dict(state_dict)."
        )


def tuple_if_list(value):
    return tuple(value) if isinstance(value, list) else value


@torch.no_grad()
def encode_trajectories(model, trajectories, batch_size: int = 64):
    """Latents ``(N*(T+1), D)`` and positions ``(N*(T+1), 2)`` of every frame.

    ``trajectories``: :class:`~ebjepa_tutorial.envs.Trajectories`; frames are
    rendered ``batch_size`` trajectories at a time and encoded without gradients.
    """
    chunks, device = [], next(model.parameters()).device
    for start in range(0, len(trajectories), batch_size):
        frames = trajectories.frames(slice(start, start + batch_size)).to(device)
        chunks.append(model.encode(frames).flatten(0, 1).cpu())
    return torch.cat(chunks), trajectories.positions.reshape(-1, 2)


def trajectory_latents(model, trajectories) -> torch.Tensor:
    """Every frame's latent, trajectory by trajectory: ``(N, T+1, D)``, without gradients
    (200 trajectories rendered at a time)."""
    latents = encode_trajectories(model, trajectories, 200)[0]
    return latents.view(len(trajectories), -1, latents.shape[-1])
