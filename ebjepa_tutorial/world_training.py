"""Training and checking the Two Rooms world model (notebook 05; its checkpoint serves 06).

Data: offline trajectories of the paper's data policy, generated once as
positions and actions (cheap) and rendered to frames batch by batch. Each
training batch is ``batch_size`` random trajectories of ``17`` frames.

Shipped checkpoint: ``python -m ebjepa_tutorial.world_training --out PATH``
trains the class-scale model and writes it (see :func:`main`).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import torch

from .envs import generate_trajectories
from .envs.trajectories import Trajectories
from .models.world import WORLD_CONFIGS, WorldConfig, WorldModel
from .probe import encode_trajectories, fit_position_probe, mean_baseline_px, probe_error_px
from .train import (
    History,
    checkpoint_paths,
    fit,
    load_checkpoint,
    load_or_train,
    resume,
    save_checkpoint,
)
from .utils import get_device
from .world_losses import WorldLossCoeffs, world_model_loss


@dataclass(frozen=True)
class WorldTrainConfig:
    """One training run of the world model. Defaults: the class scale."""

    model: WorldConfig = field(default_factory=lambda: WORLD_CONFIGS["class"])
    coeffs: WorldLossCoeffs = field(default_factory=WorldLossCoeffs)  # the paper's weights
    n_trajectories: int = 20_000  # offline data set (the paper: ~1.2 million windows)
    batch_size: int = 64  # trajectories of 17 frames per step (the paper: 384)
    steps: int = 1000  # ~10 minutes on 2 CPU cores
    lr: float = 1e-3  # AdamW, as in the paper
    weight_decay: float = 1e-5
    rollout_steps: int = 8  # K, the prediction horizon of the loss
    # the last decay_steps steps lower the learning rate linearly towards 0 (0: constant, as
    # every shipped run). Measured once, on the long run of checkpoints/README.md: annealing
    # its steps 5,000-6,000 did not plan better than the constant rate (13 vs 15 of 20).
    decay_steps: int = 0
    seed: int = 0

    def __post_init__(self):
        if not 0 <= self.decay_steps <= self.steps:
            raise ValueError(f"decay_steps must be in 0..steps={self.steps}, "
                             f"got {self.decay_steps}")


def make_data(config: WorldTrainConfig) -> Trajectories:
    """The offline training trajectories of ``config`` (seeded by ``config.seed``)."""
    return generate_trajectories(config.n_trajectories, seed=config.seed)


def new_model(config: WorldTrainConfig, data: Trajectories) -> WorldModel:
    """A fresh model whose input standardisation is fitted on 256 of the trajectories."""
    torch.manual_seed(config.seed)
    model = WorldModel(config.model)
    return model.fit_input_stats(data.frames(slice(0, 256)))


def learning_rate_decay(optimizer, config: WorldTrainConfig):
    """The schedule of ``config``: the base rate, then a linear decay over the last
    ``decay_steps`` steps (step ``s`` uses ``min(1, (steps - s) / decay_steps)`` times the
    base rate, so the last step uses ``1 / decay_steps`` of it). ``None`` when there is none.
    """
    if config.decay_steps == 0:
        return None
    return torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda step: min(1.0, (config.steps - step) / config.decay_steps))


def train_world_model(
    config: WorldTrainConfig,
    data: Trajectories | None = None,
    checkpoint: str | Path | None = None,
    progress: bool = True,
    device: torch.device | str | None = None,
) -> tuple[WorldModel, History]:
    """Train a world model on ``data`` (default :func:`make_data`); resume from ``checkpoint``.

    Batch ``step`` is drawn from a generator seeded by ``(seed, step)``, so a
    resumed run sees the same batches as an uninterrupted one. ``device``
    defaults to the best available (cuda, mps, cpu).
    """
    data = make_data(config) if data is None else data
    device = get_device(device)
    model = new_model(config, data).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr,
                                  weight_decay=config.weight_decay)
    scheduler = learning_rate_decay(optimizer, config)
    start, history = (0, History())
    if checkpoint is not None:
        start, history = resume(checkpoint, model, optimizer, scheduler, config_dict(config))
    buffer = torch.empty(config.batch_size, data.positions.shape[1], 2, 65, 65)

    def batch(step: int):
        generator = torch.Generator().manual_seed(config.seed * 1_000_003 + step)
        index = torch.randint(0, len(data), (config.batch_size,), generator=generator)
        return data.frames(index, out=buffer).to(device), data.actions[index].to(device)

    def loss(frames_and_actions):
        frames, actions = frames_and_actions
        return world_model_loss(model, frames, actions, config.coeffs, config.rollout_steps)

    fit(model, optimizer, loss, batch, config.steps, scheduler=scheduler, history=history,
        start_step=start, checkpoint=checkpoint, checkpoint_every=250, log_every=10,
        desc="world model", progress=progress, config=config_dict(config))
    model.eval()
    return model, history


def train_or_load(config: WorldTrainConfig, name: str) -> tuple[WorldModel, History]:
    """The model of ``config``: loaded if a run with exactly this config was saved, else trained.

    Looks for ``checkpoints/<name>.pt`` (shipped with the course), then
    ``data/cache/checkpoints/<name>.pt``; otherwise trains (resumable from
    ``<name>.partial`` in the cache) and saves. Returns ``(model in eval mode, history)``.
    """
    data = make_data(config)
    model = new_model(config, data)
    cache_path, shipped = checkpoint_paths(name)
    partial = cache_path.with_suffix(".partial")

    def train() -> History:
        trained, history = train_world_model(config, data, checkpoint=partial)
        model.load_state_dict(trained.state_dict())
        partial.unlink()  # finished: the saved model replaces it
        return history

    history = load_or_train(cache_path, model, train, config_dict(config), shipped)
    return model.eval(), history


def load_world_model(path: str | Path, config: WorldConfig | None = None) -> WorldModel:
    """The trained model saved at ``path`` by :func:`main` (or by any ``{"model": state_dict}``).

    With ``config``, the checkpoint must have been trained with exactly that
    architecture; a mismatch raises a ``ValueError`` naming each difference.
    Returns the model in eval mode, on the CPU.
    """
    state = load_checkpoint(path)
    weights = state.get("model") if isinstance(state, dict) else None
    if not isinstance(weights, dict) or "_extra_state" not in weights:
        raise ValueError(f"{path} holds no world model (expected a file written by "
                         "python -m ebjepa_tutorial.world_training --out PATH)")
    if config is None:
        return WorldModel.from_state_dict(weights).eval()
    model = WorldModel(config)
    model.load_state_dict(weights)
    return model.eval()


def probe_report(model: WorldModel, n_fit: int = 1000, n_test: int = 300, seed: int = 12345):
    """Position-probe error (px) of frozen latents on held-out trajectories, with baselines.

    A linear probe is fitted on every frame of ``n_fit`` fresh trajectories
    and scored on ``n_test`` others (seeds unseen in training). The baseline
    always answers the mean position.
    """
    fit_trajectories = generate_trajectories(n_fit, seed=seed)
    test_trajectories = generate_trajectories(n_test, seed=seed + 1)
    z_fit, xy_fit = encode_trajectories(model, fit_trajectories)
    z_test, xy_test = encode_trajectories(model, test_trajectories)
    probe = fit_position_probe(z_fit, xy_fit)
    return {"probe_px": probe_error_px(probe, z_test, xy_test),
            "baseline_px": mean_baseline_px(xy_fit, xy_test), "probe": probe}


ABLATABLE_TERMS = ("variance", "covariance", "temporal", "inverse_dynamics")
ABLATION_SUFFIXES = {"variance": "no_variance", "covariance": "no_covariance",
                     "temporal": "no_temporal", "inverse_dynamics": "no_idm"}  # file names


def ablation_config(config: WorldTrainConfig, *without: str) -> WorldTrainConfig:
    """``config`` with the coefficients of the terms in ``without`` set to 0 (paper, Table 4)."""
    unknown = set(without) - set(ABLATABLE_TERMS)
    if unknown:
        raise ValueError(f"unknown loss terms {sorted(unknown)}; choose from {ABLATABLE_TERMS}")
    return replace(config, coeffs=replace(config.coeffs, **{term: 0.0 for term in without}))


def with_coeffs(config: WorldTrainConfig, pairs: list[str]) -> WorldTrainConfig:
    """``config`` with loss weights set from ``"name=value"`` strings, e.g. ``["covariance=1"]``."""
    names = [f.name for f in fields(WorldLossCoeffs)]
    values = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep or name not in names:
            raise ValueError(f"--coeff wants name=value with a name from {names}, got {pair!r}")
        try:
            values[name] = float(value)
        except ValueError:
            raise ValueError(f"--coeff {pair!r}: {value!r} is not a number") from None
        if not math.isfinite(values[name]) or values[name] < 0:
            raise ValueError(f"--coeff {pair!r}: a loss weight must be finite and >= 0")
    return replace(config, coeffs=replace(config.coeffs, **values))


def config_dict(config: WorldTrainConfig) -> dict:
    """A plain dict of the config (stored in checkpoints to recognise a matching run).

    ``decay_steps`` is left out when it is 0: the runs saved before it existed
    (the shipped checkpoints among them) had a constant learning rate.
    """
    stored = asdict(config)
    if stored["decay_steps"] == 0:
        del stored["decay_steps"]
    return stored


def main(argv: list[str] | None = None) -> None:
    """Train a world model at a scale and save it: the documented command for the checkpoint."""
    parser = argparse.ArgumentParser(description="Train the Two Rooms world model.")
    parser.add_argument("--out", required=True, help="where to write the trained model")
    parser.add_argument("--steps", type=int, default=WorldTrainConfig.steps)
    parser.add_argument("--trajectories", type=int, default=WorldTrainConfig.n_trajectories,
                        help="size of the offline data set (the paper: 100,000)")
    parser.add_argument("--decay-steps", type=int, default=0,
                        help="lower the learning rate linearly to 0 over the last N steps")
    parser.add_argument("--without", action="append", default=[], choices=ABLATABLE_TERMS,
                        help="an ablation: set this term's coefficient to 0 (repeatable)")
    parser.add_argument("--no-inverse-dynamics", action="store_true",
                        help="the same as --without inverse_dynamics")
    parser.add_argument("--coeff", action="append", default=[], metavar="NAME=VALUE",
                        help="set one loss weight, e.g. covariance=1 (repeatable)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    without = args.without + (["inverse_dynamics"] if args.no_inverse_dynamics else [])
    try:
        config = with_coeffs(WorldTrainConfig(steps=args.steps, seed=args.seed,
                                              n_trajectories=args.trajectories,
                                              decay_steps=args.decay_steps), args.coeff)
    except ValueError as error:
        parser.error(str(error))  # a usage message, not a traceback
    config = ablation_config(config, *without)
    partial = Path(args.out).with_suffix(".partial")  # resumable while training
    model, history = train_world_model(config, checkpoint=partial)
    report = probe_report(model)
    save_checkpoint(args.out, model=model.state_dict(), history=dict(history),
                    config=config_dict(config), probe_px=report["probe_px"])
    partial.unlink()
    print(f"saved {args.out}: probe error {report['probe_px']:.2f} px "
          f"(mean-position baseline {report['baseline_px']:.2f} px)")


if __name__ == "__main__":
    main()
