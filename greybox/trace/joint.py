"""Joint output-error refinement of several effects added one after the other.

The several-effects loop adds one effect per pass, each fitted with the
earlier ones frozen. A pass can then borrow part of an effect that a later
pass finds (a static law fitted first absorbs some of an actuator lag with
spurious input and position terms; the lag found next is too slow). Here
every coefficient of every effect (static laws' terms, dynamic laws' pole,
filtered and feedthrough gains) is refitted at once by output error on y,
the final continuous model discretized exactly (ZOH) at every evaluation,
and terms whose 95 % interval then contains 0 are dropped one at a time.

Every effect enters the continuous model affinely:
``A(theta) = A0 + sum_q theta_q dA_q`` (same for B), so one parameter list
covers every law kind. A shared-state law (:class:`~greybox.trace.dynamic.SharedLaw`)
is affine too once its scale is fixed (the reference component's gain is 1):
its pole, the state's drivers' gains b, the other components' gains k and the
feedthrough e each move one entry (or one outer product) of A and B. So does a
second- or third-order one (:class:`~greybox.trace.shared_order2.SharedLaw2`,
observer canonical form): the denominator's alpha, the numerators' beta, k and e.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import control as ct
import numpy as np
from numpy.typing import NDArray

from .._blas import single_thread_blas
from .._lti import lti_states
from ..system import named_ss
from ..update import UpdatedModel
from .channels import Channel, kinematic_partner
from .dynamic import DynamicLaw, SharedLaw, _driver_name, _law_from, _problem, \
    _shared_law_from, _shared_problem
from .laws import StaticLaw, law_line, _one_direction, linear_part
from .oe import OutputError, zoh
from .shared_order2 import SharedLaw2
from .shared_order2 import _law_from as _shared2_law_from
from .shared_order2 import _Problem as _Shared2Problem

__all__ = ["JointEffect", "JointRefinement", "has_joint_parameters", "refine_jointly",
           "without_dead_states"]


@dataclass(frozen=True)
class JointEffect:
    """One effect of the loop, as the joint refinement needs it.

    Attributes
    ----------
    base : control.StateSpace
        The continuous model the effect was added to (states ``n_i``).
    channel : Channel
        Its channel (G of shape (n_i, md)).
    law : StaticLaw or DynamicLaw or SharedLaw
        A continuous-time linear static law, or a sparse first-order law
        (one component, or one state shared by the md components) whose
        state is appended at index ``n_i``.
    """

    base: ct.StateSpace = field(repr=False)
    channel: Channel
    law: object


@dataclass(frozen=True)
class JointRefinement:
    """Result of :func:`refine_jointly`.

    Attributes
    ----------
    laws : tuple
        The refitted law of every effect, in the loop's order.
    continuous : control.StateSpace
        Final model in continuous time.
    model : UpdatedModel
        Final model, discretized exactly (ZOH), with the loop's Q and R.
    se_before, se_after : float
        Output-error SE [%] on the estimation window of the loop's final model
        and of the jointly refitted one.
    npar_before, npar_after : int
        Coefficients before and after (terms whose interval contains 0 dropped).
    dropped : tuple of str
        Terms dropped, as ``"<channel>: <term>"``.
    partials : tuple of control.StateSpace
        ``partials[k - 1]``: the continuous model with only the first k effects,
        at their refitted values (k = 1 .. len(laws) - 1).
    moved : bool
        Whether the refit changed the effects beyond their noise: a term dropped or
        merged, or a coefficient moved by its 95 % half-width or more (or its interval
        undetermined). False: the data cannot tell the refitted effects from the found ones.
    """

    laws: tuple
    continuous: ct.StateSpace = field(repr=False)
    model: UpdatedModel = field(repr=False)
    se_before: float
    se_after: float
    npar_before: int
    npar_after: int
    dropped: tuple[str, ...] = ()
    partials: tuple = field(default=(), repr=False)
    moved: bool = True


class _Param:
    """One coefficient: its effect, its key, and where it enters (dA, dB).

    ``group``: the prunable coefficients of which one must stay (default: the
    effect's; None: it may go with all its group).
    """

    def __init__(self, eff: int, key, dA: NDArray, dB: NDArray, value: float, name: str,
                 prunable: bool, group="effect"):
        self.eff, self.key, self.dA, self.dB = eff, key, dA, dB
        self.value, self.name, self.prunable = value, name, prunable
        self.group = (eff,) if group == "effect" else group


def _is_lag(law) -> bool:
    """A sensor law that is one first-order lag (its coefficient tau [s])."""
    return isinstance(law, StaticLaw) and law.output is not None and len(law.spec) == 1 \
        and law.spec[0][1] == "yhat_lag"


def _is_held(law) -> bool:
    """A static sensor law (a gain, an offset): it acts on C and D, not on A and B, so the
    joint refit holds it at its value (the loop refits it on the refitted model after)."""
    return isinstance(law, StaticLaw) and law.output is not None and not _is_lag(law)


def has_joint_parameters(effects) -> bool:
    """Whether any of ``effects`` (JointEffect) has a coefficient the joint refit moves.

    A static sensor law (a gain, an offset) acts on C and D and is held at its value; when
    every effect is one (two sensors' gains), there is nothing to refit jointly (each
    sensor's law is refitted on its own on the loop's model)."""
    return any(not _is_held(ef.law) for ef in effects)


def _lag_param(i: int, ef: JointEffect, nf: int) -> _Param:
    """A sensor lag's one coefficient, 1/tau: ``dz/dt = (C_i x + D_i u - z) / tau`` moves
    the sensor state's row of A and B by (C_i, -1) and D_i per unit of 1/tau."""
    base, out = ef.base, ef.law.output
    n, m = base.nstates, base.ninputs
    dA, dB = np.zeros((nf, nf)), np.zeros((nf, m))
    dA[n, :n], dA[n, n] = np.asarray(base.C, dtype=float)[out], -1.0
    dB[n] = np.asarray(base.D, dtype=float)[out]
    return _Param(i, ("lag",), dA, dB, 1.0 / float(ef.law.coef[0, 0]),
                  f"{ef.channel.name}: 1/tau", False)


def _params(effects, nf: int, m: int) -> list[_Param]:
    out = []
    for i, ef in enumerate(effects):
        n = ef.base.nstates
        G = np.asarray(ef.channel.G, dtype=float)
        law = ef.law
        if _is_lag(law):
            out.append(_lag_param(i, ef, nf))
        elif _is_held(law):
            continue
        elif isinstance(law, StaticLaw):
            for c in range(law.coef.shape[0]):
                for j in np.flatnonzero(law.coef[c]):
                    unit = np.zeros_like(law.coef)
                    unit[c, j] = 1.0
                    Ddx, Ddu = linear_part(law.spec, unit, n, m)
                    dA, dB = np.zeros((nf, nf)), np.zeros((nf, m))
                    dA[:n, :n], dB[:n] = G @ Ddx, G @ Ddu
                    # group None: a static effect whose every term's interval holds 0
                    # once the others are refitted is no effect (its step is dropped)
                    out.append(_Param(i, ("s", c, int(j)), dA, dB, float(law.coef[c, j]),
                                      f"{ef.channel.name}: {law.spec[j][0]}", True,
                                      group=None))
        elif isinstance(law, SharedLaw):
            out += _shared_params(i, ef, nf, m)
        elif isinstance(law, SharedLaw2):
            out += _shared2_params(i, ef, nf, m)
        else:
            g = G[:, 0]
            dA = np.zeros((nf, nf))
            dA[n, n] = 1.0
            out.append(_Param(i, ("a",), dA, np.zeros((nf, m)), law.pole,
                              f"{ef.channel.name}: pole", False))
            for q, (wq, b, e) in enumerate(zip(law.weights, law.b, law.e)):
                dAb, dBb = np.zeros((nf, nf)), np.zeros((nf, m))
                dAe, dBe = np.zeros((nf, nf)), np.zeros((nf, m))
                dAb[n, :n], dBb[n] = wq[:n], wq[n:]
                dAe[:n, :n], dBe[:n] = np.outer(g, wq[:n]), np.outer(g, wq[n:])
                nm = law.drivers[q]
                out.append(_Param(i, ("b", q), dAb, dBb, float(b), f"{ef.channel.name}: lag {nm}",
                                  True))
                out.append(_Param(i, ("e", q), dAe, dBe, float(e), f"{ef.channel.name}: {nm}",
                                  True))
    return out


def _shared_params(i: int, ef: JointEffect, nf: int, m: int) -> list[_Param]:
    """A shared-state law's coefficients: pole, b (one stays), k (not the reference's), e."""
    law, base, nm = ef.law, ef.base, ef.channel.name
    n = base.nstates
    rows = _rows_of(base)
    out = []
    dA = np.zeros((nf, nf))
    dA[n, n] = 1.0
    out.append(_Param(i, ("a",), dA, np.zeros((nf, m)), law.pole, f"{nm}: pole", False))
    for q, (dn, b) in enumerate(zip(law.drivers, law.b)):
        w = np.zeros(n + m)
        w[rows[dn]] = 1.0
        dA, dB = np.zeros((nf, nf)), np.zeros((nf, m))
        dA[n, :n], dB[n] = w[:n], w[n:]
        out.append(_Param(i, ("b", q), dA, dB, float(b), f"{nm}: {law.state} <- {dn}", True,
                          group=(i, "b")))
    return out + _gain_params(i, ef, nf, m, law.state)


def _gain_params(i: int, ef: JointEffect, nf: int, m: int, state: str) -> list[_Param]:
    """A shared law's k (its first state's gain in each component but the reference's) and
    feedthrough e: the same entries of A and B at orders 1 and 2."""
    law, base, nm = ef.law, ef.base, ef.channel.name
    n = base.nstates
    G = np.asarray(ef.channel.G, dtype=float)
    rows = _rows_of(base)
    out = []
    for c in range(law.k.size):
        if c == law.reference:
            continue
        dA = np.zeros((nf, nf))
        dA[:n, n] = G[:, c]
        out.append(_Param(i, ("k", c), dA, np.zeros((nf, m)), float(law.k[c]),
                          f"{nm}: {state} in {ef.channel.labels[c]}", False))
    for q, (c, dn, e) in enumerate(law.feedthrough):
        w = np.zeros(n + m)
        w[rows[dn]] = 1.0
        dA, dB = np.zeros((nf, nf)), np.zeros((nf, m))
        dA[:n, :n], dB[:n] = np.outer(G[:, c], w[:n]), np.outer(G[:, c], w[n:])
        out.append(_Param(i, ("e", q), dA, dB, float(e), f"{nm}: {ef.channel.labels[c]} {dn}",
                          True, group=None))
    return out


def _shared2_params(i: int, ef: JointEffect, nf: int, m: int) -> list[_Param]:
    """An order-q shared law's coefficients (observer canonical form, see
    :mod:`greybox.trace.shared_order2`): alpha (q), beta (one stays), k (not the
    reference's), e. Each moves one entry (or one outer product) of A and B."""
    law, base, nm = ef.law, ef.base, ef.channel.name
    n, q = base.nstates, law.order
    rows = _rows_of(base)
    out = []
    for r in range(q):
        dA = np.zeros((nf, nf))
        dA[n + r, n] = -1.0  # dz_1/dt = -alpha_1 z_1 + z_2 + ..., dz_q/dt = -alpha_0 z_1 + ...
        out.append(_Param(i, ("al", r), dA, np.zeros((nf, m)), float(law.alpha[r]),
                          f"{nm}: alpha_{q - 1 - r}", False))
    for r in range(q):
        for q, dn in enumerate(law.drivers):
            if law.beta[r, q] == 0:
                continue
            w = np.zeros(n + m)
            w[rows[dn]] = 1.0
            dA, dB = np.zeros((nf, nf)), np.zeros((nf, m))
            dA[n + r, :n], dB[n + r] = w[:n], w[n:]
            out.append(_Param(i, ("b", r, q), dA, dB, float(law.beta[r, q]),
                              f"{nm}: {law.states[r]} <- {dn}", True, group=(i, "b")))
    return out + _gain_params(i, ef, nf, m, law.states[0])


def _rows_of(base: ct.StateSpace) -> dict:
    """Row in ``[x; u]`` of every state and input name of ``base``."""
    names = list(base.state_labels) + list(base.input_labels)
    return {s: r for r, s in enumerate(names)}


class _Joint:
    """Output error on y of the final model with the parameters ``ps`` free."""

    def __init__(self, A0, B0, C, D, ps, dt, y, u, x0, k0):
        self.A0, self.B0, self.C, self.D, self.ps, self.dt = A0, B0, C, D, ps, dt
        self.x0, self.k0 = x0, k0
        self.engine = OutputError(self.cont, C, D, y, u, x0, k0, dt=dt)
        self.y, self.u, self.scale = self.engine.y, self.engine.u, self.engine.scale

    def cont(self, theta, active):
        A, B = self.A0.copy(), self.B0.copy()
        for q, t in zip(active, theta):
            A += t * self.ps[q].dA
            B += t * self.ps[q].dB
        return A, B

    def resid(self, theta, active):
        return self.engine.resid(theta, active)

    def se(self, theta, active) -> float:
        return self.engine.se(theta, active)

    def fit(self, theta0, active):
        return self.engine.fit(theta0, active, max_nfev=60 * (len(active) + 1))

    def halfwidths(self, sol, active, Q, R):
        return self.engine.halfwidths(sol, Q, R, active)


def refine_jointly(effects, final: ct.StateSpace, y: NDArray, u: NDArray, *, Q: NDArray,
                   R: NDArray, dt: float, x0: NDArray, k0: int) -> JointRefinement:
    """Refit every effect's coefficients at once by output error (see module docstring).

    Parameters
    ----------
    effects : sequence of JointEffect
        The effects in the order the loop added them.
    final : control.StateSpace
        The loop's final continuous model (all effects folded in).
    y, u : ndarray, shapes (noutputs, nsteps), (ninputs, nsteps)
        Estimation record.
    Q : ndarray, shape (nstates_final, nstates_final)
        Process-noise covariance of the final discrete model (intervals).
    R : ndarray, shape (noutputs, noutputs)
        Measurement-noise covariance.
    dt : float
        Sampling period [s].
    x0 : ndarray, shape (nstates_final,)
        Initial state of the output-error simulation.
    k0 : int
        First sample of the output-error window.

    Returns
    -------
    JointRefinement
    """
    nf, m = final.nstates, final.ninputs
    ps = _params(effects, nf, m)
    theta = np.array([p.value for p in ps])
    A0 = np.asarray(final.A, dtype=float) - sum(t * p.dA for t, p in zip(theta, ps))
    B0 = np.asarray(final.B, dtype=float) - sum(t * p.dB for t, p in zip(theta, ps))
    C, D = np.asarray(final.C, dtype=float), np.asarray(final.D, dtype=float)
    prob = _Joint(A0, B0, C, D, ps, dt, y, u, np.asarray(x0, dtype=float), k0)
    active, theta, merged = _independent(ps, theta)
    start = dict(zip(active, theta))
    with single_thread_blas():
        se0 = prob.se(theta, active)
        sol = prob.fit(theta, active)
        hw = prob.halfwidths(sol, active, Q, R)
        active, sol, hw, pruned = _prune(prob, ps, active, sol, hw, Q, R)
        dropped = list(merged) + pruned
        se1 = prob.se(sol.x, active)
    values = dict(zip(active, sol.x))
    halves = dict(zip(active, hw))
    moved = bool(dropped) or not all(np.isfinite(halves[a]) and
                                     abs(values[a] - start[a]) < halves[a] for a in active)
    laws = tuple(_rebuild(i, ef, ps, values, halves, y, u, Q, R, dt, k0, prob, merged)
                 for i, ef in enumerate(effects))
    Ac, Bc = prob.cont(sol.x, active)
    Ad, Bd = zoh(Ac, Bc, dt)
    kw = dict(states=final.state_labels, inputs=final.input_labels, outputs=final.output_labels,
              name=final.name)
    cont = named_ss(Ac, Bc, C, D, 0, **kw)
    disc = named_ss(Ad, Bd, C, D, dt, **kw)
    partials = []
    for k in range(1, len(effects)):  # the first k effects at their refitted values
        nk = effects[k].base.nstates
        th = np.array([t if ps[q].eff < k else 0.0 for q, t in zip(active, sol.x)])
        Ak, Bk = prob.cont(th, active)
        # the outputs as the first k effects read them (a later sensor lag rereads one)
        Ck, Dk = (np.asarray(effects[k].base.C, dtype=float),
                  np.asarray(effects[k].base.D, dtype=float))
        partials.append(named_ss(Ak[:nk, :nk], Bk[:nk], Ck, Dk, 0,
                                 states=final.state_labels[:nk], inputs=final.input_labels,
                                 outputs=final.output_labels, name=final.name))
    return JointRefinement(laws=laws, continuous=cont,
                           model=UpdatedModel(sys=disc, Q=Q, R=R, order=nf, kind="joint"),
                           se_before=se0, se_after=se1, npar_before=len(ps),
                           npar_after=len(active), dropped=tuple(dropped),
                           partials=tuple(partials), moved=moved)


def _independent(ps, theta):
    """Keep the coefficients whose (dA, dB) are independent of the earlier ones'.

    Two effects can hold the same term (a static law's ``p1`` and a dynamic
    law's feedthrough of ``p1`` both add to the same entry of A): the later
    one's value is folded into the earlier ones (the model is unchanged) and
    it is dropped. Returns ``(active, theta_active, merged names)``.
    """
    V = np.array([np.r_[p.dA.ravel(), p.dB.ravel()] for p in ps]).T  # (entries, k)
    keep, merged = [], []
    vals = {}
    for q, t in enumerate(theta):
        if keep:
            K = V[:, keep]
            c, *_ = np.linalg.lstsq(K, V[:, q], rcond=None)
            if np.linalg.norm(K @ c - V[:, q]) <= 1e-9 * np.linalg.norm(V[:, q]):
                for i, ci in zip(keep, c):
                    vals[i] += t * ci
                merged.append(f"{ps[q].name} (the same term as an earlier effect's)")
                continue
        keep.append(q)
        vals[q] = t
    return keep, np.array([vals[q] for q in keep]), merged


# A drop's refit may raise the squared output error by at most this many times the
# local (Gauss-Newton) prediction of fixing the term at 0, plus 1e-6 of it: more means
# the refit left the fit's basin (a collapse), and the term is kept.
_COLLAPSE = 3.0


def _prune(prob, ps, active, sol, hw, Q, R):
    """Drop the weakest prunable term whose interval contains 0, refit; repeat.

    A drop whose refit raises the squared output error far above the local
    prediction ``theta_q^2 / [(J^T J)^-1]_qq`` (``_COLLAPSE`` times) is undone
    and its term kept: the refit fell into another minimum, which a term inside
    its interval cannot justify (the loop once ended with a fit worse than the
    unpruned one, kept only because the workflow rejects a worse refit).
    Returns ``(active, sol, hw, dropped names)``.
    """
    dropped, kept = [], set()
    while True:
        t = np.abs(sol.x) / np.where(np.isfinite(hw) & (hw > 0), hw, np.inf)
        weak = [q for q in range(len(active)) if ps[active[q]].prunable and t[q] < 1.0
                and active[q] not in kept and not _last_of_effect(ps, active, q)]
        if not weak:
            return active, sol, hw, dropped
        q = min(weak, key=lambda q: t[q])
        keep = [i for i in range(len(active)) if i != q]
        new = prob.fit(sol.x[keep], [active[i] for i in keep])
        rss0, rss1 = float(np.sum(sol.fun ** 2)), float(np.sum(new.fun ** 2))
        JtJ = sol.jac.T @ sol.jac
        inv_qq = float(np.linalg.pinv(JtJ)[q, q])
        pred = sol.x[q] ** 2 / inv_qq if inv_qq > 0 else np.inf
        if not rss1 - rss0 <= _COLLAPSE * pred + 1e-6 * rss0:
            kept.add(active[q])
            continue
        dropped.append(ps[active[q]].name)
        active = [active[i] for i in keep]
        sol, hw = new, prob.halfwidths(new, active, Q, R)


def _last_of_effect(ps, active, q) -> bool:
    """True if ``active[q]`` is the last prunable coefficient left of its group.

    The group is the effect (one of its terms stays), or the drivers of a shared
    state (one stays); a shared law's feedthrough terms may all go.
    """
    grp = ps[active[q]].group
    if grp is None:
        return False
    return sum(1 for i in active if ps[i].group == grp and ps[i].prunable) <= 1


def _rebuild(i, ef, ps, values, halves, y, u, Q, R, dt, k0, prob, merged=()):
    """The effect's law record at the jointly refitted values (``merged``: the names
    :func:`_independent` folded into an earlier effect's same term)."""
    law, ch, base = ef.law, ef.channel, ef.base
    mine = [(q, p) for q, p in enumerate(ps) if p.eff == i]
    if _is_held(law):
        return law
    if _is_lag(law):  # tau = 1 / a; its half-width by the delta method, h_a / a^2
        a, ha = values[mine[0][0]], halves[mine[0][0]]
        tau, htau = 1.0 / a, ha / a ** 2
        return replace(law, coef=np.array([[tau]]), ci=np.array([[htau]]),
                       formula=f"{ch.output} = {ch.output}_model / (tau s + 1), tau = "
                               f"({tau:.4g} ± {htau:.2g}) [s]")
    if isinstance(law, StaticLaw):
        coef = np.zeros_like(law.coef)
        half = np.full_like(law.coef, np.nan)
        for q, p in mine:
            if q in values:
                _, c, j = p.key
                coef[p.key[1], p.key[2]] = values[q]
                half[c, j] = halves[q]
        Ddx, Ddu = linear_part(law.spec, coef, base.nstates, base.ninputs)
        lines = []
        for c in range(coef.shape[0]):
            idx = list(np.flatnonzero(coef[c]))
            unit = ch.units[c] if c < len(ch.units) else ""
            lines.append(law_line(ch.labels[c], coef[c, idx], [law.spec[j][0] for j in idx],
                                   unit, half[c, idx]))
        if "one direction" in law.formula:
            Ad, Bd = zoh(np.asarray(base.A, float), np.asarray(base.B, float), dt)
            uw = u[:, :prob.y.shape[1]]
            x = lti_states(Ad, Bd @ uw, np.zeros(base.nstates))
            lines += _one_direction(coef, law.term_scale(x, u[:, :x.shape[1]]), ch.labels)
        return replace(law, coef=coef, ci=half, Ddx=Ddx, Ddu=Ddu, formula="; ".join(lines),
                       npar=int(np.count_nonzero(coef)))
    if isinstance(law, SharedLaw):
        return _rebuild_shared(ef, mine, values, halves, y, u, Q, R, dt, k0, prob)
    if isinstance(law, SharedLaw2):
        return _rebuild_shared2(ef, mine, values, halves, y, u, Q, R, dt, k0, prob)
    # dynamic: keep the drivers whose gains are left
    a = values[next(q for q, p in mine if p.key == ("a",))]
    ha = halves[next(q for q, p in mine if p.key == ("a",))]
    n = base.nstates
    drv, b, e, hb, he = [], [], [], [], []
    for k, wq in enumerate(law.weights):
        qb = next(q for q, p in mine if p.key == ("b", k))
        qe = next(q for q, p in mine if p.key == ("e", k))
        if qb not in values and qe not in values:
            continue
        drv.append(_driver_of(wq, n))
        b.append(values.get(qb, 0.0))
        e.append(values.get(qe, 0.0))
        hb.append(halves.get(qb, np.nan))
        he.append(halves.get(qe, np.nan))
    if not any(q in values for q, p in mine if p.key[0] == "b"):
        # every driver's lag dropped: the feedthrough left is a static law
        return _feedthrough_law(base, ch, drv, e, he)
    dprob = _problem(base, ch, y, u, dt, _x0_of(prob, n), k0, drv)
    Qb = Q[:n, :n]
    # a feedthrough merged into an earlier effect's same term: the input's path through
    # the plant is no longer this law alone, so its formula does not say it
    held = any(p.key[0] == "e" and q not in values and
               f"{p.name} (the same term as an earlier effect's)" in merged for q, p in mine)
    return _law_from(base, ch, dprob, drv, np.r_[a, b, e], np.r_[ha, hb, he], Qb, R,
                     reach=not held)


def _feedthrough_law(base: ct.StateSpace, ch: Channel, drv, e, he) -> StaticLaw:
    """The static law a first-order law leaves when the joint refit dropped every driver's
    lag: its feedthrough terms, a continuous-time linear law of the channel's first
    component of d (where the first-order law's gain enters), with their intervals."""
    spec = [(_driver_name(base, d), {"x": "x", "u": "u", "r": "rel"}[d[0]],
             (*d[1], 0) if d[0] == "r" else d[1]) for d in drv]  # rel: (i, j, eps index)
    coef = np.zeros((ch.md, len(spec)))
    half = np.full_like(coef, np.nan)
    coef[0], half[0] = e, he
    Ddx, Ddu = linear_part(spec, coef, base.nstates, base.ninputs)
    kept = np.flatnonzero(coef[0])
    formula = law_line(ch.labels[0], coef[0, kept], [spec[j][0] for j in kept],
                       ch.units[0] if ch.units else "", half[0, kept])
    return StaticLaw(spec=tuple(spec), eps=np.zeros(1), coef=coef, Ddx=Ddx, Ddu=Ddu,
                     nonlinear=False, residual_var=np.full(ch.md, np.nan), bic_gain=np.nan,
                     npar=int(kept.size), formula=formula, ci=half, time_base="continuous")


def _integrated(law: DynamicLaw, A: NDArray, B: NDArray) -> tuple | None:
    """``(pos, terms)``: the weights ``pos`` (n,) on the states with ``integral(sum_k b_k
    driver_k) = pos @ x`` and each gain's position term ``(driver, b_k / c, h_k / |c|)``,
    where every driver a gain drives is a velocity (or two velocities' difference) whose
    position is a state (a kinematic identity ``dp/dt = c x_i``, no input in row p;
    one c for both of a difference); None otherwise."""
    n, K = A.shape[0], len(law.drivers)
    pos, terms = np.zeros(n), []
    for wq, bk, h in zip(law.weights, law.b, law.ci[1:1 + K]):
        if bk == 0:
            continue
        d = _driver_of(wq, n)
        idx = (d[1],) if d[0] == "x" else d[1] if d[0] == "r" else ()
        ps = [kinematic_partner(A, i) for i in idx]
        if not idx or any(p is None or np.any(B[p]) for p in ps) or \
                len({A[p, i] for p, i in zip(ps, idx)}) != 1:
            return None
        c = A[ps[0], idx[0]]
        for p, i in zip(ps, idx):
            pos[p] += bk * wq[i] / c
        terms.append((("x", ps[0]) if d[0] == "x" else ("r", tuple(ps)), bk / c,
                      float(h) / abs(c)))
    return pos, terms


def _position_law(ef, law: DynamicLaw, terms) -> StaticLaw:
    """The static law of the positions ``terms`` (:func:`_integrated`) beside the law's
    feedthrough terms (a position both hold: their coefficients added, their half-widths
    in quadrature)."""
    n, K = ef.base.nstates, len(law.drivers)
    out = {}  # driver -> [coefficient, half-width]
    for wq, e, h in zip(law.weights, law.e, law.ci[1 + K:]):
        if e != 0:
            out[_driver_of(wq, n)] = [float(e), float(h)]
    for d, c, h in terms:
        t = out.setdefault(d, [0.0, 0.0])
        t[0], t[1] = t[0] + c, float(np.hypot(t[1], h))
    drv = list(out)
    return _feedthrough_law(ef.base, ef.channel, drv, [out[d][0] for d in drv],
                            [out[d][1] for d in drv])


def integrators_as_positions(jr: JointRefinement, effects, dt: float) -> JointRefinement:
    """``jr`` with each first-order law of state equations whose pole's 95 % interval holds
    0 and whose gains drive velocities only, stated as the static law of their positions:
    ``b / s * v = (b / c) * p`` where ``dp/dt = c v`` (a kinematic identity), one parameter
    (the pole) fewer. Zoo two_static: a missing stiffness to ground was named ``-29.6 /
    (s - (2.9e-05 +- 0.0017)) * v5``. The law's state is left an orphan (its column
    zeroed; :func:`without_dead_states` cuts it); the partial models that hold it get the
    same change. ``jr`` itself where no law qualifies; the caller compares the two by its
    criterion (the pole at 0 against its fitted value)."""
    counts = [ef.base.nstates for ef in effects] + [jr.continuous.nstates]
    laws, dropped = list(jr.laws), list(jr.dropped)
    models = [jr.continuous, *jr.partials]
    for k, (ef, law) in enumerate(zip(effects, jr.laws)):
        zi = counts[k]
        if not isinstance(law, DynamicLaw) or counts[k + 1] - zi != 1 or \
                ef.channel.kind != "equation" or not abs(law.pole) <= law.ci[0]:
            continue
        found = _integrated(law, np.asarray(ef.base.A, dtype=float),
                            np.asarray(ef.base.B, dtype=float))
        Af = np.asarray(jr.continuous.A, dtype=float)
        if found is None or np.any(Af[zi + 1:, zi]) or \
                np.any(np.asarray(jr.continuous.C, dtype=float)[:, zi]):
            continue  # z feeds a later effect or a sensor: not the law's alone
        pos, terms = found
        for q, sys in enumerate(models):
            if sys.nstates <= zi:
                continue
            A = np.array(sys.A, dtype=float)
            A[:zi, :zi] += np.outer(A[:zi, zi], pos)  # pos: the base's zi states
            A[:zi, zi] = 0.0
            models[q] = named_ss(A, sys.B, sys.C, sys.D, 0, states=sys.state_labels,
                                 inputs=sys.input_labels, outputs=sys.output_labels,
                                 name=sys.name)
        laws[k] = _position_law(ef, law, terms)
        dropped.append(f"{ef.channel.name}: the pole (an integrator of velocities is the law "
                       f"of their positions)")
    if all(a is b for a, b in zip(laws, jr.laws)):
        return jr
    cont = models[0]
    Ad, Bd = zoh(np.asarray(cont.A, dtype=float), np.asarray(cont.B, dtype=float), dt)
    disc = named_ss(Ad, Bd, cont.C, cont.D, dt, states=cont.state_labels,
                    inputs=cont.input_labels, outputs=cont.output_labels, name=cont.name)
    return replace(jr, laws=tuple(laws), continuous=cont, partials=tuple(models[1:]),
                   model=replace(jr.model, sys=disc), dropped=tuple(dropped), moved=True,
                   npar_after=jr.npar_after - sum(a is not b for a, b in zip(laws, jr.laws)))


def without_dead_states(jr: JointRefinement, effects) -> JointRefinement:
    """``jr`` with the states no effect drives any more taken out of the final model: a
    first-order law left static by the refit (no driver's lag kept:
    :func:`_feedthrough_law`) leaves its state behind, here or in a later refit of the same
    effects (the state then sits in the next effect's base). A law of the state equations
    that is static adds no state, so the states between its base and the next effect's
    (or the final model's) are such orphans: nothing drives them; from 0 they stay 0, and
    they sit below the states they fed (block-triangular), so the other states' discrete
    matrices are unchanged. The partial models keep them (a later effect's state indices
    count them). A sensor law's states (an offset, a drift, a lag) are never touched."""
    counts = [ef.base.nstates for ef in effects] + [jr.continuous.nstates]
    dead = set()
    for k, law in enumerate(jr.laws):
        if isinstance(law, StaticLaw) and law.output is None:
            dead |= set(range(counts[k], counts[k + 1]))
    if not dead:
        return jr
    keep = [k for k in range(jr.continuous.nstates) if k not in dead]

    def cut(sys):
        A, B, C = (np.asarray(a, dtype=float) for a in (sys.A, sys.B, sys.C))
        return named_ss(A[np.ix_(keep, keep)], B[keep], C[:, keep], sys.D, sys.dt,
                        states=[sys.state_labels[k] for k in keep], inputs=sys.input_labels,
                        outputs=sys.output_labels, name=sys.name)

    m = jr.model
    return replace(jr, continuous=cut(jr.continuous),
                   model=replace(m, sys=cut(m.sys), Q=np.asarray(m.Q)[np.ix_(keep, keep)],
                                 order=len(keep)))


def _kept(ef, mine, values, halves, keys):
    """A shared law's kept coefficients: ``(theta, half-widths, b drivers, e terms)``.

    theta and the half-widths are ordered by ``keys`` (the law problem's order); a b
    term is ``(row, driver)`` for an order-2 or 3 law (key ``("b", row, q)``), the driver
    for a first-order one; an e term is ``(component, driver)``.
    """
    law, base = ef.law, ef.base
    nm, im = list(base.state_labels), list(base.input_labels)

    def drv(name):
        return ("x", nm.index(name)) if name in nm else ("u", im.index(name))

    th, hw, bterms, eterms = {}, {}, [], []
    for q, p in mine:
        if q not in values:
            continue
        kind = p.key[0]
        th.setdefault(kind, []).append(values[q])
        hw.setdefault(kind, []).append(halves[q])
        if kind == "b":
            d = drv(law.drivers[p.key[-1]])
            bterms.append((p.key[1], d) if len(p.key) == 3 else d)
        elif kind == "e":
            c, dn, _ = law.feedthrough[p.key[1]]
            eterms.append((c, drv(dn)))
    theta = np.concatenate([np.asarray(th.get(k, []), dtype=float) for k in keys])
    half = np.concatenate([np.asarray(hw.get(k, []), dtype=float) for k in keys])
    return theta, half, bterms, eterms


def _rebuild_shared(ef, mine, values, halves, y, u, Q, R, dt, k0, prob):
    """A shared-state law's record at the jointly refitted values (dropped terms left out)."""
    law, ch, base = ef.law, ef.channel, ef.base
    n = base.nstates
    theta, half, bdrv, eterms = _kept(ef, mine, values, halves, ("a", "b", "k", "e"))
    sprob = _shared_problem(base, ch, y, u, dt, _x0_of(prob, n), k0, bdrv, eterms,
                            law.reference)
    return _shared_law_from(base, ch, sprob, theta, half, Q[:n, :n], R)


def _rebuild_shared2(ef, mine, values, halves, y, u, Q, R, dt, k0, prob):
    """An order-q shared law's record at the jointly refitted values (dropped terms left
    out). The coefficients' half-widths are the joint fit's; the poles' come from the law's
    own output-error Jacobian at those values (the other effects held), as
    :func:`greybox.trace.shared_order2.fit_shared_order2` gives them."""
    law, ch, base = ef.law, ef.channel, ef.base
    n = base.nstates
    theta, half, bterms, eterms = _kept(ef, mine, values, halves, ("al", "b", "k", "e"))
    sprob = _Shared2Problem(base, ch, y, u, dt, _x0_of(prob, n), k0, bterms, eterms,
                            law.reference, order=law.order)
    r0 = sprob.resid(theta)
    jac = np.empty((r0.size, theta.size))
    for j in range(theta.size):  # forward differences, as least_squares' default
        h = 1e-7 * max(1.0, abs(theta[j]))
        tj = theta.copy()
        tj[j] += h
        jac[:, j] = (sprob.resid(tj) - r0) / h
    sol = SimpleNamespace(x=theta, fun=r0, jac=jac)
    return _shared2_law_from(base, ch, sprob, sol, half, Q[:n, :n], R)


def _driver_of(wq, n):
    """The driver tuple of a weight row (see greybox.trace.dynamic.driver_weights)."""
    nz = np.flatnonzero(wq)
    if nz.size == 2:  # x_j - x_i
        i, j = (int(nz[0]), int(nz[1])) if wq[nz[1]] > 0 else (int(nz[1]), int(nz[0]))
        return ("r", (i, j))
    r = int(nz[0])
    return ("x", r) if r < n else ("u", r - n)


def _x0_of(prob, n):
    return prob.x0[:n]


def joint_effect(base: ct.StateSpace, channel: Channel, law) -> JointEffect | None:
    """The effect as the joint refinement takes it, or None if it cannot be refitted.

    Continuous-time linear static laws, sparse first-order laws and shared-state
    laws of order 1 and 2 qualify; a sensor lag (its time constant refitted), and a
    linear static sensor law (a gain and an offset state: held at its value).
    """
    if channel.kind == "output":  # a sensor law acts on C and D: only a lag has a state
        # (a static sensor law that is linear, a gain and an offset state, is held)
        ok = _is_lag(law) or (_is_held(law) and not law.nonlinear)
        return JointEffect(base=base, channel=channel, law=law) if ok and \
            not ct.isdtime(base, strict=True) else None
    if isinstance(law, DynamicLaw) and channel.md == 1:
        return JointEffect(base=base, channel=channel, law=law)
    if isinstance(law, (SharedLaw, SharedLaw2)) and channel.md == law.k.size:
        return JointEffect(base=base, channel=channel, law=law)
    if isinstance(law, StaticLaw) and law.time_base == "continuous" and not law.nonlinear:
        return JointEffect(base=base, channel=channel, law=law)
    return None
