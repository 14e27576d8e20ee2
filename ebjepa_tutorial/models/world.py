"""The world model of notebooks 05-07: an IMPALA encoder, a residual predictor ``z' = z + W f(z,
e(a))`` (``W`` zero at first), an inverse-dynamics head; its config travels in its state_dict."""

from dataclasses import asdict, dataclass, fields

import torch
import torch.nn.functional as F
from torch import nn

from ..envs.two_rooms import IMAGE_SIZE

CHANNELS = 2  # a Two Rooms frame's channels: the dot and the walls, (2, 65, 65)


@dataclass(frozen=True)
class WorldConfig:
    """Sizes of a :class:`WorldModel`. The default: the class-scale sizes (``course_recipe``
    swaps in the MLP predictor)."""

    widths: tuple[int, ...] = (16, 32, 32)  # channels of each IMPALA stack
    blocks: int = 1  # residual blocks per stack (IMPALA and the paper: 2)
    input_size: int = 33  # frames are average-pooled to this side (65: full resolution)
    latent_dim: int = 64  # D
    action_dim: int = 2
    action_embed_dim: int = 32  # width of the action MLP's output
    predictor: str = "gru"  # "gru" or "mlp" (see Predictor)
    predictor_hidden: int = 128  # width of the MLP predictor's two hidden layers
    idm_hidden: int = 128  # hidden width of the inverse-dynamics MLP

    def __post_init__(self):  # a misspelt predictor would silently build the MLP
        if self.predictor not in ("gru", "mlp"):
            raise ValueError(f"WorldConfig.predictor must be 'gru' or 'mlp', got "
                             f"{self.predictor!r}")


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


class ImpalaEncoder(nn.Module):
    """Standardised frames ``(B, C, s, s)`` -> latents ``(B, latent_dim)``."""

    def __init__(self, config: WorldConfig):
        super().__init__()
        stacks, channels, side = [], CHANNELS, config.input_size
        for width in config.widths:  # each stack: side s -> ceil(s / 2)
            stacks.append(nn.Sequential(nn.Conv2d(channels, width, 3, padding=1),
                                        nn.MaxPool2d(3, stride=2, padding=1),
                                        *[ResidualBlock(width) for _ in range(config.blocks)]))
            channels, side = width, (side + 1) // 2
        self.stacks = nn.Sequential(*stacks)
        self.linear = nn.Linear(channels * side * side, config.latent_dim)
        self.norm = nn.LayerNorm(config.latent_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm(self.linear(F.relu(self.stacks(x)).flatten(1)))


class Predictor(nn.Module):
    """``z' = z + W GRUCell(e, z)`` (``"gru"``) or ``z + W MLP([z, e])`` (``"mlp"``, two GELU
    layers): latents ``(N, D)``, action embeddings ``(N, E)`` -> ``(N, D)``."""

    def __init__(self, config: WorldConfig):
        super().__init__()
        d, e, hidden = config.latent_dim, config.action_embed_dim, config.predictor_hidden
        self.gru = config.predictor == "gru"
        if self.gru:
            self.cell = nn.GRUCell(e, d)
        else:
            self.body = nn.Sequential(nn.Linear(d + e, hidden), nn.GELU(),
                                      nn.Linear(hidden, hidden), nn.GELU())
        self.out = nn.Linear(d if self.gru else hidden, d)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, z: torch.Tensor, action_embedding: torch.Tensor) -> torch.Tensor:
        if self.gru:
            return z + self.out(self.cell(action_embedding, z))
        return z + self.out(self.body(torch.cat([z, action_embedding], dim=-1)))


class WorldModel(nn.Module):
    """Encoder, predictor, and two Linear-ReLU-Linear MLPs: action encoder, inverse dynamics."""

    def __init__(self, config: WorldConfig | None = None):
        super().__init__()
        self.config = c = WorldConfig() if config is None else config
        self.latent_dim = c.latent_dim
        self.register_buffer("input_mean", torch.zeros(CHANNELS))
        self.register_buffer("input_std", torch.ones(CHANNELS))
        self.register_buffer("input_stats_fitted", torch.tensor(False))
        self.encoder = ImpalaEncoder(c)
        self.action_encoder = nn.Sequential(nn.Linear(c.action_dim, c.action_embed_dim), nn.ReLU(),
                                            nn.Linear(c.action_embed_dim, c.action_embed_dim))
        self.predictor = Predictor(c)
        self.inverse_dynamics = nn.Sequential(nn.Linear(2 * c.latent_dim, c.idm_hidden), nn.ReLU(),
                                              nn.Linear(c.idm_hidden, c.action_dim))

    @torch.no_grad()
    def fit_input_stats(self, frames: torch.Tensor) -> "WorldModel":
        """Set the per-channel mean and std from ``frames`` ``(N, [T,] C, 65, 65)`` (a few hundred
        trajectories: then the dot, 0.3% of the pixels, is not drowned by the walls); self."""
        channels = frames.movedim(-3, 0).reshape(CHANNELS, -1).float()
        self.input_mean.copy_(channels.mean(dim=1))
        self.input_std.copy_(channels.std(dim=1).clamp_min(1e-6))
        self.input_stats_fitted.fill_(True)
        return self

    def normalize(self, frames: torch.Tensor) -> torch.Tensor:
        """Pool to ``input_size``, standardise each channel: ``(N, C, 65, 65) -> (N, C, s, s)``."""
        if self.config.input_size != IMAGE_SIZE:  # pooling first is cheaper and equal (affine)
            frames = F.adaptive_avg_pool2d(frames, self.config.input_size)
        return (frames - self.input_mean[:, None, None]) / self.input_std[:, None, None]

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """Frames ``(B, C, 65, 65)`` -> ``(B, D)``, or ``(B, T, C, 65, 65)`` -> ``(B, T, D)``."""
        framed = frames.ndim in (4, 5) and frames.shape[-3:] == (CHANNELS, IMAGE_SIZE, IMAGE_SIZE)
        if not framed or not frames.is_floating_point():
            raise ValueError("frames must be (B, 2, 65, 65) or (B, T, 2, 65, 65) (dot and walls), "
                             "float in [0, 1] (Trajectories.frames; one frame: frames[None]); "
                             f"got {tuple(frames.shape)} {frames.dtype}")
        z = self.encoder(self.normalize(frames.flatten(0, frames.ndim - 4)))
        return z.view(*frames.shape[:-3], -1)

    def predict(self, z: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """One step: latents ``(B, D)`` and actions ``(B, 2)`` -> next latents ``(B, D)``."""
        self._check_inputs(z, actions)
        return self.predictor(z, self.action_encoder(actions))  # actions embedded: (B, E)

    def rollout(self, z0: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """``H`` steps on the model's own predictions: ``(B, D), (B, H, 2) -> (B, H, D)``; output
        ``[:, k]`` is the latent after actions ``0..k``."""
        self._check_inputs(z0, actions, steps=actions.shape[1] if actions.ndim == 3 else "H")
        embeddings = self.action_encoder(actions)  # (B, H, E), all steps in one batch
        z, out = z0, []
        for k in range(actions.shape[1]):
            z = self.predictor(z, embeddings[:, k])
            out.append(z)
        return torch.stack(out, dim=1)

    def predict_actions(self, z: torch.Tensor, z_next: torch.Tensor) -> torch.Tensor:
        """Inverse dynamics: latents ``(..., D)`` at t and t+1 -> the action ``(..., 2)``."""
        return self.inverse_dynamics(torch.cat([z, z_next], dim=-1))

    def _check_inputs(self, z: torch.Tensor, actions: torch.Tensor, **steps) -> None:
        if z.ndim != 2 or z.shape[1] != self.latent_dim:
            raise ValueError(f"need latents of shape (B, {self.latent_dim}), got {list(z.shape)}")
        shape = (z.shape[0], *steps.values(), self.config.action_dim)
        if tuple(actions.shape) != shape or not torch.isfinite(actions).all():
            got = tuple(actions.shape) if tuple(actions.shape) != shape else "NaN or infinity"
            raise ValueError(f"actions must have shape {shape} (batch, [steps,] dx-dy), without "
                             f"NaN or infinite values; got {got}")

    def get_extra_state(self) -> dict:
        return {"config": asdict(self.config)}

    def set_extra_state(self, state: dict) -> None:  # a clear error for another config
        saved, ours = asdict(_saved_config(state)), asdict(self.config)
        differences = [f"{name}: the checkpoint has {value!r}, this model has {ours[name]!r}"
                       for name, value in saved.items() if value != ours[name]]
        if differences:
            raise ValueError("this checkpoint's world model has another configuration ("
                             + "; ".join(differences) + "): use WorldModel.from_state_dict")

    @classmethod
    def from_state_dict(cls, state_dict: dict) -> "WorldModel":
        """A model built with the config saved in ``state_dict``, its weights loaded."""
        model = cls(_saved_config(state_dict["_extra_state"]))
        model.load_state_dict(state_dict)
        return model


def _saved_config(state: dict) -> WorldConfig:
    """The saved config; fields it lacks take their defaults, fields we dropped are left out."""
    names = {f.name for f in fields(WorldConfig)}
    return WorldConfig(**{name: v for name, v in state["config"].items() if name in names})


@torch.no_grad()
def encode_trajectories(model, trajectories, batch_size: int = 64):
    """Latents ``(N*(T+1), D)`` and positions ``(N*(T+1), 2)`` of every frame of
    :class:`~ebjepa_tutorial.envs.Trajectories`, rendered ``batch_size`` trajectories at a time."""
    chunks, device = [], next(model.parameters()).device
    for start in range(0, len(trajectories), batch_size):
        frames = trajectories.frames(slice(start, start + batch_size)).to(device)
        chunks.append(model.encode(frames).flatten(0, 1).cpu())
    return torch.cat(chunks), trajectories.positions.reshape(-1, 2)
