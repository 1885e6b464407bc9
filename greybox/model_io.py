"""MODEL.json and measurement CSV files for ``greybox update``.

MODEL.json schema (one JSON object)::

    {
      "time": "continuous" | "discrete",   # how A, B, C, D are written
      "Ts": 0.01,                          # sampling period of the data [s]
                                           # (the model's dt if discrete)
      "states":  ["p1", "v1", ...],        # names, one per state
      "inputs":  ["F", ...],               # names of the measured inputs
      "outputs": ["p1", ...],              # names of the measured outputs
      "A": [[...], ...], "B": [[...]], "C": [[...]], "D": [[...]],   # D optional (zero)
      "Q": [[...]] or [diag...],           # process-noise covariance (discrete model)
      "R": [[...]] or [diag...],           # measurement-noise covariance
      "channels": {                        # optional candidate error channels
        "tension": [0, 0, 0, 0, 1.2, -1.5],    # a G column (nstates entries), or
        "coupling": ["v1", "v2"]               # state equations entered together
      },
      "name": "my model"                   # optional
    }

CSV: a header row naming every input and every output of the model (any
order) and optionally a time column named ``time`` or ``t`` [s]; one row
per sample; numbers only.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import control as ct
import numpy as np

from ._validation import check_covariance, check_matrix
from .exceptions import DataError, DimensionError, ModelError
from .system import named_ss

__all__ = ["ModelSpec", "read_model", "model_to_dict", "write_model", "read_csv"]

_TIME_COLUMNS = ("time", "t")


@dataclass(frozen=True)
class ModelSpec:
    """A model read from MODEL.json.

    Attributes
    ----------
    sys : control.StateSpace
        Continuous (dt = 0) or discrete (dt = Ts) model with named signals.
    Ts : float
        Sampling period of the data [s].
    Q, R : ndarray
        Noise covariances.
    channels : dict or None
        Candidate channels as given (see :func:`greybox.trace.resolve_channel_spec`).
    """

    sys: ct.StateSpace
    Ts: float
    Q: np.ndarray
    R: np.ndarray
    channels: dict | None = None


def _names(d, key):
    v = d.get(key)
    if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
        raise ModelError(f"MODEL.json: '{key}' must be a list of names; found {v!r}")
    if len(set(v)) != len(v):
        raise ModelError(f"MODEL.json: '{key}' has repeated names {v}")
    return v


def read_model(path) -> ModelSpec:
    """Read and check MODEL.json (schema in the module docstring)."""
    try:
        text = Path(path).read_text()
    except OSError as e:
        raise DataError(f"cannot read model file {path}: {e.strerror}") from e
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise DataError(f"{path} is not valid JSON (line {e.lineno}, column {e.colno}: "
                        f"{e.msg})") from e
    if not isinstance(d, dict):
        raise ModelError(f"{path}: expected a JSON object with A, B, C, ...; found "
                         f"{type(d).__name__}")
    missing = [k for k in ("time", "Ts", "states", "inputs", "outputs", "A", "B", "C", "Q", "R")
               if k not in d]
    if missing:
        raise ModelError(f"{path}: missing keys {missing}; see the MODEL.json schema")
    if d["time"] not in ("continuous", "discrete"):
        raise ModelError(f"{path}: 'time' must be 'continuous' or 'discrete'; found "
                         f"{d['time']!r}")
    if isinstance(d["Ts"], bool):
        raise ModelError(f"{path}: 'Ts' must be a number [s]; found {d['Ts']!r}")
    try:
        Ts = float(d["Ts"])
    except (TypeError, ValueError) as e:
        raise ModelError(f"{path}: 'Ts' must be a number [s]; found {d['Ts']!r}") from e
    if not np.isfinite(Ts) or Ts <= 0:
        raise ModelError(f"{path}: 'Ts' must be > 0 [s]; found {Ts}")
    xs, us, ys = _names(d, "states"), _names(d, "inputs"), _names(d, "outputs")
    n, m, p = len(xs), len(us), len(ys)
    clash = sorted(set(us) & set(ys))
    if clash:
        raise ModelError(f"{path}: {clash} named both as input and as output; CSV columns "
                         f"must be unique: rename one of them")
    reserved = sorted(set(us + ys) & set(_TIME_COLUMNS))
    if reserved:
        raise ModelError(f"{path}: signal name(s) {reserved} are reserved for the CSV time "
                         f"column; rename them")
    try:
        A = check_matrix(d["A"], (n, n), "A")
        B = check_matrix(d["B"], (n, m), "B") if m else np.zeros((n, 0))
        C = check_matrix(d["C"], (p, n), "C")
        D = check_matrix(d.get("D", np.zeros((p, m))), (p, m), "D") if m else np.zeros((p, 0))
        Q = check_covariance(d["Q"], n, "Q", definite=False)
        R = check_covariance(d["R"], p, "R", definite=True)
    except (DimensionError, DataError) as e:
        raise ModelError(f"{path}: {e} (states {n}, inputs {m}, outputs {p})") from e
    chans = d.get("channels")
    if chans is not None and not isinstance(chans, dict):
        raise ModelError(f"{path}: 'channels' must be an object {{name: G column or state "
                         f"names}}; found {type(chans).__name__}")
    dt = Ts if d["time"] == "discrete" else 0
    sys = named_ss(A, B, C, D, dt, states=xs, inputs=us, outputs=ys,
                   name=str(d.get("name", "model")))
    return ModelSpec(sys=sys, Ts=Ts, Q=Q, R=R, channels=chans)


def model_to_dict(sys: ct.StateSpace, Q, R, *, Ts: float | None = None,
                  channels: dict | None = None) -> dict:
    """The MODEL.json object of a (discrete or continuous) model."""
    disc = ct.isdtime(sys, strict=True)
    out = {"time": "discrete" if disc else "continuous",
           "Ts": float(sys.dt) if disc else float(Ts),
           "name": sys.name, "states": list(sys.state_labels),
           "inputs": list(sys.input_labels), "outputs": list(sys.output_labels)}
    for k in ("A", "B", "C", "D"):
        out[k] = np.asarray(getattr(sys, k), dtype=float).tolist()
    out["Q"] = np.asarray(Q, dtype=float).tolist()
    out["R"] = np.asarray(R, dtype=float).tolist()
    if channels:
        out["channels"] = channels
    return out


def write_model(path, sys: ct.StateSpace, Q, R, *, Ts: float | None = None) -> None:
    """Write a model as MODEL.json atomically."""
    from .io import atomic_write_json

    atomic_write_json(path, model_to_dict(sys, Q, R, Ts=Ts))


def read_csv(path, *, inputs, outputs, Ts: float, min_steps: int = 200):
    """Read a measurement CSV; return ``(y, u)``, shapes (noutputs, N), (ninputs, N).

    Raises
    ------
    DataError
        Missing or extra columns, non-numeric cells, NaN rows, a time column
        that disagrees with Ts, or fewer than ``min_steps`` rows.
    """
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:  # tolerate Excel's BOM
            rows = list(csv.reader(f))
    except OSError as e:
        raise DataError(f"cannot read {path}: {e.strerror}") from e
    except (UnicodeDecodeError, csv.Error) as e:
        raise DataError(f"{path} is not a readable CSV file ({e})") from e
    rows = [r for r in rows if any(c.strip() for c in r)]
    if not rows:
        raise DataError(f"{path} is empty; expected a header row and data")
    header = [h.strip() for h in rows[0]]
    want = list(inputs) + list(outputs)
    tcol = [h for h in header if h in _TIME_COLUMNS]
    missing = [c for c in want if c not in header]
    extra = [h for h in header if h not in want and h not in _TIME_COLUMNS]
    if missing or extra or len(set(header)) != len(header) or len(tcol) > 1:
        raise DataError(f"{path}: columns {header}; expected {want} (+ optional 'time')"
                        + (f"; missing {missing}" if missing else "")
                        + (f"; unexpected {extra}" if extra else ""))
    data = rows[1:]
    for i, r in enumerate(data):
        if len(r) != len(header):
            raise DataError(f"{path}, row {i + 2}: {len(r)} cells; expected {len(header)}")
    try:
        arr = np.array([[float(c) for c in r] for r in data], dtype=float).reshape(-1, len(header))
    except ValueError as e:
        for i, r in enumerate(data):
            for j, c in enumerate(r):
                try:
                    float(c)
                except ValueError:
                    raise DataError(f"{path}, row {i + 2}, column '{header[j]}': {c!r} is not "
                                    f"a number") from e
        raise DataError(f"{path}: non-numeric cells") from e
    bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
    if bad.size:
        raise DataError(f"{path}: {bad.size} row(s) with NaN or inf (first: row {bad[0] + 2}); "
                        f"remove or interpolate them")
    if arr.shape[0] < min_steps:
        raise DataError(f"{path}: {arr.shape[0]} samples; at least {min_steps} are needed")
    if tcol:
        t = arr[:, header.index(tcol[0])]
        dtv = np.diff(t)
        if np.max(np.abs(dtv - Ts)) > 1e-3 * Ts:
            raise DataError(f"{path}: the time column steps by {np.median(dtv):g} s (range "
                            f"{dtv.min():g}..{dtv.max():g}); the model's Ts is {Ts:g} s")
    u = np.array([arr[:, header.index(c)] for c in inputs]).reshape(len(inputs), -1)
    y = np.array([arr[:, header.index(c)] for c in outputs]).reshape(len(outputs), -1)
    return y, u
