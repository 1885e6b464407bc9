"""Plots of greybox result records.

This module only draws what result records already contain; it never
computes estimates. matplotlib is imported lazily, inside the functions, so
that the compute modules never depend on it.
"""

from __future__ import annotations

__all__: list[str] = ["plot_unknown_input", "plot_residual_autocorrelation", "plot_outputs", "plot_singular_values",
                     "plot_pump_load", "plot_fleet_coefficients", "plot_law"]


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


def _law_variable(spec_j, x, u, states, inputs):
    """(values, name) of the variable a law term reads (the state of x, v^3, sign(v), |v|;
    the input of u and of a dead zone or saturation; the relative coordinate of a pair;
    the state of a product x*u); None for a constant."""
    _, kind, i = spec_j
    if kind in ("x", "x^3", "sign", "abs"):
        return x[i], states[i]
    if kind == "u":
        return u[i], inputs[i]
    if kind in ("u_dz", "u_sat"):
        return u[i[0]], inputs[i[0]]
    if kind.startswith("rel"):
        return x[i[1]] - x[i[0]], f"{states[i[1]]} - {states[i[0]]}"
    if kind == "x*u":
        return x[i[0]], states[i[0]]
    if kind in ("x_hi", "x_lo"):
        return x[i[0]], states[i[0]]
    return None


def plot_law(report, u, *, bins: int = 20, max_points: int = 3000, ax=None):
    """The figure that explains a static law: d^ against the law's variable, the law over it.

    For each component of d, the term with the largest contribution names the
    variable (a velocity for a friction, the relative deflection for a spring
    between bodies, the input for a dead zone). Drawn: the partial residual
    ``d^ - (the law's other terms)`` against that variable (a thinned cloud),
    its means in ``bins`` quantile bins with +-2 standard errors (the law's
    shape, out of d^'s noise), and the term with its 95 % band (the
    coefficient's interval). The law's own estimate (``report.trace.law_estimate``:
    delayed and/or smoothed, for a channel of relative degree 2) is drawn where the
    report has it, else the filter's d^.

    Parameters
    ----------
    report : LoopReport
        With a static effect (``report.effect.law``) in state, force or input
        equations and its trace (``report.trace.filter_result``).
    u : array_like, shape (ninputs, nsteps)
        The estimation inputs close the loop was given.
    bins : int
    max_points : int
        Points of the cloud at most.
    ax : matplotlib Axes or list of them, optional
        One per component of d.

    Returns
    -------
    dict
        ``{"figure", "axes", "variables", "bins"}``: the variable drawn per
        component and its bins ``(centres, means, 2 standard errors)``.
    """
    import numpy as np
    from dataclasses import replace

    from .exceptions import DataError

    law = getattr(report.effect, "law", None)
    tr = report.trace
    if law is None or tr is None or tr.filter_result is None or law.output is not None \
            or not np.any(law.coef):
        raise DataError("this report has no static law in state or input equations to draw "
                        "(a dynamic, sensor or no effect); plot_unknown_input draws d^ itself")
    res = tr.filter_result
    u = np.atleast_2d(np.asarray(u, dtype=float))
    est = tr.law_estimate if tr.law_estimate is not None else res
    s = max(tr.relative_degree - 1, 0) if tr.law_estimate is not None else 0
    K = min(est.d_est.shape[1], est.x_filt.shape[1], u.shape[1]) - s
    # d^[j] of a delayed estimate estimates d about s samples later
    x, uu, d = est.x_filt[:, s:s + K], u[:, s:s + K], est.d_est[:, :K]
    states = list(res.sys.state_labels)
    inputs = list(report.nominal.input_labels)
    md = law.coef.shape[0]
    fig, axs = _axes(ax, md, figsize=(6.4, 3.2 * md))
    ok = np.all(np.isfinite(d), axis=0) & np.all(np.isfinite(x), axis=0)
    ok[:min(res.settled(20), K)] = False  # the filter's start-up transient
    names, binned = [], []
    for c in range(md):
        cols = np.flatnonzero(law.coef[c])
        if not cols.size:
            names.append(None)
            binned.append(None)
            continue
        one = {}
        for j in cols:
            coef = np.zeros_like(law.coef)
            coef[c, j] = law.coef[c, j]
            one[j] = replace(law, coef=coef).evaluate(x, uu)[c]
        j = max(cols, key=lambda q: float(np.sqrt(np.nanmean(one[q] ** 2))))
        var = _law_variable(law.spec[j], x, uu, states, inputs)
        ax_ = axs[c]
        if var is None:
            names.append(None)
            binned.append(None)
            continue
        v, vname = var
        part = d[c] - (law.evaluate(x, uu)[c] - one[j])
        keep = np.flatnonzero(ok)
        pick = keep[np.linspace(0, keep.size - 1, min(max_points, keep.size)).astype(int)]
        ax_.plot(v[pick], part[pick], ".", ms=2, alpha=0.2, color="0.5", label="d^ (partial)")
        edges = np.unique(np.nanquantile(v[keep], np.linspace(0, 1, bins + 1)))
        idx = np.clip(np.searchsorted(edges, v[keep], side="right") - 1, 0, edges.size - 2)
        mid, mean, err = [], [], []
        for b in range(edges.size - 1):
            sel = part[keep][idx == b]
            if sel.size > 2:
                mid.append(float(np.mean(v[keep][idx == b])))
                mean.append(float(np.mean(sel)))
                err.append(2 * float(np.std(sel)) / np.sqrt(sel.size))
        ax_.errorbar(mid, mean, yerr=err, fmt="o", ms=4, color="C0", label="bin means +-2 SE")
        order = np.argsort(v[keep])
        vs, fs = v[keep][order], one[j][keep][order]
        ax_.plot(vs, fs, "C3", lw=1.5, label=f"law: {law.spec[j][0]}")
        h = law.ci[c, j] if law.ci is not None else np.nan
        if np.isfinite(h) and law.coef[c, j] != 0:
            lo, hi = fs * (1 - h / abs(law.coef[c, j])), fs * (1 + h / abs(law.coef[c, j]))
            ax_.fill_between(vs, np.minimum(lo, hi), np.maximum(lo, hi), color="C3",
                             alpha=0.2, lw=0, label="95 % band")
        ax_.set_xlabel(vname)
        ax_.set_ylabel(str(res.unknown_labels[c]) if c < len(res.unknown_labels) else "d")
        ax_.legend(loc="best", fontsize="small")
        names.append(vname)
        binned.append((np.array(mid), np.array(mean), np.array(err)))
    axs[0].set_title(report.effect.formula[:90], fontsize="small")
    return {"figure": fig, "axes": axs, "variables": names, "bins": binned}
