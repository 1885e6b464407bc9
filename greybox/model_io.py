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

The file must be UTF-8 JSON. It is read strictly: unknown keys (a typo such
as ``chanels``), repeated keys, empty or repeated names, an all-zero channel
and a ``Ts`` that disagrees with the model's time scale by orders of
magnitude are refused with one line saying what to change. A model without
inputs (``"inputs": []``, B and D may then be omitted) is valid.

MODEL.py (a nonlinear model, or any model python-control can hold): a Python
file that defines, at module level::

    model = control.nlsys(f, h, states=[...], inputs=[...], outputs=[...])
                                           # a NonlinearIOSystem (continuous, or
                                           # discrete with dt = Ts) or a StateSpace,
                                           # named signals, linear output map
    Q = ...                                # process-noise covariance (discrete)
    R = ...                                # measurement-noise covariance
    Ts = 0.01                              # sampling period of the data [s]
                                           # (optional for a discrete model: its dt)
    channels = {...}                       # optional, as in MODEL.json

It is *executed* as Python (``runpy.run_path``) to obtain them: read only
files you trust. Any other module-level names (imports, helper functions,
parameters) are ignored; an exception inside the file is reported as one
ModelError naming the file.

CSV: a header row naming every input and every output of the model (any
order) and optionally a time column named ``time`` or ``t`` [s]; one row
per sample; numbers only (UTF-8, an Excel byte-order mark is accepted).
:func:`read_csv` parses with numpy's compiled text parser chunk by chunk
(>= 5e6 values/s; peak memory about twice the numbers) and re-reads only a
chunk that fails, to name the row and column at fault.
"""

from __future__ import annotations

import codecs
import contextlib
import csv
import difflib
import io
import json
import os
import stat
import sys
import unicodedata
import warnings
from dataclasses import dataclass

import control as ct
import numpy as np

from ._validation import MAX_MAGNITUDE, check_covariance, check_matrix
from .exceptions import CovarianceError, DataError, DimensionError, GreyboxWarning, ModelError
from .nonlinear import linear_output_map
from .system import named_ss

__all__ = ["ModelSpec", "read_model", "read_model_py", "model_to_dict", "write_model", "read_csv"]

_TIME_COLUMNS = ("time", "t")
_KEYS = ("time", "Ts", "states", "inputs", "outputs", "A", "B", "C", "D", "Q", "R",
         "channels", "name")
_REQUIRED = ("time", "Ts", "states", "inputs", "outputs", "A", "C", "Q", "R")
#: |eigenvalue| * Ts bounds of a continuous model outside which Ts cannot be
#: the sampling period of data that show its dynamics (refused).
_TS_TOO_FAST, _TS_TOO_SLOW = 1e-9, 1e3


@dataclass(frozen=True)
class ModelSpec:
    """A model read from MODEL.json.

    Attributes
    ----------
    sys : control.StateSpace or control.NonlinearIOSystem
        Continuous (dt = 0) or discrete (dt = Ts) model with named signals
        (a NonlinearIOSystem only from MODEL.py).
    Ts : float
        Sampling period of the data [s].
    Q, R : ndarray
        Noise covariances.
    channels : dict or None
        Candidate channels as given (see :func:`greybox.trace.resolve_channel_spec`).
    """

    sys: ct.StateSpace | ct.NonlinearIOSystem
    Ts: float
    Q: np.ndarray
    R: np.ndarray
    channels: dict | None = None


#: Largest MODEL.json or MODEL.py read [bytes] (a 1000-state model takes about 50 MB).
_MAX_MODEL_BYTES = 1 << 28


def _open_regular(path, what: str):
    """A regular file opened for binary reading, or one clear DataError.

    A folder, a device (``/dev/zero``), a named pipe (it would wait for a
    writer) or a socket is refused before anything is read.
    """
    label = f"{what} {path}" if what else f"{path}"
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as e:
        kind = _kind_of(path)
        raise DataError(f"cannot read {label}: "
                        f"{f'it is {kind}, not a file' if kind else e.strerror}") from e
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise DataError(f"cannot read {label}: it is {_kind_of(path) or 'not a file'}, not a "
                        f"regular file; give a file")
    return os.fdopen(fd, "rb")


def _kind_of(path) -> str:
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return ""
    for test, kind in ((stat.S_ISDIR, "a folder"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a named pipe (FIFO)"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return ""


def _read_text(path, what: str) -> str:
    """The UTF-8 text of a file (a UTF-8 byte-order mark is dropped), or one clear DataError."""
    with _open_regular(path, what) as f:
        try:
            raw = f.read(_MAX_MODEL_BYTES + 1)
        except OSError as e:
            raise DataError(f"cannot read {what} {path}: {e.strerror}") from e
    if len(raw) > _MAX_MODEL_BYTES:
        raise DataError(f"{path}: a {what} larger than {_MAX_MODEL_BYTES >> 20} MB; is it the "
                        f"right file?")
    enc = _foreign_encoding(raw)
    if enc:
        raise DataError(f"{path} is {enc} text; greybox reads UTF-8: save it as UTF-8")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise DataError(f"{path} is not UTF-8 text (byte {e.start}: {raw[e.start:e.start + 1]!r}); "
                        f"save it as UTF-8") from e


def _foreign_encoding(head: bytes) -> str:
    for bom, name in ((codecs.BOM_UTF32_LE, "UTF-32"), (codecs.BOM_UTF32_BE, "UTF-32"),
                      (codecs.BOM_UTF16_LE, "UTF-16"), (codecs.BOM_UTF16_BE, "UTF-16")):
        if head.startswith(bom):
            return name
    if len(head) >= 4 and head[1:4:2] == b"\0\0" and head[0] and head[2]:
        return "UTF-16"  # little-endian without a byte-order mark
    return ""


def _no_repeated_keys(pairs):
    keys = [k for k, _ in pairs]
    seen = set()
    for k in keys:
        if k in seen:
            raise ModelError(f"key {k!r} appears twice in one object; keep one")
        seen.add(k)
    return dict(pairs)


def _names(d, key, path, *, allow_empty=False):
    v = d.get(key)
    if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
        raise ModelError(f"{path}: '{key}' must be a list of names; found {v!r}")
    if not v and not allow_empty:
        raise ModelError(f"{path}: '{key}' is empty; give at least one name")
    blank = [i for i, s in enumerate(v) if not s.strip()]
    if blank:
        raise ModelError(f"{path}: '{key}'[{blank[0]}] is an empty name; every signal needs "
                         f"a name")
    _check_name_chars(v, f"{path}: '{key}'")
    v = [_nfc(s) for s in v]
    if len(set(v)) != len(v):
        how = "" if len(set(d[key])) != len(v) else (
            " (written with different Unicode code points for the same letters, e.g. an "
            "accent composed or not: they look the same)")
        raise ModelError(f"{path}: '{key}' has repeated names {v}{how}")
    return v


def _check_name_chars(names, where: str) -> None:
    """Refuse names python-control cannot hold ('.') and names a CSV header cannot match."""
    for i, s in enumerate(names):
        if "." in s:
            raise ModelError(f"{where}[{i}] {s!r} contains '.', which python-control reserves "
                             f"for subsystem signals; use '_' instead ({s.replace('.', '_')!r})")
        if s != s.strip():
            raise ModelError(f"{where}[{i}] {s!r} begins or ends with a space; remove it (CSV "
                             f"header cells are read without their spaces)")


def _check_csv_names(us, ys, path) -> None:
    """Input and output names become CSV columns: unique, and not a time column's name."""
    clash = sorted(set(us) & set(ys))
    if clash:
        raise ModelError(f"{path}: {clash} named both as input and as output; CSV columns "
                         f"must be unique: rename one of them")
    reserved = sorted(set(us + ys) & set(_TIME_COLUMNS))
    if reserved:
        raise ModelError(f"{path}: signal name(s) {reserved} are reserved for the CSV time "
                         f"column; rename them")


def _check_channels(chans, xs, path):
    if chans is None:
        return None
    if not isinstance(chans, dict):
        raise ModelError(f"{path}: 'channels' must be an object {{name: G column or state "
                         f"names}}; found {type(chans).__name__}")
    if not chans:
        raise ModelError(f"{path}: 'channels' is empty; leave it out to try every state "
                         f"equation")
    n = len(xs)
    for name, v in chans.items():
        if not name.strip():
            raise ModelError(f"{path}: a channel has an empty name; name every channel")
        if isinstance(v, list) and v and all(isinstance(t, str) for t in v):
            bad = [t for t in v if t not in xs]
            if bad:
                raise ModelError(f"{path}: channel {name!r} names unknown states {bad}; "
                                 f"states are {xs}")
            if len(set(v)) != len(v):
                raise ModelError(f"{path}: channel {name!r} repeats a state: {v}")
            continue
        try:
            G = check_matrix(v, (n, 1), f"channel {name!r}") if not (
                isinstance(v, list) and v and isinstance(v[0], list)) else \
                np.array(v, dtype=float)
        except (DimensionError, DataError) as e:
            raise ModelError(f"{path}: {e}; a channel is a G column of {n} numbers or a list "
                             f"of state names") from e
        except (TypeError, ValueError) as e:
            raise ModelError(f"{path}: channel {name!r} must be a G column of {n} numbers or "
                             f"a list of state names; found {v!r}") from e
        if G.ndim != 2 or G.shape[0] != n or not np.all(np.isfinite(G)):
            raise ModelError(f"{path}: channel {name!r} has shape {G.shape}; expected ({n},) "
                             f"or ({n}, md), finite")
        zero = np.flatnonzero(np.all(G == 0, axis=0))
        if zero.size:
            raise ModelError(f"{path}: channel {name!r} is all zero"
                             f"{f' in column {zero[0]}' if G.shape[1] > 1 else ''}: it enters "
                             f"no state equation; remove it or give its G entries")
    return chans


def _check_time_scale(A, Ts, time, path):
    """Refuse a Ts orders of magnitude away from a continuous model's time scale."""
    if time != "continuous" or A.size == 0:
        return
    lam = np.abs(np.linalg.eigvals(A))
    lam = lam[lam > 1e-12 * max(1.0, lam.max())]
    if lam.size == 0:
        return  # pure integrators: no time scale
    fast, slow = lam.max() * Ts, lam.min() * Ts
    if fast < _TS_TOO_FAST:
        raise ModelError(f"{path}: Ts = {Ts:g} s is {fast:.2g} of the model's fastest time "
                         f"constant ({1 / lam.max():.3g} s): the sampled model would be the "
                         f"identity to {-np.log10(fast):.0f} digits. Check Ts (in seconds) and "
                         f"the units of A")
    if slow > _TS_TOO_SLOW:
        raise ModelError(f"{path}: Ts = {Ts:g} s is {slow:.2g} times the model's slowest time "
                         f"constant ({1 / lam.min():.3g} s): every mode settles (or explodes) "
                         f"within one sample. Check Ts (in seconds) and the units of A")
    if fast < 1e-6 or slow > 20:
        what = ("heavily oversampled" if fast < 1e-6 else
                "every mode settles within a few samples")
        warnings.warn(f"{path}: Ts = {Ts:g} s vs the model's time constants "
                      f"{1 / lam.max():.3g}..{1 / lam.min():.3g} s: {what}; check Ts and the "
                      f"units of A", GreyboxWarning, stacklevel=3)


class _HugeNumber(ValueError):
    """A JSON integer too long to be a float (raised inside json.loads)."""


def _json_int(digits: str):
    """A JSON integer: an int, or a clear error when it is beyond MAX_MAGNITUDE."""
    if len(digits) > 18 and not abs(float(digits)) <= MAX_MAGNITUDE:  # float(): inf, no error
        n = len(digits.lstrip("-"))
        raise _HugeNumber(f"the integer {digits[:12]}... ({n} digits) is beyond "
                          f"{MAX_MAGNITUDE:g} in magnitude and would overflow the computations; "
                          f"rescale (change units)")
    return int(digits)


def _check_discrete_A(A, time, path) -> None:
    """Refuse a model said to be discrete whose A is plainly a continuous-time matrix.

    Sampling puts every eigenvalue of a physical model at exp(lambda Ts):
    stable modes inside the unit circle, never beyond it with a negative
    real part. A matrix whose eigenvalues all lie in the open left
    half-plane, some of them outside the unit circle, is dx/dt = A x.
    """
    if time != "discrete" or A.size == 0:
        return
    lam = np.linalg.eigvals(A)
    if np.all(lam.real < 0) and np.max(np.abs(lam)) > 1 + 1e-9:
        big = lam[np.argmax(np.abs(lam))]
        raise ModelError(f"{path}: 'time' is 'discrete' but A looks like a continuous-time "
                         f"matrix: its eigenvalues all have negative real parts and one, "
                         f"{big:.3g}, lies outside the unit circle (an unstable discrete "
                         f"model, a stable continuous one); if A is dx/dt = A x + B u, set "
                         f"\"time\": \"continuous\"")


def read_model(path) -> ModelSpec:
    """Read and check MODEL.json or MODEL.py (schemas in the module docstring).

    Parameters
    ----------
    path : str or path-like
        The MODEL.json file (UTF-8), or a MODEL.py file (name ending in
        ``.py``; executed, see :func:`read_model_py`).

    Returns
    -------
    ModelSpec

    Raises
    ------
    DataError
        The file cannot be read, is not UTF-8 or not JSON.
    ModelError
        The content breaks the schema (one line says what and where).
    """
    if str(path).endswith(".py"):
        return read_model_py(path)
    text = _read_text(path, "model file")
    try:
        d = json.loads(text, object_pairs_hook=_no_repeated_keys, parse_int=_json_int)
    except json.JSONDecodeError as e:
        raise DataError(f"{path} is not valid JSON (line {e.lineno}, column {e.colno}: "
                        f"{e.msg})") from e
    except ModelError as e:
        raise ModelError(f"{path}: {e}") from e
    except RecursionError as e:
        raise DataError(f"{path}: JSON nested too deeply") from e
    except _HugeNumber as e:
        raise ModelError(f"{path}: {e}") from None
    if not isinstance(d, dict):
        raise ModelError(f"{path}: expected a JSON object with A, B, C, ...; found "
                         f"{type(d).__name__}")
    unknown = [k for k in d if k not in _KEYS]
    if unknown:
        k = unknown[0]
        near = difflib.get_close_matches(k, _KEYS, n=1)
        raise ModelError(f"{path}: unknown key {k!r}"
                         + (f" (did you mean {near[0]!r}?)" if near else "")
                         + f"; the keys are {list(_KEYS)}")
    missing = [k for k in _REQUIRED if k not in d]
    if missing:
        raise ModelError(f"{path}: missing keys {missing}; see the MODEL.json schema")
    if d["time"] not in ("continuous", "discrete"):
        raise ModelError(f"{path}: 'time' must be 'continuous' or 'discrete'; found "
                         f"{d['time']!r}")
    if isinstance(d["Ts"], bool) or not isinstance(d["Ts"], (int, float)):
        raise ModelError(f"{path}: 'Ts' must be a number [s]; found {d['Ts']!r}")
    Ts = float(d["Ts"])
    if not np.isfinite(Ts) or Ts <= 0:
        raise ModelError(f"{path}: 'Ts' must be > 0 [s]; found {Ts}")
    xs = _names(d, "states", path)
    us = _names(d, "inputs", path, allow_empty=True)
    ys = _names(d, "outputs", path)
    n, m, p = len(xs), len(us), len(ys)
    if m and "B" not in d:
        raise ModelError(f"{path}: missing key 'B' (the model has {m} inputs)")
    _check_csv_names(us, ys, path)
    try:
        A = check_matrix(d["A"], (n, n), "A")
        B = check_matrix(d["B"], (n, m), "B") if m else np.zeros((n, 0))
        C = check_matrix(d["C"], (p, n), "C")
        D = check_matrix(d.get("D", np.zeros((p, m))), (p, m), "D") if m else np.zeros((p, 0))
        Q = check_covariance(d["Q"], n, "Q", definite=False)
        R = check_covariance(d["R"], p, "R", definite=True)
    except (DimensionError, DataError, CovarianceError) as e:
        raise ModelError(f"{path}: {e} (states {n}, inputs {m}, outputs {p})") from e
    for k, M in (("A", A), ("B", B), ("C", C), ("D", D), ("Q", Q), ("R", R)):
        if M.size and np.max(np.abs(M)) > MAX_MAGNITUDE:
            raise ModelError(f"{path}: '{k}' has entries up to {np.max(np.abs(M)):.3g}; above "
                             f"{MAX_MAGNITUDE:g} the computations overflow: rescale (change "
                             f"units)")
    if "name" in d and not isinstance(d["name"], str):
        raise ModelError(f"{path}: 'name' must be a string; found {d['name']!r}")
    if "." in d.get("name", ""):
        raise ModelError(f"{path}: 'name' {d['name']!r} contains '.', which python-control "
                         f"does not allow in a system name; use '_' instead")
    chans = _check_channels(d.get("channels"), xs, path)
    _check_time_scale(A, Ts, d["time"], path)
    _check_discrete_A(A, d["time"], path)
    dt = Ts if d["time"] == "discrete" else 0
    sys = named_ss(A, B, C, D, dt, states=xs, inputs=us, outputs=ys,
                   name=str(d.get("name", "model")))
    return ModelSpec(sys=sys, Ts=Ts, Q=Q, R=R, channels=chans)


_PY_KEYS = ("model", "Q", "R", "Ts", "channels")


def read_model_py(path) -> ModelSpec:
    """Execute a MODEL.py file; check its ``model``, ``Q``, ``R`` (``Ts``, ``channels``).

    Parameters
    ----------
    path : str or path-like
        The Python file (UTF-8). It is executed: read only files you trust.

    Returns
    -------
    ModelSpec
        With ``sys`` the file's ``model`` (NonlinearIOSystem or StateSpace).

    Raises
    ------
    DataError
        The file cannot be read or is not UTF-8.
    ModelError
        The file raises, lacks ``model``, ``Q`` or ``R``, its model has
        unnamed or clashing signals, a nonlinear output map, or a ``Ts``
        that disagrees with a discrete model's dt.
    """
    _read_text(path, "model file")  # readable, UTF-8 (one clear error otherwise)
    ns = _run_model_py(path)
    missing = [k for k in ("model", "Q", "R") if k not in ns]
    if missing:
        raise ModelError(f"{path}: defines no {missing}; a MODEL.py must define model (a "
                         f"control.NonlinearIOSystem or StateSpace), Q and R (and Ts for a "
                         f"continuous model)")
    sys = ns["model"]
    if not isinstance(sys, ct.NonlinearIOSystem):  # StateSpace is a NonlinearIOSystem subclass
        raise ModelError(f"{path}: 'model' must be a control.NonlinearIOSystem (control.nlsys) "
                         f"or control.StateSpace; found {type(sys).__name__}")
    if sys.nstates is None or sys.ninputs is None or not sys.noutputs:
        raise ModelError(f"{path}: 'model' must declare its states, inputs and outputs")
    xs, us, ys = (list(v) for v in (sys.state_labels, sys.input_labels, sys.output_labels))
    n, m, p = len(xs), len(us), len(ys)
    for key, v in (("states", xs), ("inputs", us), ("outputs", ys)):
        _check_name_chars(v, f"{path}: model's {key}")
    _check_csv_names(us, ys, path)
    disc = sys.isdtime(strict=True)
    if disc and sys.dt is True:
        raise ModelError(f"{path}: 'model' is discrete with an unspecified dt (True); give "
                         f"its sampling period")
    Ts = ns.get("Ts", float(sys.dt) if disc else None)
    if Ts is None:
        raise ModelError(f"{path}: 'model' is continuous-time; define Ts, the sampling period "
                         f"of the data [s]")
    if isinstance(Ts, bool) or not isinstance(Ts, (int, float, np.floating, np.integer)) or \
            not np.isfinite(Ts) or Ts <= 0:
        raise ModelError(f"{path}: 'Ts' must be a number > 0 [s]; found {Ts!r}")
    Ts = float(Ts)
    if disc and abs(Ts - float(sys.dt)) > 1e-9 * Ts:
        raise ModelError(f"{path}: Ts = {Ts:g} s disagrees with the discrete model's dt = "
                         f"{sys.dt:g} s")
    try:
        Q = check_covariance(ns["Q"], n, "Q", definite=False)
        R = check_covariance(ns["R"], p, "R", definite=True)
    except (DimensionError, DataError, CovarianceError) as e:
        raise ModelError(f"{path}: {e} (states {n}, inputs {m}, outputs {p})") from e
    if not isinstance(sys, ct.StateSpace):
        _check_update_size(sys, xs, path)
        try:
            linear_output_map(sys)
        except (ModelError, DimensionError) as e:
            raise ModelError(f"{path}: {e}") from e
    chans = ns.get("channels")
    if chans is not None:
        chans = _check_channels(dict(chans) if isinstance(chans, dict) else chans, xs, path)
    return ModelSpec(sys=sys, Ts=Ts, Q=Q, R=R, channels=chans)


def _run_model_py(path) -> dict:
    """Execute a MODEL.py; its module-level names, or one ModelError naming the file.

    What the file prints goes to stderr (stdout may hold a JSON document);
    ``sys.exit`` and any other exception (Ctrl-C excepted) become a
    ModelError; the working folder is restored if the file changed it.
    """
    import runpy

    cwd = os.getcwd()
    try:
        with contextlib.redirect_stdout(sys.stderr):
            return runpy.run_path(str(path), run_name="greybox_model")
    except SyntaxError as e:
        raise ModelError(f"{path}: Python syntax error at line {e.lineno}: {e.msg}") from e
    except SystemExit as e:
        raise ModelError(f"{path} called sys.exit({e.code!r}) while being executed; a MODEL.py "
                         f"must only define model, Q, R (and Ts): remove the exit") from None
    except KeyboardInterrupt:
        raise
    except BaseException as e:  # noqa: BLE001 - a user's file: report whatever it raised
        raise ModelError(f"{path} raised {type(e).__name__} while being executed: "
                         f"{' '.join(str(e).split())}") from e
    finally:
        if os.getcwd() != cwd:
            os.chdir(cwd)


def _check_update_size(sys, xs, path) -> None:
    """Refuse an update function f that returns the wrong number of values (at x = 0, u = 0)."""
    n = len(xs)
    try:
        dx = np.asarray(sys.updfcn(0.0, np.zeros(n), np.zeros(sys.ninputs), sys.params),
                        dtype=float)
    except Exception:  # noqa: BLE001 - f may be undefined at 0; the filters then report it
        return
    if dx.size != n:
        raise ModelError(f"{path}: the model's update function f returns {dx.size} value(s) "
                         f"(shape {dx.shape}) for {n} states {xs}; it must return one "
                         f"derivative (or next value) per state, in that order")


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

    Parameters
    ----------
    path : str or path-like
        The CSV file (UTF-8; a header row, then one row per sample).
    inputs, outputs : sequence of str
        Column names of the model's inputs and outputs (compared with the
        header in Unicode normal form NFC, so that an accented name typed
        in two ways still matches).
    Ts : float
        The model's sampling period [s], checked against a time column.
    min_steps : int
        Fewest rows accepted.

    Returns
    -------
    y : ndarray, shape (noutputs, N)
    u : ndarray, shape (ninputs, N)

    Raises
    ------
    DataError
        Missing or extra columns (a separator other than the comma, a
        trailing comma, an unnamed index column named as such),
        non-numeric cells (row and column named; a Unicode minus sign or a
        ``1_000`` digit separator said so), NaN rows, values beyond 1e150 in
        magnitude, a time column that goes backwards, misses samples, jitters
        or disagrees with Ts (row and tolerance named), fewer than
        ``min_steps`` rows, a file that is not UTF-8 or not a regular file.
    """
    inputs, outputs = [_nfc(c) for c in inputs], [_nfc(c) for c in outputs]
    with _open_regular(path, "") as f:
        head = f.read(4)
        enc = _foreign_encoding(head)
        if enc:
            raise DataError(f"{path} is {enc} text; greybox reads UTF-8: save it as UTF-8")
        f.seek(3 if head.startswith(codecs.BOM_UTF8) else 0)
        header, line_no = _read_header(f, path)
        want = list(inputs) + list(outputs)
        tcol = [h for h in header if h in _TIME_COLUMNS]
        _check_header(header, want, path)
        ncol = len(header)
        parts = _read_numbers(f, line_no + 1, ncol, header, path)
    nrows = sum(a.shape[0] for a in parts)
    if nrows < min_steps:
        raise DataError(f"{path}: {nrows} samples; at least {min_steps} are needed")
    y, u = np.empty((len(outputs), nrows)), np.empty((len(inputs), nrows))
    t = np.empty(nrows) if tcol else None
    dest = [(y[i], outputs[i]) for i in range(len(outputs))] + \
        [(u[i], inputs[i]) for i in range(len(inputs))] + ([(t, tcol[0])] if tcol else [])
    k = 0
    while parts:  # move the chunks into the signals, freeing each as it goes
        a = parts.pop(0)
        for v, c in dest:
            v[k:k + a.shape[0]] = a[:, header.index(c)]
        k += a.shape[0]
        del a  # the numbers now live in y, u (and t) only: peak about twice the numbers
    for v, c in dest:
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise DataError(f"{path}: {bad.size} row(s) with NaN or inf (first: data row "
                            f"{bad[0] + 1}, column '{c}'); remove or interpolate them")
        big = np.flatnonzero(np.abs(v) > MAX_MAGNITUDE)
        if big.size:
            raise DataError(f"{path}: data row {big[0] + 1}, column '{c}': {v[big[0]]:.3g} is "
                            f"beyond {MAX_MAGNITUDE:g} in magnitude and would overflow the "
                            f"fit; rescale (change units)")
    if t is not None:
        _check_time_column(t, Ts, path)
    return y, u


def _nfc(name: str) -> str:
    """A name in Unicode normal form NFC (an accent composed with its letter)."""
    return unicodedata.normalize("NFC", name)


#: Separators a spreadsheet may write instead of the comma, with their names.
_SEPARATORS = ((";", "semicolons"), ("\t", "tabs"), ("|", "vertical bars"), (" ", "spaces"))


def _check_header(header, want, path) -> None:
    """One clear DataError if the header does not name the model's columns exactly."""
    tcol = [h for h in header if h in _TIME_COLUMNS]
    missing = [c for c in want if c not in header]
    extra = [h for h in header if h not in want and h not in _TIME_COLUMNS]
    if not (missing or extra or len(set(header)) != len(header) or len(tcol) > 1):
        return
    expected = f"expected {want} (+ optional 'time')"
    for sep, what in _SEPARATORS:
        cells = [c.strip() for h in header for c in h.split(sep)]
        if missing and any(sep in h for h in header) and not [c for c in want
                                                              if c not in cells]:
            raise DataError(f"{path}: the header {','.join(header)!r} is separated by {what}; "
                            f"the separator must be a comma (save as comma-separated values)")
    blank = [j for j, h in enumerate(header) if not h or h.startswith("Unnamed: ")]
    if blank and not missing:
        j = blank[0]
        if j == len(header) - 1 and not header[j]:
            why = "a comma at the end of every line? remove it"
        elif j == 0:
            why = ("an index column, as pandas writes by default? save with index=False or "
                   "remove that column")
        else:
            why = "remove that column or name it"
        raise DataError(f"{path}: header column {j + 1} has no name ({why}); {expected}")
    near = [(h, c) for h in extra for c in missing if h.strip().casefold() == c.casefold()]
    raise DataError(f"{path}: columns {header}; {expected}"
                    + (f"; missing {missing}" if missing else "")
                    + (f"; unexpected {extra}" if extra else "")
                    + (f" ({near[0][0]!r} differs from {near[0][1]!r} only in case)"
                       if near else ""))


def _check_time_column(t, Ts: float, path) -> None:
    """One clear DataError if the time column is not one row every Ts (0.1 % tolerance)."""
    dtv = np.diff(t)
    tol = 1e-3 * Ts
    off = np.flatnonzero(np.abs(dtv - Ts) > tol)
    if not off.size:
        return
    k = int(off[0])
    step, row = float(dtv[k]), k + 2  # t[k + 1] is on data row k + 2
    at = f"data row {row} ({t[k]:.10g} s -> {t[k + 1]:.10g} s)"
    need = f"one row every Ts = {Ts:g} s (tolerance 0.1 %, {tol:.3g} s)"
    if step <= 0:
        what = "goes backwards" if step < 0 else "repeats a time"
        raise DataError(f"{path}: the time column {what} at {at}; greybox needs the rows in "
                        f"time order, {need}")
    med = float(np.median(dtv))
    if abs(med - Ts) > tol:
        raise DataError(f"{path}: the time column steps by {med:g} s (median); the model's Ts "
                        f"is {Ts:g} s: check Ts in the model and the time unit (seconds)")
    ratio = step / Ts
    if ratio > 1.5 and abs(ratio - round(ratio)) < 0.1:
        raise DataError(f"{path}: {round(ratio) - 1} sample(s) missing before {at}; greybox "
                        f"needs {need}: fill the gap (interpolate) or cut the record there")
    worst = float(np.max(np.abs(dtv - Ts)))
    raise DataError(f"{path}: the time steps jitter by up to {100 * worst / Ts:.2g} % of Ts, "
                    f"first beyond the tolerance at {at}; greybox needs {need}: resample the "
                    f"data onto a regular time grid")


_CHUNK_BYTES = 1 << 22
#: Longest header line read [bytes]; a longer first line is not a CSV header.
_MAX_HEADER_BYTES = 1 << 20


def _read_numbers(f, first: int, ncol: int, header, path) -> list:
    """The data rows as arrays (rows, ncol): numpy's compiled reader, else chunk by chunk.

    ``numpy.loadtxt`` reads a clean file in one pass (peak about 1.1x the
    numbers); on any irregularity (a bad cell, a ragged row, blank cells,
    bytes that are not UTF-8) the file is re-read by :func:`_parse_chunk`,
    which accepts what greybox accepts and names the row and column at fault.
    """
    start = f.tell()
    try:
        text = io.TextIOWrapper(f, encoding="utf-8", newline=None)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. "input contained no data"
            arr = np.loadtxt(text, delimiter=",", comments=None, ndmin=2, dtype=float)
        text.detach()
        if arr.shape[1] == ncol or arr.size == 0:
            return [arr.reshape(-1, ncol)]
    except (ValueError, UnicodeDecodeError):
        text.detach()
    f.seek(start)
    return [_parse_chunk(chunk, line, ncol, header, path) for line, chunk in _chunks(f, first)]


def _read_header(f, path):
    """Header cells and the header's line number (blank leading lines skipped)."""
    line_no = 0
    while True:
        raw = f.readline(_MAX_HEADER_BYTES)
        if not raw:
            raise DataError(f"{path} is empty; expected a header row and data")
        line_no += 1
        if len(raw) == _MAX_HEADER_BYTES and not raw.endswith(b"\n"):
            raise DataError(f"{path}: line {line_no} is longer than "
                            f"{_MAX_HEADER_BYTES >> 20} MB; expected a header row naming the "
                            f"columns: is it a CSV file?")
        if b"\r" in raw.rstrip(b"\r\n"):
            raise DataError(f"{path}: its lines end with a carriage return alone (CR, as old "
                            f"Mac programs write); save it with LF or CRLF line endings")
        if b"\0" in raw:
            raise DataError(f"{path} holds NUL bytes (line {line_no}); it is not a CSV text file")
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError as e:
            raise DataError(f"{path} is not UTF-8 text (line {line_no}: {e.reason}); save it "
                            f"as UTF-8") from e
        if line.strip().strip(","):
            line = line.lstrip("\ufeff")  # a second byte-order mark (before a quote too)
            try:
                cells = next(csv.reader([line]))
            except csv.Error as e:
                raise DataError(f"{path}: header is not readable CSV ({e})") from e
            cells = [_nfc(h.strip()) for h in cells]
            return cells, line_no


def _chunks(f, first):
    """``(first line number, bytes)`` of whole lines, about 4 MB at a time."""
    while True:
        chunk = f.read(_CHUNK_BYTES)
        if not chunk:
            return
        if not chunk.endswith(b"\n"):
            chunk += f.readline()
        yield first, chunk
        first += chunk.count(b"\n")


def _parse_chunk(chunk: bytes, first: int, ncol: int, header, path):
    """Numbers of whole CSV lines, shape (rows, ncol): numpy's parser, else a careful one."""
    b = np.frombuffer(chunk, dtype=np.uint8)
    nl = np.flatnonzero(b == 10)
    if b.size and b[-1] != 10:
        nl = np.append(nl, b.size)
    nlines = nl.size
    if nlines and b.max() < 128:  # plain ASCII
        cpos = np.flatnonzero(b == 44)
        per_line = np.bincount(np.searchsorted(nl, cpos), minlength=nlines)
        line_len = np.diff(nl, prepend=-1)
        if np.all(per_line == ncol - 1) and np.all(line_len > ncol):
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("error")  # "could not be read to its end": a bad cell
                    a = np.fromstring(chunk.replace(b"\n", b","), sep=",")
            except (ValueError, DeprecationWarning):
                a = None
            if a is not None and a.size == nlines * ncol:
                return a.reshape(nlines, ncol)
    try:
        text = chunk.decode("utf-8")
    except UnicodeDecodeError as e:
        line = first + chunk[:e.start].count(b"\n")
        raise DataError(f"{path} is not UTF-8 text (line {line}: {e.reason}); save it as "
                        f"UTF-8") from e
    return _parse_lines_slowly(text.splitlines(keepends=True), first, ncol, header, path)


#: Characters that look like a minus sign but are not the ASCII hyphen-minus.
_MINUS_LOOKALIKES = {"\u2212": "minus sign U+2212", "\u2012": "figure dash U+2012",
                     "\u2013": "en dash U+2013", "\u2014": "em dash U+2014",
                     "\u2010": "hyphen U+2010", "\ufe63": "small hyphen-minus U+FE63",
                     "\uff0d": "fullwidth hyphen-minus U+FF0D"}


def _cell_value(c: str, where: str) -> float:
    """The number in one CSV cell, or one DataError saying what is wrong with it."""
    try:
        v = float(c)
    except ValueError:
        hint = ""
        odd = [name for ch, name in _MINUS_LOOKALIKES.items() if ch in c]
        if odd:
            hint = f": it holds a Unicode {odd[0]}; write the ASCII minus '-' instead"
        elif any(sep in c for sep in ";\t|"):
            hint = ": the separator must be a comma"
        raise DataError(f"{where}: {c!r} is not a number{hint}") from None
    if "_" in c:
        raise DataError(f"{where}: {c!r} holds '_' as a digit separator; write plain numbers "
                        f"({c.replace('_', '').strip()}), as other programs would not read it "
                        f"as {v:g}")
    return v


def _parse_lines_slowly(lines, first, ncol, header, path):
    """Cell by cell: skips blank lines, names the row and column of a bad cell."""
    rows = []
    try:
        for i, r in enumerate(csv.reader(lines)):
            if not any(c.strip() for c in r):
                continue
            if len(r) != ncol:
                raise DataError(f"{path}, row {first + i}: {len(r)} cells; expected {ncol}")
            rows.append([_cell_value(c, f"{path}, row {first + i}, column '{header[j]}'")
                         for j, c in enumerate(r)])
    except csv.Error as e:
        raise DataError(f"{path} is not a readable CSV file ({e})") from e
    return np.array(rows, dtype=float).reshape(-1, ncol)
