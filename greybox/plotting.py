"""Plots of greybox result records.

This module only draws what result records already contain; it never
computes estimates. matplotlib is imported lazily, inside the functions, so
that the compute modules never depend on it.
"""

from __future__ import annotations

__all__: list[str] = ["plot_unknown_input", "plot_residual_autocorrelation", "plot_outputs", "plot_singular_values",
                     "plot_pump_load", "plot_fleet_coefficients", "plot_law",
                     "plot_dynamic_law"]


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
    from .terms import term_kind

    _, kind, i = spec_j
    return term_kind(kind).variable(i, x, u, states, inputs)


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


def _feed_gain(law, c, name):
    """Index in the law's feedthrough of the term (component c, driver name), or None."""
    for q, (cc, nm, _) in enumerate(law.feedthrough):
        if cc == c and nm == name:
            return q
    return None


def _dynamic_law_curves(law, dlabels):
    """Curves of a continuous-time law: ``(names, theta, halfwidths, H)``.

    ``H(theta, s)`` is the complex transfer, shape (ncurves, nfreq), of each
    (component of d, driving signal) at the parameters ``theta`` (the order of
    the law's ``ci``) and the complex frequencies ``s`` [1/s]. ``halfwidths`` is
    None where the record's intervals cannot be laid on ``theta`` (see
    :func:`plot_dynamic_law`).
    """
    import numpy as np

    ci = np.asarray(law.ci, dtype=float)
    if not hasattr(law, "k"):  # DynamicLaw: d = sum_i (e_i + b_i / (s - a)) w_i
        nb = len(law.drivers)
        theta = np.r_[law.pole, law.b, law.e]
        names = [(dlabels[0], dv) for dv in law.drivers]
        return (names, theta, ci,
                lambda t, s: t[1 + nb:, None] + t[1:1 + nb, None] / (s[None, :] - t[0]))
    md, ref = law.k.size, law.reference
    feed = np.array([f[2] for f in law.feedthrough])
    drivers = list(law.drivers) + [nm for _, nm, _ in law.feedthrough if nm not in law.drivers]
    pairs = [(c, nm) for c in range(md) for nm in dict.fromkeys(drivers)
             if (nm in law.drivers and law.k[c] != 0) or _feed_gain(law, c, nm) is not None]
    if hasattr(law, "alpha"):  # SharedLaw2: z_1 = sum_j num_j(s) / den(s) w_j
        q = law.order
        pos = [tuple(rc) for rc in np.argwhere(law.beta != 0)]  # row-major = the fit's order
        ok = (law.beta.shape[1] == 1 or bool(np.all(law.beta[0] != 0))) and \
            ci.size == q + len(pos) + md - 1 + feed.size
        theta = np.r_[law.alpha, [law.beta[rc] for rc in pos], np.delete(law.k, ref), feed]

        def H(t, s):
            den = np.polyval(np.r_[1.0, t[:q]], s)
            beta = np.zeros_like(law.beta, dtype=float)
            for v, rc in zip(t[q:q + len(pos)], pos):
                beta[rc] = v
            k = np.insert(t[q + len(pos):q - 1 + len(pos) + md], ref, 1.0)
            e = t[q - 1 + len(pos) + md:]
            out = []
            for c, nm in pairs:
                j = law.drivers.index(nm) if nm in law.drivers else None
                h = k[c] * np.polyval(beta[:, j], s) / den if j is not None else 0 * s
                f = _feed_gain(law, c, nm)
                out.append(h + (e[f] if f is not None else 0.0))
            return np.array(out)
        return [(dlabels[c], nm) for c, nm in pairs], theta, ci if ok else None, H
    nb = len(law.drivers)  # SharedLaw: d_c = k_c sum_i b_i / (s - a) w_i + e_c,i w_i
    theta = np.r_[law.pole, law.b, np.delete(law.k, ref), feed]

    def H1(t, s):
        b, k = t[1:1 + nb], np.insert(t[1 + nb:nb + md], ref, 1.0)
        e = t[nb + md:]
        out = []
        for c, nm in pairs:
            h = (k[c] * b[law.drivers.index(nm)] / (s - t[0]) if nm in law.drivers else 0 * s)
            f = _feed_gain(law, c, nm)
            out.append(h + (e[f] if f is not None else 0.0))
        return np.array(out)
    return ([(dlabels[c], nm) for c, nm in pairs], theta,
            ci if ci.size == theta.size else None, H1)


def _subsystem_curves(sub, dt):
    """Curves of a discrete subsystem (update.Subsystem, no intervals): ``(names, H)`` with
    ``H(s)`` evaluated at ``z = exp(s dt)``."""
    import numpy as np

    Bw, Dw = np.hstack([sub.Bdu, sub.Bdx]), np.hstack([sub.Ddu, sub.Ddx])
    wnames = list(sub.input_labels) + list(sub.state_labels)
    dnames = list(sub.unknown_labels) or [f"d[{c}]" for c in range(Dw.shape[0])]
    cols = [j for j in range(Bw.shape[1]) if np.any(Bw[:, j] != 0) or np.any(Dw[:, j] != 0)]
    names = [(dnames[c], wnames[j]) for c in range(Dw.shape[0]) for j in cols]
    nd = sub.Ad.shape[0]

    def H(s):
        out = np.empty((len(names), s.size), dtype=complex)
        for f, z in enumerate(np.exp(s * dt)):
            G = sub.Cd @ np.linalg.solve(z * np.eye(nd) - sub.Ad, Bw) + Dw if nd else Dw
            out[:, f] = [G[c, j] for c in range(Dw.shape[0]) for j in cols]
        return out
    return names, H


def _pole_marks(law, sub, dt):
    """(pole [1/s], 95 % half-width or NaN) of each real pole and of each complex pair (its
    upper member) the record states; a discrete subsystem's poles mapped by ``log(z) / dt``."""
    import numpy as np

    if law is None:
        lam = np.linalg.eigvals(sub.Ad).astype(complex) if sub.Ad.size else np.zeros(0)
        return [(p, np.nan) for p in np.log(lam) / dt if p.imag >= 0]
    if not hasattr(law, "poles"):
        return [(complex(law.pole), float(law.ci[0]))]
    return [(complex(p), float(h) if abs(p.imag) == 0 else np.nan)
            for p, h in zip(law.poles, law.pole_ci) if p.imag >= 0]


def _band(H, theta, hw, s, nominal, n_samples: int = 400):
    """Pointwise 2.5/97.5 % of |H| and of the phase [deg] over parameters drawn independently
    from normals with standard deviation ``hw / 1.96`` (seeded: the same band each call)."""
    import numpy as np

    rng = np.random.default_rng(0)
    draws = theta + (hw / 1.959964) * rng.standard_normal((n_samples, theta.size))
    resp = np.array([H(t, s) for t in draws])  # (n_samples, ncurves, nfreq)
    mag = np.nanpercentile(np.abs(resp), [2.5, 97.5], axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        dph = np.degrees(np.angle(resp / nominal[None]))
    base = np.degrees(np.unwrap(np.angle(nominal), axis=-1))
    ph = base[None] + np.nanpercentile(dph, [2.5, 97.5], axis=0)
    return mag, ph


def plot_dynamic_law(report, *, ax=None, n_freq: int = 200):
    """The figure that explains a dynamic law: its frequency response with the 95 % band.

    Bode magnitude and phase of the law's transfer from each signal driving it
    (a state or input of the model, or a relative coordinate) to each
    component of d, in physical units (d's units per unit of that signal;
    the phase in degrees), at frequencies ``w`` [rad/s] on a log scale, with
    the law's poles marked (vertical lines at ``|p|`` [rad/s], the time
    constant ``-1/p`` [s] of a real one, the 95 % interval of a real pole
    shaded). A continuous-time law (``report.effect.dynamic_law``: DynamicLaw,
    SharedLaw or SharedLaw2) is drawn in continuous time; a discrete subsystem
    (``report.effect.subsystem``) at ``z = exp(j w dt)`` up to the Nyquist
    frequency ``pi / dt``.

    The band: the records keep each coefficient's 95 % half-width ``h`` (their
    ``ci``), not the covariance, so 400 parameter vectors are drawn
    independently from normals of standard deviation ``h / 1.96`` around the
    estimate (seed 0) and the band is the pointwise 2.5 - 97.5 % range of
    magnitude and phase. Leaving out the correlations (a pole's and its gain's
    are strong) makes the band wider than the joint one: conservative. A
    discrete subsystem carries no intervals, nor does a SharedLaw2 whose
    numerator intervals cannot be laid on its terms (a driver missing from the
    numerator's leading row); no band is drawn then, and the title says so.

    Parameters
    ----------
    report : LoopReport
        With a dynamic effect (``report.effect.kind == "dynamic"``).
    ax : pair of matplotlib Axes, optional
        (magnitude, phase); a new figure with both is made if None.
    n_freq : int
        Number of frequencies, log-spaced from 1/30 of the slowest pole's
        ``|p|`` to 30 times the fastest (at most ``pi / dt``).

    Returns
    -------
    dict
        ``figure``, ``axes`` (magnitude, phase), ``frequency`` (ndarray, shape
        (n_freq,), [rad/s]), ``names`` (list of (component of d, driving
        signal), one per curve), ``response`` (complex ndarray, shape (ncurves,
        n_freq): the law's transfer, d's units per the signal's unit),
        ``band`` ((2, ncurves, n_freq) magnitude 2.5 / 97.5 % bounds, or None),
        ``poles`` (list of (pole [1/s], 95 % half-width or NaN)).
    """
    import numpy as np

    from .exceptions import DataError

    eff = report.effect
    law, sub = getattr(eff, "dynamic_law", None), getattr(eff, "subsystem", None)
    if eff.kind != "dynamic" or (law is None and sub is None):
        raise DataError(f"this report's effect is {eff.kind!r}, not a dynamic law; plot_law "
                        f"draws a static one")
    dt = float(law.dt if law is not None else report.nominal.dt)
    ch = report.channel
    dlabels = list(ch.labels) if ch is not None else \
        [f"d[{c}]" for c in range(len(getattr(law, "k", [1.0])))]
    units = list(ch.units) if ch is not None and ch.units else [""] * len(dlabels)
    marks = _pole_marks(law, sub, dt)
    speeds = [abs(p) for p, _ in marks if abs(p) > 0] or [0.1 * np.pi / dt]
    w = np.logspace(np.log10(min(speeds) / 30), np.log10(min(max(speeds) * 30, np.pi / dt)),
                    n_freq)
    s = 1j * w
    if law is not None:
        names, theta, hw, H = _dynamic_law_curves(law, dlabels)
        resp = H(theta, s)
        band = _band(H, theta, hw, s, resp) if hw is not None and np.all(np.isfinite(hw)) \
            else None
        why = ("" if band is not None else " (no band: the intervals are not determined)"
               if hw is not None else " (no band: its intervals cannot be laid on its terms)")
    else:
        names, Hs = _subsystem_curves(sub, dt)
        resp, band, why = Hs(s), None, " (no band: a discrete subsystem carries no intervals)"
    fig, (am, ap) = _axes(ax, 2, figsize=(6.8, 5.6))
    phase = np.degrees(np.unwrap(np.angle(resp), axis=-1))
    for i, (dn, drv) in enumerate(names):
        col = f"C{i % 10}"
        am.loglog(w, np.abs(resp[i]), color=col, lw=1.5, label=f"{dn} / {drv}")
        ap.semilogx(w, phase[i], color=col, lw=1.5)
        if band is not None:
            am.fill_between(w, band[0][0, i], band[0][1, i], color=col, alpha=0.2, lw=0,
                            label="95 % band (coefficients drawn from their intervals)"
                            if i == 0 else None)
            ap.fill_between(w, band[1][0, i], band[1][1, i], color=col, alpha=0.2, lw=0)
    for p, h in marks:
        lab = (f"pole {p.real:.3g} 1/s (time constant {-1 / p.real:.3g} s)" if p.imag == 0
               else f"poles {p.real:.3g} ± {p.imag:.3g}j 1/s (|p| = {abs(p):.3g} rad/s)")
        for a in (am, ap):
            a.axvline(abs(p), color="0.3", ls="--", lw=1, label=lab if a is am else None)
            if np.isfinite(h) and abs(p.real) > h:
                a.axvspan(abs(p.real) - h, abs(p.real) + h, color="0.5", alpha=0.15, lw=0)
    unit = units[0] if len(set(units)) == 1 and units[0] else "d's units"
    am.set_ylabel(f"|d / signal| ({unit} per unit of the signal)")
    ap.set_ylabel("phase [deg]")
    ap.set_xlabel("frequency w [rad/s]")
    am.legend(loc="best", fontsize="x-small")
    am.set_title(f"{eff.channel}: frequency response of the law{why}", fontsize="small")
    fig.tight_layout()
    return {"figure": fig, "axes": [am, ap], "frequency": w, "names": names, "response": resp,
            "band": None if band is None else band[0], "poles": marks}
