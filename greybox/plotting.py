"""Plots of greybox result records.

This module only draws what result records already contain; it never
computes estimates. matplotlib is imported lazily, inside the functions, so
that the compute modules never depend on it.
"""

from __future__ import annotations

__all__: list[str] = []


def _plt():
    """Import pyplot lazily (Agg-safe)."""
    import matplotlib.pyplot as plt

    return plt


def _axes(ax, nrows: int = 1, figsize=None):
    """Return (fig, axes list): new axes, or the given one(s)."""
    plt = _plt()
    if ax is None:
        fig, axs = plt.subplots(nrows, 1, figsize=figsize, squeeze=False)
        return fig, list(axs[:, 0])
    axs = list(ax) if isinstance(ax, (list, tuple)) else [ax]
    return axs[0].figure, axs
