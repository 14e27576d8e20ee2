"""Figures the notebooks share: training curves, eigenvalue spectra, embeddings.

Every function draws on a matplotlib ``Axes`` it is given (or a new one) and
returns it, so notebooks can lay out several panels side by side.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import torch


def _axes(ax):
    return plt.subplots(figsize=(4.5, 3.2))[1] if ax is None else ax


def plot_history(history: dict, names: list[str] | None = None, ax=None, log: bool = True):
    """Curves of the logged terms of a :class:`~ebjepa_tutorial.train.History` against step."""
    ax = _axes(ax)
    names = [n for n in history if n != "step"] if names is None else names
    for name in names:
        ax.plot(history["step"], history[name], label=name)
    if log:
        ax.set_yscale("symlog", linthresh=1e-3)
    ax.set(xlabel="step", ylabel="loss term")
    ax.legend(fontsize=8)
    return ax


def plot_spectrum(eigenvalues: dict[str, torch.Tensor], ax=None):
    """Covariance eigenvalues (largest first, log scale), one line per labelled run."""
    ax = _axes(ax)
    for label, values in eigenvalues.items():
        ranks = torch.arange(1, len(values) + 1)
        ax.semilogy(ranks, values.clamp_min(1e-8), marker="o", label=label)
    ax.set(xlabel="eigenvalue rank", ylabel="eigenvalue of Cov(z)")
    ax.legend(fontsize=8)
    return ax


def pca_2d(z: torch.Tensor) -> torch.Tensor:
    """Project ``z`` ``(N, D)`` onto its two principal directions: ``(N, 2)``."""
    centred = z - z.mean(dim=0)
    _, _, v = torch.linalg.svd(centred, full_matrices=False)
    return centred @ v[:2].T


def plot_embedding(z: torch.Tensor, labels: torch.Tensor, ax=None, title: str = ""):
    """Scatter the first two principal components of ``z`` ``(N, D)``, coloured by label."""
    ax = _axes(ax)
    xy = pca_2d(z.detach().cpu())
    ax.scatter(xy[:, 0], xy[:, 1], c=labels, cmap="tab10", s=6, vmin=0, vmax=9)
    ax.set(title=title, xlabel="PC 1", ylabel="PC 2")
    return ax


def plot_energy_map(coords, energy, anchor, points=None, ax=None, title: str = ""):
    """Heat map of ``E(anchor, y)`` over a grid of ``y`` (from :func:`toy.energy_map`)."""
    ax = _axes(ax)
    extent = [coords[0], coords[-1], coords[0], coords[-1]]
    image = ax.imshow(energy, origin="lower", extent=extent, cmap="viridis")
    if points is not None:
        ax.scatter(points[:, 0], points[:, 1], s=1, c="white", alpha=0.3)
    ax.scatter([anchor[0]], [anchor[1]], marker="*", s=150, c="red")
    ax.set(title=title, xticks=[], yticks=[])
    plt.colorbar(image, ax=ax, fraction=0.046)
    return ax
