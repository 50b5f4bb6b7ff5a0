"""Figures for experiment results: one look for all of them, written as PNG without a screen.

Built with matplotlib's object-oriented API (`Figure` + `savefig`), not pyplot: a figure saved to a file
needs no GUI backend, so nothing here switches the backend of a notebook or a service that imports it.
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.axes import Axes
from matplotlib.figure import Figure


def new_figure(title: str, rows: int = 1, cols: int = 1) -> tuple[Figure, Axes]:
    """A figure with one axes (or the first of a grid) and a title; grid on."""
    fig = Figure(figsize=(8, 4.5 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax in axes.flat:
        ax.grid(True, alpha=0.3)
    fig.suptitle(title)
    return fig, axes.flat[0]


def save_figure(fig: Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path
