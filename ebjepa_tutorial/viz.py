"""Figures the notebooks draw, each on the matplotlib ``Axes`` it is given (or a new one)."""

from __future__ import annotations

import re

import matplotlib.pyplot as plt
import torch
from matplotlib.animation import FuncAnimation

from .envs.two_rooms import wall_images
from .losses.sigreg import epps_pulley


def _axes(ax):
    return plt.subplots(figsize=(4.5, 3.2))[1] if ax is None else ax


def _legend(ax, **props):
    ax.set(**props)
    ax.legend(fontsize=8)
    return ax


def grouped_bars(ax, series: list[tuple[str, list]]):
    """Grouped bars: bar ``i`` of each ``(label, heights)`` around ``x = i``, side by side."""
    width = 0.8 / len(series)
    for k, (label, heights) in enumerate(series):
        shift = (k - (len(series) - 1) / 2) * width
        ax.bar([i + shift for i in range(len(heights))], heights, width, label=label)


def plot_spectrum(eigenvalues: dict[str, torch.Tensor], ax=None, marker: str | None = "o"):
    """Covariance eigenvalues ``(D,)`` (largest first, log scale), one line per labelled run."""
    ax = _axes(ax)
    for label, values in eigenvalues.items():
        ranks = torch.arange(1, len(values) + 1)
        ax.semilogy(ranks, values.clamp_min(1e-8), marker=marker, label=label)
    return _legend(ax, xlabel="eigenvalue rank", ylabel="eigenvalue of Cov(z)")


def plot_embedding(z: torch.Tensor, labels: torch.Tensor, ax=None, title: str = ""):
    """Scatter the first two principal components of ``z`` ``(N, D)``, coloured by label."""
    ax = _axes(ax)
    centred = z.detach().cpu() - z.detach().cpu().mean(dim=0)
    xy = centred @ torch.linalg.svd(centred, full_matrices=False)[2][:2].T  # (N, 2)
    ax.scatter(xy[:, 0], xy[:, 1], c=labels, cmap="tab10", s=6, vmin=0, vmax=9)
    ax.set(title=title, xlabel="PC 1", ylabel="PC 2")
    return ax


def plot_energy_map(coords, energy, anchor, points, ax=None, title: str = ""):
    """Heat map of ``E(anchor, y)`` over a grid of ``y``, the data ``points`` ``(N, 2)`` over it."""
    ax = _axes(ax)
    half = float(coords[1] - coords[0]) / 2  # each cell centred on its grid point
    extent = [float(coords[0]) - half, float(coords[-1]) + half] * 2
    energy = torch.as_tensor(energy).numpy()  # numpy 2 warns when matplotlib converts a tensor
    image = ax.imshow(energy, origin="lower", extent=extent, cmap="viridis")
    ax.scatter(points[:, 0], points[:, 1], s=1, c="white", alpha=0.3)
    ax.scatter([anchor[0]], [anchor[1]], marker="*", s=150, c="red")
    ax.set(title=title, xticks=[], yticks=[])
    plt.colorbar(image, ax=ax, fraction=0.046)
    return ax


def two_rooms_rgb(obs: torch.Tensor):
    """A Two Rooms observation ``(2, H, W)`` (dot, walls) -> ``(H, W, 3)``: red dot, grey walls."""
    obs = obs.detach().cpu().float()
    dot, wall = obs[0, ..., None], obs[1, ..., None]
    floor = 1 - wall * (1 - torch.tensor([0.35, 0.4, 0.5]))
    return (floor * (1 - dot) + torch.tensor([0.85, 0.1, 0.1]) * dot).numpy()


# The HTML player's button icons come from a web font on a CDN: blank offline. Characters instead.
_PLAYER_ICONS = {"minus": "\u2212", "fast-backward": "\u23ee", "step-backward": "\u23f4\u23f4",
                 "play": "\u25b6", "pause": "\u23f8", "step-forward": "\u23f5\u23f5",
                 "fast-forward": "\u23ed", "plus": "+"}


def play(animation):
    """A ``matplotlib.animation.Animation`` as an HTML player that needs no network."""
    from IPython.display import HTML

    html = animation.to_jshtml(default_mode="loop")
    html = re.sub(r'<link rel="stylesheet"\s+href="https://[^"]*font-awesome[^"]*">', "", html)
    rules = "".join(f".anim-buttons .fa-{name}::before {{content: '{char}';}}"
                    for name, char in _PLAYER_ICONS.items())
    flip = ".anim-buttons .fa-flip-horizontal {display: inline-block; transform: scaleX(-1);}"
    return HTML(f"<style>.anim-buttons .fa {{font-style: normal;}} {flip} {rules}</style>{html}")


def _gray(frame: torch.Tensor):
    """One frame ``(1, H, W)`` or ``(H, W)``, uint8 or float in [0, 1] -> ``(H, W)`` array."""
    frame = frame.detach().cpu()
    frame = frame.float() / 255 if frame.dtype == torch.uint8 else frame.float()
    return frame.reshape(frame.shape[-2:]).numpy()


def animate_clips(clips: torch.Tensor, centres: torch.Tensor, grid: int):
    """Clips ``(N, T, 1, H, W)`` side by side, their digits' ``centres`` ``(N, T, K, 2)`` (x, y
    pixels) as red crosses, the ``grid x grid`` detection cells as lines: an animation."""
    n, t, size = clips.shape[0], clips.shape[1], clips.shape[-1]
    fig, axes = plt.subplots(1, n, figsize=(1.9 * n, 2.2), dpi=80, squeeze=False)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.02, top=0.85, wspace=0.05)
    images, marks = [], []
    for i, ax in enumerate(axes[0]):
        images.append(ax.imshow(_gray(clips[i, 0]), cmap="gray", vmin=0, vmax=1))
        marks.append(ax.plot([], [], "+", color="tab:red", ms=10, mew=2)[0])
        for line in torch.arange(1, grid) * size / grid - 0.5:
            ax.axhline(line, color="tab:blue", lw=0.4, alpha=0.6)
            ax.axvline(line, color="tab:blue", lw=0.4, alpha=0.6)
        ax.set(xticks=[], yticks=[])

    def draw(frame: int):
        for i in range(n):
            images[i].set_data(_gray(clips[i, frame]))
            # a pixel i covers [i, i + 1): imshow draws its centre at i
            marks[i].set_data(centres[i, frame, :, 0] - 0.5, centres[i, frame, :, 1] - 0.5)
            axes[0, i].set_title(f"clip {i}, frame {frame}", fontsize=9)
        return images + marks

    animation = FuncAnimation(fig, draw, frames=t, interval=250)
    plt.close(fig)
    return animation


def show_frame_rows(rows: dict[str, tuple[int, torch.Tensor]], n_frames: int):
    """One labelled row of frames per ``label: (first, frames)``, ``frames`` ``(n, [1,] H, W)``
    in columns ``first .. first + n - 1``. Returns the axes ``(len(rows), n_frames)``."""
    fig, axes = plt.subplots(len(rows), n_frames, figsize=(0.95 * n_frames, 0.95 * len(rows)),
                             squeeze=False)
    for row, (label, (first, frames)) in zip(axes, rows.items()):
        for t, ax in enumerate(row):
            ax.set(xticks=[], yticks=[])
            if first <= t < first + len(frames):
                ax.imshow(_gray(frames[t - first]), cmap="gray", vmin=0, vmax=1)
            else:
                ax.axis("off")
        row[0].set_ylabel(label, fontsize=8, rotation=0, ha="right", va="center")
        row[0].axis("on")
        row[0].spines[:].set_visible(first == 0)
    for t, ax in enumerate(axes[0]):
        ax.set_title(f"t={t}", fontsize=8)
    return axes


def plot_ap_curves(curves: dict[str, torch.Tensor], ax=None, spread: dict | None = None,
                   styles: dict[str, dict] | None = None):
    """Detection AP ``(H,)`` against the horizon ``k = 1 .. H`` per label; ``spread``:
    ``{label: (low, high)}`` drawn as a band; ``styles``: keyword arguments per label."""
    ax = _axes(ax)
    spread, styles = spread or {}, styles or {}
    for label, ap in curves.items():
        horizons = torch.arange(1, len(ap) + 1)
        style = {"marker": "o", "ms": 4, **styles.get(label, {})}
        line = ax.plot(horizons, ap, label=label, **style)[0]
        if label in spread:
            ax.fill_between(horizons, *spread[label], color=line.get_color(), alpha=0.2, lw=0)
    return _legend(ax, xlabel="steps ahead k", ylabel="detection AP", ylim=(0, 1))


def plot_characteristic_functions(samples: dict[str, torch.Tensor]):
    """Three panels for 1-D samples ``(N,)`` tested against N(0, 1): histograms; Re and |phi_N(t)|
    against exp(-t^2/2); ``N w(t) |phi_N(t) - phi(t)|^2`` with ``w(t) = exp(-t^2 / 2)``, whose
    area over [-3, 3] is the Epps-Pulley statistic (in the legend). Returns the axes."""
    axes = plt.subplots(1, 3, figsize=(13, 3.4))[1]
    t = torch.linspace(-3.0, 3.0, 241)
    gaussian_cf = torch.exp(-(t**2) / 2)
    grid = torch.linspace(-4, 4, 161)
    axes[0].plot(grid, torch.exp(-(grid**2) / 2) / (2 * torch.pi) ** 0.5, "k--", label="N(0, 1)")
    axes[1].plot(t, gaussian_cf, "k--", lw=2, label=r"$e^{-t^2/2}$, N(0, 1)")
    for i, (label, x) in enumerate(samples.items()):
        x = x.detach().float().cpu()
        color = f"C{i}"
        axes[0].hist(x.clamp(-4, 4), bins=48, range=(-4, 4), density=True, alpha=0.45,
                     color=color, label=label)
        xt = x[:, None] * t  # (N, T)
        real, imag = torch.cos(xt).mean(dim=0), torch.sin(xt).mean(dim=0)
        axes[1].plot(t, real, color=color, label=label)
        axes[1].plot(t, torch.sqrt(real**2 + imag**2), color=color, ls=":")
        gap = (len(x) * gaussian_cf * ((real - gaussian_cf) ** 2 + imag**2)).clamp_min(1e-4)
        axes[2].semilogy(t, gap, color=color, label=f"{label}: EP = {epps_pulley(x).item():.3g}")
        axes[2].fill_between(t, 1e-4, gap, color=color, alpha=0.15)
    axes[0].set(xlabel="x", ylabel="density", ylim=(0, 0.8), title="samples")
    axes[1].set(xlabel="t", title=r"Re $\varphi_N(t)$ (solid) and $|\varphi_N(t)|$ (dotted)")
    axes[2].set(xlabel="t", ylim=(1e-4, None), title=r"$N\,w(t)\,|\varphi_N(t) - \varphi(t)|^2$")
    for ax in axes:
        ax.legend(fontsize=7)
    return axes


def plot_success_rates(rows: dict[str, tuple[float, float, float]], ax=None,
                       reference: dict[str, float] | None = None, colors=None):
    """Bars of ``name: (rate, low, high)``; ``reference`` rates as black ticks across their bars."""
    ax = _axes(ax)
    names = list(rows)
    rates, lows, highs = zip(*rows.values())  # (bars,) each
    yerr = [[r - low for r, low in zip(rates, lows)], [high - r for r, high in zip(rates, highs)]]
    ax.bar(range(len(names)), rates, yerr=yerr, color=colors, capsize=3)
    marked = [(i, reference[name]) for i, name in enumerate(names) if name in (reference or {})]
    if marked:
        xs, ys = zip(*marked)
        ax.hlines(ys, [x - 0.4 for x in xs], [x + 0.4 for x in xs], colors="k", lw=2,
                  label="the paper")
        ax.legend(fontsize=8, loc="upper right")
    ax.set_xticks(range(len(names)), names, rotation=25, ha="right", fontsize=8)
    ax.set(ylim=(0, 1.15), yticks=[0, 0.2, 0.4, 0.6, 0.8, 1.0], ylabel="success rate")
    ax.axhline(1.0, color="0.8", lw=0.8)  # the band above it holds the legend
    return ax


def plot_stopped_by_door_distance(by_distance: dict[str, list[dict]], ax=None, title: str = ""):
    """Grouped bars: the wall test's ``stopped`` per distance from the door, per ``name: bins``."""
    ax = _axes(ax)
    grouped_bars(ax, [(name, [b["stopped"] for b in bins]) for name, bins in by_distance.items()])
    first = next(iter(by_distance.values()))
    ax.set_xticks(range(len(first)), [f"{b['lo']}-{b['hi']} px\n({b['n']} steps)" for b in first])
    ax.set(xlabel="distance along the wall from the door's centre", ylabel="stopped (wall test)",
           ylim=(0, 1.3), yticks=[0, 0.25, 0.5, 0.75, 1], title=title)
    ax.legend(loc="upper center", ncol=len(by_distance), fontsize=8)
    return ax


def plot_energy_shapes(profiles: dict[str, torch.Tensor], edges, ax=None, title: str = ""):
    """Each ``name: profile`` over its rings' middles (``edges``), divided by its maximum."""
    ax = _axes(ax)
    middles = [(low + high) / 2 for low, high in zip(edges[:-1], edges[1:])]
    for name, profile in profiles.items():
        ax.plot(middles, profile / profile.max(), "o-", ms=3, label=name)
    return _legend(ax, xlabel="dot's distance to the goal, px (ring middle)", ylim=(0, 1.05),
                   ylabel="latent distance / its maximum", title=title)


def draw_two_rooms(ax, layout: torch.Tensor, goal, start):
    """The walls of ``layout`` (``(2,)`` Two Rooms, ``(4,)`` Three Rooms), goal and start."""
    walls = wall_images(layout.view(1, -1))[0].float()
    ax.imshow(two_rooms_rgb(torch.stack([torch.zeros_like(walls), walls])), origin="upper")
    ax.add_patch(plt.Circle(tuple(goal.tolist()), 4.5, fill=False, color="green", lw=1.5))
    ax.scatter([goal[0]], [goal[1]], marker="*", s=120, c="green", zorder=3)
    ax.scatter([start[0]], [start[1]], marker="o", s=40, c="black", zorder=3)
    ax.set(xticks=[], yticks=[], xlim=(-0.5, 64.5), ylim=(64.5, -0.5))
    return ax


def animate_episodes(results, indices: list[int], every: int, titles: list[str]):
    """The episodes ``indices`` of an :class:`~ebjepa_tutorial.planning.EpisodeResults`, the
    dot's trail over the walls and goal, ``every`` steps a frame: an animation."""
    fig, axes = plt.subplots(1, len(indices), figsize=(3 * len(indices), 3.2), squeeze=False)
    trails, dots = [], []
    for ax, i, title in zip(axes[0], indices, titles):
        draw_two_rooms(ax, results.episodes.layouts[i], results.episodes.goals[i],
                       results.episodes.starts[i])
        ax.set_title(title, fontsize=9)
        trails.append(ax.plot([], [], color="tab:red", lw=1)[0])
        dots.append(ax.plot([], [], "o", color="tab:red", ms=6)[0])

    def draw(t):
        for line, dot, i in zip(trails, dots, indices):
            path = results.paths[i, : t + 1]
            line.set_data(path[:, 0], path[:, 1])
            dot.set_data(path[-1:, 0], path[-1:, 1])
        fig.suptitle(f"step {t}", fontsize=10)
        return trails + dots

    steps = list(range(0, results.paths.shape[1], every))
    animation = FuncAnimation(fig, draw, frames=steps, interval=80)
    plt.close(fig)
    return animation
