"""Close the loop on a fleet of units of one design, in parallel on Dask.

One nominal model (MODEL.json or MODEL.py) and one estimation and one
validation record per unit: :func:`fleet` runs :func:`greybox.close_the_loop`
for every unit as one Dask task, writes each unit's result as it arrives and
summarizes the fleet: which units deviate from the model, grouped by the
explanation found (same equations, kind, order and law terms), the spread of
each coefficient across a group's units, the units whose model is right, and
one line for every unit that could not be done.

Records (``records``):

- a folder with one sub-folder per unit (its name is the unit's name), each
  holding ``estimation.csv`` and ``validation.csv`` (the CSV format of
  :func:`greybox.model_io.read_csv`); or
- a manifest CSV with the header ``unit,estimation,validation`` and one row
  per unit (paths relative to the manifest's folder, or absolute).

Output folder (``out``)::

    out/units/<unit>.json   each unit's result, written (atomically) as it arrives
    out/fleet.json          the fleet report (strict JSON)
    out/fleet.md            the fleet report (markdown), opening with the answer
    out/coefficients.png    strip plots of each group's coefficients

A rerun skips the units whose result says "done" for the same input files
(sizes and modification times) and settings, unless ``force``; failed units
are tried again. Ctrl-C keeps every unit written so far.

Dask (``pip install "greybox[fleet]"``) is imported only when :func:`fleet`
runs: ``import greybox`` does not import it. By default a ``LocalCluster``
with one single-threaded worker process per core (BLAS held to one thread
per worker) runs the tasks; pass ``client`` (a ``distributed.Client`` or a
scheduler address) to use an existing cluster, whose workers must have
greybox installed and see the model and record files under the same paths.
Each task receives four paths and reads its own files: the task and its
result are a few kilobytes whatever the records' length.
"""

from __future__ import annotations

import contextlib
import csv
import functools
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._validation import check_positive
from .exceptions import DataError, MissingDependencyError
from .progress import Progress

__all__ = ["FleetReport", "UnitResult", "ExplanationGroup", "CoefficientSpread", "UnitFiles",
           "fleet", "find_units", "run_unit", "summarize", "effect_terms", "explanation_key",
           "group_units", "fleet_answer", "fleet_markdown", "EXIT_FAILED", "OUTLIER_Z"]

#: Exit code of ``greybox fleet`` when some units failed (the others are reported).
EXIT_FAILED = 3
#: Modified z-score above which a coefficient is a robust outlier (Iglewicz and Hoaglin):
#: ``|x - median| > OUTLIER_Z * 1.4826 * MAD``.
OUTLIER_Z = 3.5
_MAD_TO_STD = 1.4826
_STATUSES = ("done", "failed", "skipped (done before)")
_BLAS_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


# ----------------------------------------------------------------------------- records
@dataclass(frozen=True)
class UnitFiles:
    """One unit's input files.

    Attributes
    ----------
    name : str
        The unit's name (its sub-folder, or the manifest's ``unit``).
    estimation, validation : pathlib.Path
        Its estimation and validation CSV files (absolute paths).
    """

    name: str
    estimation: Path
    validation: Path


@dataclass(frozen=True)
class UnitResult:
    """What close the loop found on one unit.

    Attributes
    ----------
    unit : str
        The unit's name.
    status : str
        "done", "failed" or "skipped (done before)" (read back from its file).
    verdict : str
        "deviates" (an effect was found and added), "right" (the nominal
        residuals are white), "unexplained" (a model error was detected but no
        candidate passed the gates), or "" for a failed unit.
    message : str
        The one-sentence conclusion of :func:`greybox.close_the_loop`.
    error : str
        One line saying why a failed unit could not be done ("" otherwise).
    effects : tuple of str
        One line per effect added: equations, kind, order and law.
    se_before, se_after : float
        Validation SE [%] (eq. 42) of the nominal and the updated model (NaN
        when undefined or failed).
    explanation : tuple of (tuple of str, str, int, tuple of str)
        Per effect: the equations it enters, its kind, its order and the
        names of its law's terms, without coefficients. Units with equal
        explanations form one group.
    coefficients : tuple of (str, float)
        The law's coefficients by term name (prefixed "k: " for the k-th
        effect when there are several), in the units of the equations (for a
        force in eq(v2) on positions: [m/s^2 per m]).
    seconds, cpu_seconds : float
        Wall time and CPU time of the unit's task [s] (a worker runs one
        thread: the CPU time is the unit's cost on an idle core).
    """

    unit: str
    status: str
    verdict: str = ""
    message: str = ""
    error: str = ""
    effects: tuple[str, ...] = ()
    se_before: float = float("nan")
    se_after: float = float("nan")
    explanation: tuple = ()
    coefficients: tuple[tuple[str, float], ...] = ()
    seconds: float = float("nan")
    cpu_seconds: float = float("nan")

    @property
    def key(self) -> str:
        """The explanation as one readable line (the group's name)."""
        return explanation_key(self.explanation)

    def as_dict(self) -> dict:
        """JSON-ready record (the fields; ``explanation`` as a list of objects)."""
        return {"unit": self.unit, "status": self.status, "verdict": self.verdict,
                "message": self.message, "error": self.error, "effects": list(self.effects),
                "se_before": self.se_before, "se_after": self.se_after,
                "explanation": [{"equations": list(e), "kind": k, "order": o, "terms": list(t)}
                                for e, k, o, t in self.explanation],
                "group": self.key, "coefficients": dict(self.coefficients),
                "seconds": self.seconds, "cpu_seconds": self.cpu_seconds}

    @classmethod
    def from_dict(cls, d: dict, *, status: str | None = None) -> UnitResult:
        """The record of :meth:`as_dict` (null numbers read back as NaN)."""
        def num(v):
            return float("nan") if v is None else float(v)

        expl = tuple((tuple(e["equations"]), str(e["kind"]), int(e["order"]),
                      tuple(e["terms"])) for e in d.get("explanation", ()))
        return cls(unit=str(d["unit"]), status=status or str(d["status"]),
                   verdict=str(d.get("verdict", "")), message=str(d.get("message", "")),
                   error=str(d.get("error", "")), effects=tuple(d.get("effects", ())),
                   se_before=num(d.get("se_before")), se_after=num(d.get("se_after")),
                   explanation=expl,
                   coefficients=tuple((str(k), num(v))
                                      for k, v in (d.get("coefficients") or {}).items()),
                   seconds=num(d.get("seconds")), cpu_seconds=num(d.get("cpu_seconds")))


def explanation_key(explanation) -> str:
    """One line naming an explanation: ``"eq(v2) static: p2"``, effects joined by " + "."""
    parts = []
    for eqs, kind, order, terms in explanation:
        o = f" order {order}" if order else ""
        parts.append(f"eq({','.join(eqs)}) {kind}{o}: {', '.join(terms) or '-'}")
    return " + ".join(parts)


def _safe_name(name: str, where) -> str:
    bad = (not name or name in (".", "..") or name.startswith(".") or
           any(c in name for c in "/\\\0") or name != name.strip())
    if bad:
        raise DataError(f"{where}: unit name {name!r} cannot name a file; use letters, digits, "
                        f"'-', '_' (no path separator, no leading dot)")
    return name


def _read_manifest(path: Path) -> list[UnitFiles]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"cannot read the manifest {path}: {e}") from e
    rows = list(csv.reader(text.splitlines()))
    head = [h.strip() for h in rows[0]] if rows else []
    want = ["unit", "estimation", "validation"]
    if sorted(head) != sorted(want):
        raise DataError(f"{path}: manifest header {head}; expected {want} (one row per unit)")
    col = {h: head.index(h) for h in want}
    units = []
    for i, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        if len(row) != 3:
            raise DataError(f"{path}, line {i}: {len(row)} fields; expected 3 "
                            f"(unit,estimation,validation)")
        name = _safe_name(row[col["unit"]].strip(), f"{path}, line {i}")
        files = [Path(row[col[k]].strip()) for k in ("estimation", "validation")]
        files = [(f if f.is_absolute() else path.parent / f).absolute() for f in files]
        units.append(UnitFiles(name, *files))
    return units


def find_units(records, *, exclude=None) -> tuple[UnitFiles, ...]:
    """The units of a records folder or manifest (see the module docstring).

    Parameters
    ----------
    records : str or path-like
        A folder with one sub-folder per unit (``estimation.csv``,
        ``validation.csv``; hidden sub-folders are ignored), or a manifest CSV
        ``unit,estimation,validation``.
    exclude : str or path-like, optional
        A folder not to take as a unit (the output folder, when it lies
        inside ``records``).

    Returns
    -------
    tuple of UnitFiles
        Sorted by name. A unit's files are not opened here: a missing or bad
        file fails that unit alone.

    Raises
    ------
    DataError
        ``records`` does not exist, holds no unit, names a unit twice, or a
        unit name cannot name a file.
    """
    p = Path(records)
    if p.is_dir():
        skip = Path(exclude).absolute() if exclude is not None else None
        units = [UnitFiles(d.name, (d / "estimation.csv").absolute(),
                           (d / "validation.csv").absolute())
                 for d in sorted(p.iterdir()) if d.is_dir() and not d.name.startswith(".")
                 and d.absolute() != skip]
    elif p.is_file():
        units = _read_manifest(p)
    else:
        raise DataError(f"{p}: no such folder or manifest; give a folder with one sub-folder "
                        f"per unit (estimation.csv, validation.csv) or a manifest CSV "
                        f"unit,estimation,validation")
    if not units:
        raise DataError(f"{p} holds no unit: expected one sub-folder per unit with "
                        f"estimation.csv and validation.csv (or manifest rows)")
    names = [u.name for u in units]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise DataError(f"{p}: unit name(s) {twice} appear more than once; name each unit once")
    for u in units:
        _safe_name(u.name, p)
    return tuple(sorted(units, key=lambda u: u.name))


# ----------------------------------------------------------------------------- the task
class _UnitTimeout(Exception):
    """A unit ran past its time limit (raised at a stage boundary of close the loop)."""


def _deadline(timeout):
    """A progress callback raising :class:`_UnitTimeout` once ``timeout`` seconds are over."""
    if timeout is None:
        return None
    end = time.monotonic() + float(timeout)

    def check(p: Progress) -> None:
        if time.monotonic() > end:
            raise _UnitTimeout(f"timeout: still running after {timeout:g} s (at stage "
                               f"'{p.stage}'); allow more with --timeout")
    return check


def _stat(path) -> list:
    """[size, modification time in ns] of a file, or None when it cannot be read."""
    try:
        s = os.stat(path)
    except OSError:
        return None
    return [s.st_size, s.st_mtime_ns]


def _fingerprint(model, unit: UnitFiles, delta: bool) -> dict:
    return {"model": _stat(model), "estimation": _stat(unit.estimation),
            "validation": _stat(unit.validation), "delta": bool(delta)}


@functools.lru_cache(maxsize=4)
def _model(path: str, stamp: tuple):
    """The model file, read once per worker process (``stamp``: size, mtime)."""
    from .model_io import read_model

    return read_model(path)


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    if isinstance(e, _UnitTimeout):
        return text
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def run_unit(model: str, unit: str, estimation: str, validation: str, *, delta: bool = False,
             timeout: float | None = None) -> dict:
    """Close the loop on one unit (one Dask task): read its files, run, summarize.

    Parameters
    ----------
    model : str
        Path of MODEL.json or MODEL.py (read once per worker process).
    unit : str
        The unit's name.
    estimation, validation : str
        Paths of its CSV files.
    delta : bool
        Fit the parallel delta baseline (a comparison row; off by default).
    timeout : float, optional
        Give up after this many seconds [s]; checked at every stage boundary
        of close the loop (each candidate channel), so a unit stops within
        one stage of the limit.

    Returns
    -------
    dict
        :meth:`UnitResult.as_dict` with status "done" plus ``"report"`` (the
        :meth:`greybox.LoopReport.as_dict` document), or status "failed" and
        the one-line ``error``; ``"warnings"`` lists the warnings raised (one
        line each). Never raises for a bad unit.
    """
    import warnings

    from ._blas import single_thread_blas
    from .model_io import read_csv
    from .workflow import close_the_loop

    t0, c0 = time.perf_counter(), time.process_time()
    caught, rep = [], None
    try:
        with single_thread_blas(), warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            spec = _model(str(model), tuple(_stat(model) or ()))
            ins, outs = list(spec.sys.input_labels), list(spec.sys.output_labels)
            y, u = read_csv(estimation, inputs=ins, outputs=outs, Ts=spec.Ts)
            yv, uv = read_csv(validation, inputs=ins, outputs=outs, Ts=spec.Ts, min_steps=100)
            rep = close_the_loop(spec.sys, y, u, yv, uv, Q=spec.Q, R=spec.R, dt=spec.Ts,
                                 channels=spec.channels, delta=delta,
                                 progress=_deadline(timeout))
        res = summarize(rep, unit)
    except Exception as e:  # noqa: BLE001 - a unit's failure is data (timeout too)
        res, rep = UnitResult(unit, "failed", error=_one_line(e)), None
    notes = list(dict.fromkeys(" ".join(str(w.message).split()) for w in caught))
    return {**res.as_dict(), "seconds": time.perf_counter() - t0,
            "cpu_seconds": time.process_time() - c0, "warnings": notes,
            **({"report": rep.as_dict()} if rep is not None else {})}


# ----------------------------------------------------------------------------- summary
def _static_terms(law, equations) -> list[tuple[str, float]]:
    coef = np.atleast_2d(np.asarray(law.coef, dtype=float))
    md = coef.shape[0]
    out = []
    for r in range(md):
        where = "" if md == 1 else f" in d_{equations[r] if len(equations) == md else r}"
        out += [(f"{law.spec[j][0]}{where}", float(coef[r, j]))
                for j in np.flatnonzero(coef[r])]
    return out


def _dynamic_terms(law, equations) -> list[tuple[str, float]]:
    """Term names and coefficients of a DynamicLaw, SharedLaw or SharedLaw2."""
    out = []
    if hasattr(law, "alpha"):  # SharedLaw2: s^q + alpha_1 s^(q-1) + ...
        q = len(law.alpha)
        out += [(f"alpha_{q - 1 - i}", float(a)) for i, a in enumerate(law.alpha)]
        beta = np.atleast_2d(law.beta)
        out += [(f"{d}: beta_{q - 1 - i}", float(beta[i, j])) for j, d in enumerate(law.drivers)
                for i in range(beta.shape[0]) if beta[i, j] != 0]
    else:
        out.append(("pole [1/s]", float(law.pole)))
        feed = np.zeros(len(law.drivers)) if not hasattr(law, "e") else law.e
        out += [(f"{d}/(s-a)", float(b)) for d, b in zip(law.drivers, law.b) if b != 0]
        out += [(d, float(e)) for d, e in zip(law.drivers, feed) if e != 0]
    if hasattr(law, "k"):  # shared by the components: their gains and feedthroughs
        out += [(f"gain in d_{equations[c] if c < len(equations) else c}", float(k))
                for c, k in enumerate(law.k) if c != law.reference]
        out += [(f"{d} in d_{equations[c] if c < len(equations) else c}", float(e))
                for c, d, e in law.feedthrough]
    return out


def effect_terms(effect) -> list[tuple[str, float]]:
    """(term name, coefficient) of an :class:`greybox.Effect`'s law.

    A static law: its selected terms (``"p2"``, ``"(p2-p1)"``; ``" in d_v1"``
    appended when the channel has several components). A first-order law:
    ``"pole [1/s]"``, its filtered drivers ``"x/(s-a)"`` and feedthroughs; a
    shared subsystem also its gains; an unstructured subsystem: its order only
    (no coefficient named), as for refitted nominal parameters.
    """
    if effect.dynamic_law is not None:
        return _dynamic_terms(effect.dynamic_law, effect.equations)
    if effect.law is not None:
        return _static_terms(effect.law, effect.equations)
    if effect.kind == "dynamic":
        return [(f"subsystem of order {effect.order}", float("nan"))]
    return [(effect.kind, float("nan"))]


def summarize(report, unit: str) -> UnitResult:
    """A :class:`UnitResult` (status "done") from one unit's :class:`greybox.LoopReport`.

    Parameters
    ----------
    report : greybox.LoopReport
        The unit's close-the-loop report.
    unit : str
        The unit's name.

    Returns
    -------
    UnitResult
    """
    table = report.table

    def se(row):
        v = table.get(row)
        return float(v.se.value) if v is not None and v.se_defined else float("nan")

    if not report.model_error_detected:
        verdict = "right"
    else:
        verdict = "deviates" if report.updated else "unexplained"
    effects = [st.effect for st in report.steps] if report.steps else (
        [report.effect] if report.updated else [])
    lines, expl, coefs = [], [], []
    for i, eff in enumerate(effects):
        o = f" order {eff.order}" if eff.order else ""
        lines.append(f"eq({','.join(eff.equations)}) {eff.kind}{o}: {eff.formula}")
        terms = effect_terms(eff)
        expl.append((tuple(eff.equations), eff.kind, int(eff.order),
                     tuple(name for name, _ in terms)))
        pre = f"{i + 1}: " if len(effects) > 1 else ""
        coefs += [(pre + name, v) for name, v in terms if math.isfinite(v)]
    return UnitResult(unit, "done", verdict=verdict, message=report.message,
                      effects=tuple(lines), se_before=se("nominal"),
                      se_after=se("updated") if report.updated else se("nominal"),
                      explanation=tuple(expl), coefficients=tuple(coefs))


# ----------------------------------------------------------------------------- groups
@dataclass(frozen=True)
class CoefficientSpread:
    """One coefficient across a group's units.

    Attributes
    ----------
    name : str
        Term name (see :attr:`UnitResult.coefficients`).
    values : tuple of (str, float)
        (unit, coefficient) for every unit of the group.
    median : float
    mad : float
        Median absolute deviation from the median (unscaled; 1.4826 MAD
        estimates a normal standard deviation).
    outliers : tuple of str
        Units with ``|x - median| > 3.5 * 1.4826 * MAD`` (a modified z-score
        above 3.5; none with fewer than three units or a zero MAD).
    """

    name: str
    values: tuple[tuple[str, float], ...]
    median: float
    mad: float
    outliers: tuple[str, ...] = ()

    def as_dict(self) -> dict:
        """JSON-ready record."""
        return {"name": self.name, "median": self.median, "mad": self.mad,
                "outliers": list(self.outliers), "values": dict(self.values)}


@dataclass(frozen=True)
class ExplanationGroup:
    """The units that deviate from the model in the same way.

    Attributes
    ----------
    key : str
        The explanation in one line (equations, kind, order, law terms).
    explanation : tuple
        As :attr:`UnitResult.explanation`.
    units : tuple of str
    coefficients : tuple of CoefficientSpread
        One per term of the law.
    """

    key: str
    explanation: tuple
    units: tuple[str, ...]
    coefficients: tuple[CoefficientSpread, ...] = ()

    def as_dict(self) -> dict:
        """JSON-ready record."""
        return {"key": self.key, "units": list(self.units),
                "explanation": [{"equations": list(e), "kind": k, "order": o, "terms": list(t)}
                                for e, k, o, t in self.explanation],
                "coefficients": [c.as_dict() for c in self.coefficients]}


def _spread(name: str, values) -> CoefficientSpread:
    x = np.array([v for _, v in values], dtype=float)
    med = float(np.median(x))
    mad = float(np.median(np.abs(x - med)))
    out = ()
    if x.size >= 3 and mad > 0:
        out = tuple(u for u, v in values if abs(v - med) > OUTLIER_Z * _MAD_TO_STD * mad)
    return CoefficientSpread(name, tuple(values), med, mad, out)


def group_units(units) -> tuple[ExplanationGroup, ...]:
    """Group the deviating units by explanation; spread of each coefficient per group.

    Parameters
    ----------
    units : iterable of UnitResult
        Units of any verdict; only those that deviate (an effect added) are grouped.

    Returns
    -------
    tuple of ExplanationGroup
        Largest group first (then by key).
    """
    by_key: dict[tuple, list] = {}
    for r in units:
        if r.verdict == "deviates" and r.status != "failed":
            by_key.setdefault(r.explanation, []).append(r)
    groups = []
    for expl, rs in by_key.items():
        names = []
        for r in rs:
            names += [n for n, _ in r.coefficients if n not in names]
        spreads = tuple(_spread(n, [(r.unit, dict(r.coefficients)[n]) for r in rs
                                    if n in dict(r.coefficients)]) for n in names)
        groups.append(ExplanationGroup(explanation_key(expl), expl,
                                       tuple(r.unit for r in rs), spreads))
    return tuple(sorted(groups, key=lambda g: (-len(g.units), g.key)))


# ----------------------------------------------------------------------------- report
@dataclass(frozen=True)
class FleetReport:
    """Result of :func:`fleet`.

    Attributes
    ----------
    answer : str
        The opening sentence: how many units deviate, grouped how, how many
        are right, how many failed.
    units : tuple of UnitResult
        Every unit, sorted by name.
    groups : tuple of ExplanationGroup
        The deviating units grouped by explanation, largest first.
    out : str
        The output folder.
    workers : int
        Dask workers used (0 when every unit was done before).
    seconds : float
        Wall time of the run [s].
    model : str
        The model file.
    figure : str
        Path of the strip plot, "" when no group has a coefficient.
    """

    answer: str
    units: tuple[UnitResult, ...]
    groups: tuple[ExplanationGroup, ...]
    out: str
    workers: int
    seconds: float
    model: str = ""
    figure: str = ""

    def by_verdict(self, verdict: str) -> tuple[str, ...]:
        """Names of the units with this verdict ("deviates", "right", "unexplained")."""
        return tuple(r.unit for r in self.units if r.verdict == verdict and
                     r.status != "failed")

    @property
    def failed(self) -> tuple[UnitResult, ...]:
        """The units that could not be done."""
        return tuple(r for r in self.units if r.status == "failed")

    def as_dict(self) -> dict:
        """JSON-ready record (``fleet.json``)."""
        return {"answer": self.answer, "model": self.model, "out": self.out,
                "workers": self.workers, "seconds": self.seconds, "figure": self.figure,
                "counts": {"units": len(self.units),
                           "deviates": len(self.by_verdict("deviates")),
                           "right": len(self.by_verdict("right")),
                           "unexplained": len(self.by_verdict("unexplained")),
                           "failed": len(self.failed),
                           "skipped (done before)": sum(r.status == "skipped (done before)"
                                                        for r in self.units)},
                "groups": [g.as_dict() for g in self.groups],
                "right": list(self.by_verdict("right")),
                "unexplained": list(self.by_verdict("unexplained")),
                "failed": {r.unit: r.error for r in self.failed},
                "units": [r.as_dict() for r in self.units]}


def _plural(n: int, one: str, many: str) -> str:
    return f"{n} {one if n == 1 else many}"


def fleet_answer(units, groups) -> str:
    """The report's opening sentence (see :attr:`FleetReport.answer`)."""
    units = list(units)
    ok = [r for r in units if r.status != "failed"]
    dev = [r for r in ok if r.verdict == "deviates"]
    parts = [f"{_plural(len(units), 'unit', 'units')}: "
             f"{len(dev)} {'deviates' if len(dev) == 1 else 'deviate'} from the model"]
    if groups:
        how = "; ".join(f"{len(g.units)} by {g.key}" for g in groups)
        parts[0] += f" ({_plural(len(groups), 'explanation', 'explanations')}: {how})"
    une = sum(r.verdict == "unexplained" for r in ok)
    if une:
        parts.append(f"{une} {'shows' if une == 1 else 'show'} a model error no candidate "
                     f"explains")
    right = sum(r.verdict == "right" for r in ok)
    parts.append(f"{right} {'is' if right == 1 else 'are'} right")
    parts.append(f"{len(units) - len(ok)} failed")
    return ", ".join(parts) + "."


def _num(v, fmt=".3g") -> str:
    return "n/a" if v is None or not math.isfinite(v) else format(v, fmt)


def fleet_markdown(report: FleetReport) -> str:
    """The fleet report as markdown (``fleet.md``): the answer first, then groups, units.

    Parameters
    ----------
    report : FleetReport

    Returns
    -------
    str
    """
    out = ["# greybox fleet report", "", f"**{report.answer}**", "",
           f"Model `{report.model}`; one close the loop per unit ("
           + (f"{report.workers} Dask workers, {report.seconds:.1f} s" if report.workers else
              "none computed now: every unit was done before")
           + "). Coefficients are in the "
           f"units of the state equations they enter; outliers: |x - median| > "
           f"{OUTLIER_Z:g} x 1.4826 MAD.", ""]
    if report.groups:
        out += ["## Units that deviate, grouped by explanation", ""]
    for i, g in enumerate(report.groups, start=1):
        out += [f"### {i}. {g.key} ({_plural(len(g.units), 'unit', 'units')})", "",
                "Units: " + ", ".join(g.units), ""]
        if g.coefficients:
            out += ["| coefficient | median | MAD | min | max | outliers |",
                    "|---|---|---|---|---|---|"]
            for c in g.coefficients:
                v = [x for _, x in c.values]
                out.append(f"| `{c.name}` | {_num(c.median, '.4g')} | {_num(c.mad, '.3g')} | "
                           f"{_num(min(v), '.4g')} | {_num(max(v), '.4g')} | "
                           f"{', '.join(c.outliers) or '-'} |")
            out.append("")
    if report.figure:
        out += [f"![coefficients across units]({Path(report.figure).name})", ""]
    lists = [("Units whose model is right", report.by_verdict("right")),
             ("Units with a model error no candidate explains", report.by_verdict("unexplained"))]
    for title, names in lists:
        if names:
            out += [f"## {title}", "", ", ".join(names), ""]
    if report.failed:
        out += ["## Failed units", "", "| unit | error |", "|---|---|"]
        out += [f"| {r.unit} | {r.error.replace('|', '/')} |" for r in report.failed] + [""]
    out += ["## Every unit", "",
            "| unit | status | verdict | effects | SE before [%] | SE after [%] |",
            "|---|---|---|---|---|---|"]
    for r in report.units:
        eff = "<br>".join(f"`{e}`" for e in r.effects) or (r.error.replace("|", "/") or "-")
        out.append(f"| {r.unit} | {r.status} | {r.verdict or '-'} | {eff} | "
                   f"{_num(r.se_before)} | {_num(r.se_after)} |")
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------- running
def _dask():
    """The ``distributed`` module, or one MissingDependencyError saying how to install it."""
    try:
        import distributed
    except ImportError as e:
        raise MissingDependencyError(
            'greybox fleet runs on Dask, which is not installed: pip install "greybox[fleet]" '
            '(dask[distributed] >= 2024.1)') from e
    return distributed


def _cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def _sigint_ignored():
    """SIGINT ignored while the block starts worker processes, which inherit it.

    A terminal's Ctrl-C reaches every process of its group; workers that
    ignore it do not die mid-task printing tracebacks: this process cancels
    their tasks and closes the cluster. A no-op outside the main thread.
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def _connect(client, workers):
    """(Client, number of workers): the given one, one to an address, or a LocalCluster."""
    import logging

    distributed = _dask()
    if client is not None and not isinstance(client, (str, os.PathLike)):
        yield client, len(client.nthreads())
        return
    if client is not None:
        try:
            c = distributed.Client(str(client), timeout=10)
        except (OSError, TimeoutError) as e:
            raise DataError(f"cannot reach the Dask scheduler at {client}: {_one_line(e)}; "
                            f"check the address (tcp://host:8786)") from e
        try:
            yield c, len(c.nthreads())
        finally:
            c.close()
        return
    n = workers or _cores()
    with _sigint_ignored():  # the workers inherit it: Ctrl-C reaches this process alone
        cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=logging.ERROR,
                                           env=dict(_BLAS_ENV))
    try:
        c = distributed.Client(cluster)
        try:
            yield c, n
        finally:
            c.close()
    finally:
        cluster.close()


def _previous(out: Path, units, prints, force: bool) -> dict:
    """Units done before with the same inputs (unless ``force``): name -> UnitResult."""
    import json

    done = {}
    for u in units if not force else ():
        try:
            d = json.loads((out / "units" / f"{u.name}.json").read_text(encoding="utf-8"))
            if d.get("status") == "done" and d.get("inputs") == prints[u.name]:
                done[u.name] = UnitResult.from_dict(d, status="skipped (done before)")
        except (OSError, ValueError, KeyError, TypeError):
            continue  # missing, partial or foreign: run the unit again
    return done


def _run_all(client, model, todo, out, *, delta, timeout, prints, arrived) -> dict:
    """Submit one task per unit; write each result as it arrives; name -> UnitResult."""
    from .io import atomic_write_json, deferred_interrupt

    distributed = _dask()
    futures = {client.submit(run_unit, str(model), u.name, str(u.estimation),
                             str(u.validation), delta=delta, timeout=timeout, pure=False,
                             key=f"greybox-unit-{u.name}-{os.urandom(4).hex()}"): u
               for u in todo}
    results = {}
    try:
        for fut in distributed.as_completed(list(futures)):
            u = futures.pop(fut)
            try:
                d = fut.result()
            except Exception as e:  # noqa: BLE001 - a worker died, the task was lost
                d = UnitResult(u.name, "failed", error=f"worker lost: {_one_line(e)}").as_dict()
            fut.release()  # the worker may drop the result: it is on disk now
            d["inputs"] = prints[u.name]
            with deferred_interrupt():
                atomic_write_json(out / "units" / f"{u.name}.json", d)
            results[u.name] = UnitResult.from_dict(d)
            arrived(results[u.name])
    finally:
        if futures:  # interrupted: the units not finished are cancelled
            client.cancel(list(futures))
    return results


def _unit_line(r: UnitResult) -> str:
    if r.status == "failed":
        return f"{r.unit}: failed: {r.error}"
    what = {"right": "model right", "unexplained": "model error not explained"}.get(
        r.verdict, r.key)
    return f"{r.unit}: {r.verdict if r.verdict == 'deviates' else 'done'} ({what}), " \
           f"{r.seconds:.1f} s"


def fleet(model, records, *, out, client=None, workers: int | None = None, force: bool = False,
          timeout: float | None = None, delta: bool = False, progress=None) -> FleetReport:
    """Close the loop on every unit of a fleet, in parallel on Dask; report across units.

    Parameters
    ----------
    model : str or path-like
        The nominal model of the design: MODEL.json (or MODEL.py), as for
        ``greybox update``.
    records : str or path-like
        A folder with one sub-folder per unit holding ``estimation.csv`` and
        ``validation.csv``, or a manifest CSV ``unit,estimation,validation``.
    out : str or path-like
        Output folder: ``units/<unit>.json``, ``fleet.json``, ``fleet.md``,
        ``coefficients.png``. Reused by a rerun (units done before are kept).
    client : distributed.Client or str, optional
        An existing Dask client, or a scheduler address (``tcp://host:8786``);
        default a LocalCluster of ``workers`` processes.
    workers : int, optional
        Worker processes of the LocalCluster (one thread each); default the
        number of cores. Ignored with ``client``.
    force : bool
        Compute every unit again (and write into a folder holding files
        greybox did not write).
    timeout : float, optional
        Per-unit time limit [s]; a unit over it fails with a "timeout" line.
    delta : bool
        Also fit each unit's parallel delta baseline (a comparison row only).
    progress : callable, optional
        Called with a :class:`greybox.progress.Progress` record per unit as it
        finishes (``stage`` holds the unit's one-line result, ``k`` of ``K``
        units); None reports nothing.

    Returns
    -------
    FleetReport

    Raises
    ------
    DataError, ModelError, OutputExistsError
        Bad model, records or output folder (nothing is written then).
    MissingDependencyError
        Dask is not installed (``pip install "greybox[fleet]"``).
    KeyboardInterrupt
        On Ctrl-C, after cancelling the pending units; every unit finished
        before is in ``out/units``.
    """
    from .io import check_output_dir, record_outputs
    from .model_io import read_model

    t0 = time.perf_counter()
    # every input first: nothing is written when one is bad
    if workers is not None:
        workers = check_positive(workers, "workers", integer=True)
    if timeout is not None:
        timeout = check_positive(timeout, "timeout")
    model, out = Path(model).absolute(), Path(out)
    read_model(model)  # a bad model is bad input for every unit: refused here, once
    units = find_units(records, exclude=out)
    check_output_dir(out, force=force, kind="fleet")
    _dask()
    prints = {u.name: _fingerprint(model, u, delta) for u in units}
    results = _previous(out, units, prints, force)
    todo = [u for u in units if u.name not in results]
    count = [len(results)]

    def tell(stage: str) -> None:
        if progress is not None:
            progress(Progress(stage, count[0], len(units), time.perf_counter() - t0))

    def arrived(r: UnitResult) -> None:
        count[0] += 1
        tell(_unit_line(r))

    if results:
        tell(f"{len(results)} units done before: skipped (force recomputes them)")
    nworkers = 0
    if todo:
        with _connect(client, workers) as (c, nworkers):
            (out / "units").mkdir(parents=True, exist_ok=True)
            record_outputs(out, "fleet", ["units"])
            results.update(_run_all(c, model, todo, out, delta=delta, timeout=timeout,
                                    prints=prints, arrived=arrived))
    return _finish(model, out, [results[u.name] for u in units], nworkers,
                   time.perf_counter() - t0)


def _finish(model, out: Path, units, nworkers: int, seconds: float) -> FleetReport:
    """Group, write fleet.json, fleet.md and the strip plot; the report."""
    from .io import atomic_write_json, atomic_write_text, record_outputs

    groups = group_units(units)
    out.mkdir(parents=True, exist_ok=True)
    figure = ""
    if any(g.coefficients for g in groups):
        figure = str(out / "coefficients.png")
        _strip_plot(groups, figure)
    rep = FleetReport(fleet_answer(units, groups), tuple(units), groups, str(out), nworkers,
                      seconds, str(model), figure)
    atomic_write_json(out / "fleet.json", rep.as_dict())
    atomic_write_text(out / "fleet.md", fleet_markdown(rep))
    record_outputs(out, "fleet", ["units", "fleet.json", "fleet.md"]
                   + (["coefficients.png"] if figure else []))
    return rep


def _strip_plot(groups, path) -> None:
    from .io import save_figure
    from .plotting import plot_fleet_coefficients

    save_figure(plot_fleet_coefficients(groups)["figure"], path)
