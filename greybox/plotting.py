"""Plots of greybox result records.

This module only draws what result records already contain; it never
computes estimates. matplotlib is imported lazily, inside the functions, so
that the compute modules never depend on it.
"""

from __future__ import annotations

__all__: list[str] = ["plot_unknown_input", "plot_residual_autocorrelation", "plot_outputs", "plot_singular_values",
                     "plot_pump_load", "plot_fleet_coefficients"]


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


def plot_unknown_input(result, channel=0, *, d_true=None, window=None, ax=None):
    """Unknown-input estimate with its confidence band (the paper's Fig. 1).

    Parameters
    ----------
    result : FilterResult
        Record of :func:`greybox.uikf`.
    channel : int or str
        Unknown-input channel (index or label).
    d_true : array_like, shape (nsteps,) or (md, nsteps), optional
        True unknown input, drawn for comparison.
    window : (int, int), optional
        Sample range to draw; all samples by default.
    ax : matplotlib Axes, optional

    Returns
    -------
    dict
        ``{"figure", "ax", "estimate", "band", "truth"}`` artists.
    """
    import numpy as np

    from ._validation import resolve_channels

    if not result.unknown_labels:
        from .exceptions import DataError

        raise DataError("this filter result has no unknown input to plot (a Kalman filter?)")
    (j,) = resolve_channels(channel, result.unknown_labels, "channel")
    label = result.unknown_labels[j]
    N = result.d_est.shape[1]
    a, b = window if window is not None else (0, N - 1)
    k = np.arange(a, b)
    fig, (ax,) = _axes(ax)
    band = ax.fill_between(k, result.d_lower[j, a:b], result.d_upper[j, a:b], color="C0",
                           alpha=0.25, lw=0,
                           label=f"{100 * result.level:.0f}% confidence interval")
    est, = ax.plot(k, result.d_est[j, a:b], color="C0", lw=1, label="unknown-input filter")
    truth = None
    if d_true is not None:
        dt_ = np.atleast_2d(np.asarray(d_true, dtype=float))
        truth, = ax.plot(k, dt_[j if dt_.shape[0] > 1 else 0, a:b], "k--", lw=1,
                         label="true value")
    ax.set_xlabel("sample k")
    ax.set_ylabel(f"{label}")
    ax.legend(loc="best", fontsize="small")
    return {"figure": fig, "ax": ax, "estimate": est, "band": band, "truth": truth}


def plot_singular_values(result, ax=None):
    """Plot the singular values of a subspace identification and the chosen order.

    Parameters
    ----------
    result : greybox.ident.N4SIDResult
        Record of :func:`greybox.ident.n4sid` or :func:`greybox.ident.pbsid`.
    ax : matplotlib Axes, optional
        Axes to draw on; a new figure is made if None.

    Returns
    -------
    dict
        ``figure``, ``ax``, ``singular_values`` (Line2D of sigma_k against
        k = 1, 2, ... on a log scale) and ``order`` (vertical Line2D at
        order + 1/2, between the kept and the discarded values).
    """
    import numpy as np

    fig, (ax,) = _axes(ax)
    s = np.asarray(result.singular_values, dtype=float)
    k = np.arange(1, s.size + 1)
    shown = np.where(s > 0, s, np.nan)
    (line,) = ax.semilogy(k, shown, "o-", label="singular values")
    vline = ax.axvline(result.order + 0.5, color="C3", linestyle="--",
                       label=f"chosen order n = {result.order}")
    ax.set_xlabel("index k")
    ax.set_ylabel("singular value (scaled data)")
    ax.set_title(f"{result.method}: {result.weighting} weighting, horizon {result.horizon}")
    ax.legend(loc="best", fontsize="small")
    return {"figure": fig, "ax": ax, "singular_values": line, "order": vline}


def plot_residual_autocorrelation(validations, *, ax=None):
    """Autocorrelation of one-step prediction residuals with the 99 % band (Fig. 2).

    Parameters
    ----------
    validations : ModelValidation or sequence of them
        One panel per model (e.g. initial and updated).
    ax : sequence of Axes, optional
        One per model.

    Returns
    -------
    dict
        ``{"figure", "axes", "lines", "bands"}``.
    """
    import numpy as np

    vals = list(validations) if isinstance(validations, (list, tuple)) else [validations]
    fig, axes = _axes(ax, nrows=len(vals), figsize=(7, 2.6 * len(vals)))
    lines, bands = [], []
    for a, v in zip(axes, vals):
        lags = np.arange(v.autocorr.shape[1])
        for i in range(v.autocorr.shape[0]):
            lab = v.output_labels[i] if i < len(v.output_labels) else f"y[{i}]"
            lines.append(a.plot(lags, v.autocorr[i], marker="o", ms=3, lw=1, label=lab)[0])
        bands.append(a.axhspan(-v.band, v.band, color="grey", alpha=0.3, lw=0,
                               label="99% band"))
        a.set_title(f"{v.name}: autocorrelation of one-step prediction residuals")
        a.set_xlabel("lag")
        a.set_ylim(-1.05, 1.05)
        a.legend(loc="upper right", fontsize="x-small", ncol=4)
    fig.tight_layout()
    return {"figure": fig, "axes": axes, "lines": lines, "bands": bands}


def plot_outputs(y, validations, *, outputs=None, dt=None, window=None, ax=None):
    """Measured outputs against the simulated outputs of several models.

    Parameters
    ----------
    y : ndarray, shape (noutputs, nsteps)
        Measured outputs.
    validations : sequence of ModelValidation
        Their ``y_sim`` are drawn.
    outputs : sequence of int, optional
        Which outputs (all by default).
    dt : float, optional
        Sampling period [s] for the time axis (samples if None).
    window : (int, int), optional
        Sample range.
    ax : sequence of Axes, optional

    Returns
    -------
    dict
        ``{"figure", "axes", "lines"}``.
    """
    import numpy as np

    vals = list(validations)
    outputs = list(range(y.shape[0])) if outputs is None else list(outputs)
    a0, b0 = window if window is not None else (0, y.shape[1])
    t = np.arange(a0, b0) * (dt if dt else 1.0)
    fig, axes = _axes(ax, nrows=len(outputs), figsize=(7, 2.0 * len(outputs)))
    lines = []
    for a, i in zip(axes, outputs):
        labels = vals[0].output_labels if vals else ()
        lines.append(a.plot(t, y[i, a0:b0], "k", lw=1, label="measured")[0])
        for v in vals:
            lines.append(a.plot(t, v.y_sim[i, a0:b0], lw=1,
                                label=f"{v.name} (SE {v.se.per_output[i]:.1f}%)")[0])
        a.set_ylabel(labels[i] if i < len(labels) else f"y[{i}]")
        a.legend(loc="upper right", fontsize="x-small")
    axes[-1].set_xlabel("time [s]" if dt else "sample")
    fig.tight_layout()
    return {"figure": fig, "axes": axes, "lines": lines}


def plot_pump_load(table5, *, window=None, ax=None):
    """True pump load h_r and its recovered estimate with the 95 % band (the paper's Fig. 3).

    Parameters
    ----------
    table5 : greybox.reproduce.Table5
        Record of :func:`greybox.reproduce.reproduce_table5`; the estimate is
        ``h_r^ = -d^ / Mdot^^2`` (:meth:`Table5.load_estimate`).
    window : (int, int), optional
        Sample range to draw; the paper shows samples 1000-2500 (the default).
    ax : matplotlib Axes, optional
        Axes to draw on; a new figure is made if None.

    Returns
    -------
    dict
        ``{"figure", "ax", "estimate", "band", "truth"}`` artists.
    """
    import numpy as np

    est, half = table5.load_estimate()
    a, b = window if window is not None else (1000, min(2500, est.size - 1))
    k = np.arange(a, b)
    fig, (ax,) = _axes(ax)
    band = ax.fill_between(k, est[a:b] - half[a:b], est[a:b] + half[a:b], color="C0",
                           alpha=0.25, lw=0, label="95% confidence interval")
    line, = ax.plot(k, est[a:b], color="C0", lw=1, label="unknown-input UKF estimate")
    truth, = ax.plot(k, table5.load[a:b], "k--", lw=1, label="true value")
    ax.set_xlabel("simulation step k")
    ax.set_ylabel("pump load h_r")
    ax.set_title("Fig. 3: true and estimated pump load")
    ax.legend(loc="best", fontsize="small")
    return {"figure": fig, "ax": ax, "estimate": line, "band": band, "truth": truth}


def plot_fleet_coefficients(groups, *, max_panels: int = 12):
    """Strip plot of each explanation group's coefficients across its units (``greybox fleet``).

    One panel per (group, coefficient): every unit's value (jittered sideways),
    the median (line), a band of +- 1.4826 MAD (a normal standard deviation's
    robust estimate) and the robust outliers (red crosses, named).

    Parameters
    ----------
    groups : sequence of greybox.fleet.ExplanationGroup
        Groups of :func:`greybox.fleet.group_units`, largest first.
    max_panels : int
        Draw at most this many panels (the first groups' coefficients).

    Returns
    -------
    dict
        ``{"figure", "axes"}``: a standalone matplotlib Figure (not registered
        with pyplot: save it; there is nothing to close).
    """
    import math

    import numpy as np
    from matplotlib.figure import Figure

    panels = [(i, g, c) for i, g in enumerate(groups, start=1) for c in g.coefficients]
    panels = panels[:max_panels]
    ncols = max(1, min(3, len(panels)))
    nrows = max(1, math.ceil(len(panels) / ncols))
    fig = Figure(figsize=(4.2 * ncols, 3.2 * nrows), layout="constrained")
    axes = list(fig.subplots(nrows, ncols, squeeze=False).ravel())
    jitter = np.random.default_rng(0)
    for ax, (i, g, c) in zip(axes, panels):
        names = [u for u, _ in c.values]
        x = np.array([v for _, v in c.values], dtype=float)
        side = jitter.uniform(-0.3, 0.3, x.size)
        out = np.array([u in c.outliers for u in names], dtype=bool)
        ax.axhspan(c.median - 1.4826 * c.mad, c.median + 1.4826 * c.mad, color="C0",
                   alpha=0.15, lw=0)
        ax.axhline(c.median, color="C0", lw=1)
        ax.scatter(side[~out], x[~out], s=16, color="C0")
        ax.scatter(side[out], x[out], s=30, color="C3", marker="x")
        for j in np.flatnonzero(out):
            ax.annotate(names[j], (side[j], x[j]), xytext=(4, 0), textcoords="offset points",
                        fontsize=7, color="C3")
        ax.set_xlim(-1, 1)
        ax.set_xticks([])
        key = g.key if len(g.key) <= 48 else g.key[:45] + "..."
        ax.set_title(f"group {i} ({len(g.units)} units): {key}", fontsize=8)
        ax.set_ylabel(f"coefficient of {c.name}")
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    return {"figure": fig, "axes": axes[:len(panels)]}
