"""Input checks used once, at the public boundary of every greybox function.

Messages follow the pattern "what, found, expected, hint". Nothing here
computes results; these helpers only convert and check.
"""

from __future__ import annotations

from collections.abc import Sequence

import warnings

import control as ct
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .exceptions import CovarianceError, DataError, DimensionError, GreyboxWarning, ModelError

#: Largest magnitude accepted in any signal or matrix: sums of squares and
#: covariances of values up to 1e150 stay far below float64's 1.8e308.
MAX_MAGNITUDE = 1e150
#: Range of the peak magnitude of a measured record's signal in
#: :func:`check_records`: the laws' cubic terms and their sums of squares
#: (x^6) neither overflow nor underflow inside it.
RECORD_RANGE = (1e-50, 1e50)
#: A measured output varying (RMS about its mean) less than this fraction of
#: its noise standard deviation sqrt(R_ii) is refused: data and R disagree on units.
MIN_SIGNAL_TO_NOISE = 1e-6

__all__ = [
    "MAX_MAGNITUDE",
    "RECORD_RANGE",
    "check_records",
    "check_input_record",
    "check_matrix",
    "check_vector",
    "as_signal",
    "check_covariance",
    "check_signal",
    "check_same_length",
    "check_discrete",
    "check_statespace",
    "resolve_channels",
    "check_positive",
    "check_real",
]


def check_flag(value, name: str) -> bool:
    """``value`` as a bool; DataError unless it is True or False (not 1, "yes", None)."""
    if not isinstance(value, (bool, np.bool_)):
        raise DataError(f"{name} must be True or False; found {value!r}")
    return bool(value)


def check_real(value, name: str) -> float:
    """Return ``value`` as a float if it is a finite real number (not a string or bool)."""
    if isinstance(value, (str, bytes, bool, np.bool_)) or value is None:
        raise DimensionError(f"{name} must be a number; found {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError) as e:
        raise DimensionError(f"{name} must be a number; found {value!r}") from e
    if not np.isfinite(v) or abs(v) > MAX_MAGNITUDE:
        raise DataError(f"{name} must be finite (|{name}| <= {MAX_MAGNITUDE:g}); found {value!r}")
    return v


def check_positive(value, name: str, *, integer: bool = False, allow_zero: bool = False):
    """Return ``value`` if it is a finite positive number (or integer).

    Strings and booleans are refused (``"0.8"`` is a typo for 0.8, not 0.8).
    """
    if isinstance(value, (str, bytes, bool, np.bool_)):
        raise DimensionError(f"{name} must be a number; found {value!r} "
                             f"({type(value).__name__})")
    try:
        v = float(value)
    except (TypeError, ValueError) as e:
        raise DimensionError(f"{name} must be a number; found {value!r}") from e
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise DataError(f"{name} must be finite and {bound}; found {value!r}")
    if integer:
        if int(v) != v:
            raise DimensionError(f"{name} must be an integer; found {value!r}")
        return int(v)
    return v


def float_array(x) -> NDArray[np.float64]:
    """``np.array(x, dtype=float)`` that refuses complex values instead of dropping them.

    Raises TypeError or ValueError (callers turn them into greybox errors).
    """
    if isinstance(x, (str, bytes)):
        raise ValueError(f"a string ({x!r}) is not a number")
    if isinstance(x, np.ma.MaskedArray):
        if np.ma.count_masked(x):
            raise ValueError(f"a masked array with {np.ma.count_masked(x)} masked entries; "
                             f"greybox does not skip masked values: fill or remove them")
        x = np.ma.getdata(x)
    if _is_frame(x):
        raise ValueError("a pandas DataFrame, whose labels cannot be matched here; pass "
                         "df[names].to_numpy() in the order expected")
    a = np.asarray(x)
    if a.dtype.kind == "c":
        if np.any(a.imag != 0):
            raise ValueError("complex values; expected real numbers")
        a = a.real
    if a.dtype.kind in "USO":
        a = np.array(a.tolist() if a.dtype.kind == "O" else a, dtype=float)
    return np.array(a, dtype=float)


def as_signal(y, name: str) -> NDArray[np.float64]:
    """Convert to a float array with time as the last axis (1-D -> one row).

    Only converts; shapes and finiteness are checked by :func:`check_signal`.
    """
    try:
        return np.atleast_2d(float_array(y))
    except (TypeError, ValueError) as e:
        raise DimensionError(f"{name} must be a numeric array; could not convert it ({e})") from e


def check_vector(v, n: int, name: str, *, what: str = "") -> NDArray[np.float64]:
    """Convert ``v`` to a finite float vector of length n (e.g. an initial state)."""
    try:
        a = float_array(v).reshape(-1)
    except (TypeError, ValueError) as e:
        raise DimensionError(f"{name} must be a numeric vector of length {n}; could not "
                             f"convert it ({e})") from e
    if a.size != n:
        raise DimensionError(f"{name} has {a.size} entries; expected {what}{n}")
    if not np.all(np.isfinite(a)):
        raise DataError(f"{name} contains NaN or inf; give finite values")
    _check_magnitude(a, name)
    return a


def _check_magnitude(a, name: str) -> None:
    """Refuse finite values so large that their squares would overflow."""
    if a.size:
        big = max(abs(float(np.nanmax(a))), abs(float(np.nanmin(a))))  # no |a| copy
        if big > MAX_MAGNITUDE:
            raise DataError(f"{name} has values up to {big:.3g} in magnitude; above "
                            f"{MAX_MAGNITUDE:g} sums of squares overflow: rescale (change units)")


def check_matrix(M: ArrayLike, shape: tuple[int, int], name: str) -> NDArray[np.float64]:
    """Convert ``M`` to a finite float 2-D array of the given shape.

    A scalar is accepted for a (1, 1) matrix; a 1-D array of length n is
    accepted for shape (n, 1) or (1, n) when unambiguous.
    """
    try:
        A = float_array(M)
    except (TypeError, ValueError) as e:
        raise DimensionError(f"{name} must be a numeric array; could not convert it ({e})") from e
    if A.ndim == 0 and shape == (1, 1):
        A = A.reshape(1, 1)
    elif A.ndim == 1:
        if shape[1] == 1 and A.size == shape[0]:
            A = A.reshape(shape)
        elif shape[0] == 1 and A.size == shape[1]:
            A = A.reshape(shape)
    if A.shape != tuple(shape):
        raise DimensionError(f"{name} has shape {A.shape}; expected {tuple(shape)}")
    if not np.all(np.isfinite(A)):
        raise DataError(f"{name} contains NaN or inf; all entries must be finite")
    _check_magnitude(A, name)
    return A


def check_covariance(
    M: ArrayLike, n: int, name: str, *, definite: bool = True, rtol: float = 1e-10
) -> NDArray[np.float64]:
    """Check a covariance matrix: shape (n, n), finite, symmetric, PD or PSD.

    A 1-D array of length n is read as a diagonal; a scalar with n == 1 as 1x1.

    Parameters
    ----------
    definite : bool
        If True the matrix must be positive definite, otherwise positive
        semidefinite.
    """
    try:
        A = float_array(M) if not np.isscalar(M) else float_array([[M]])
    except (TypeError, ValueError) as e:
        raise DimensionError(f"{name} must be a numeric ({n}, {n}) matrix or a length-{n} "
                             f"diagonal; could not convert it ({e})") from e
    if A.ndim == 1 and A.size == n:
        A = np.diag(A)
    A = check_matrix(A, (n, n), name)
    if n == 0:
        return A
    scale = max(np.max(np.abs(A)), np.finfo(float).tiny)
    if np.max(np.abs(A - A.T)) > rtol * scale * 1e3:
        raise CovarianceError(
            f"{name} is not symmetric (max |{name} - {name}.T| = "
            f"{np.max(np.abs(A - A.T)):.3g}); pass a symmetric matrix, e.g. ({name} + {name}.T)/2"
        )
    A = 0.5 * (A + A.T)
    dg = np.diag(A)
    if definite and np.any(dg <= 0):
        raise CovarianceError(
            f"{name} is not positive definite: diagonal entry {int(np.argmin(dg))} is "
            f"{dg.min():.3g}; a covariance here must be > 0 on its diagonal"
        )
    if not definite and np.any(dg < 0):
        raise CovarianceError(
            f"{name} is not positive semidefinite: diagonal entry {int(np.argmin(dg))} is "
            f"{dg.min():.3g} < 0; check its sign"
        )
    # eigenvalues of the diagonally scaled matrix: channels of very different
    # units (1e-12 next to 1) are fine, only the correlation structure counts
    d = np.where(dg > 0, 1.0 / np.sqrt(np.where(dg > 0, dg, 1.0)), 0.0)
    w = np.linalg.eigvalsh(A * d[:, None] * d[None, :])
    if definite and w.min() <= rtol:
        raise CovarianceError(
            f"{name} is not positive definite: its correlation matrix has smallest "
            f"eigenvalue {w.min():.3g} (channels perfectly correlated); add a small positive "
            f"diagonal"
        )
    if not definite and w.min() < -1e-8:
        raise CovarianceError(
            f"{name} is not positive semidefinite (correlation-matrix eigenvalue "
            f"{w.min():.3g} < 0); check its sign and symmetry"
        )
    return A


def check_signal(
    y: ArrayLike,
    nrows: int | None,
    name: str,
    *,
    min_steps: int = 1,
    allow_nan: bool = False,
) -> NDArray[np.float64]:
    """Convert a signal to a float array of shape (nrows, nsteps).

    Time is the last axis. A 1-D array is accepted when ``nrows == 1``;
    ``nrows=None`` takes the number of rows from the data (a 1-D array or a
    scalar is one row).
    """
    y = _unmasked(y, name, allow_nan)
    if nrows is None:
        a = as_signal(y, name)
        nrows = a.shape[0]
    else:
        try:
            a = float_array(y)
        except (TypeError, ValueError) as e:
            raise DimensionError(f"{name} must be a numeric array; could not convert it "
                                 f"({e})") from e
    if a.ndim == 1 and nrows == 1:
        a = a.reshape(1, -1)
    if a.ndim != 2 or a.shape[0] != nrows:
        hint = ""
        if a.ndim == 2 and a.shape[1] == nrows:
            hint = " (time must be the last axis: pass the transpose)"
        raise DimensionError(
            f"{name} has shape {a.shape}; expected ({nrows}, nsteps){hint}"
        )
    if a.shape[1] < min_steps:
        raise DataError(
            f"{name} has {a.shape[1]} samples; at least {min_steps} are needed"
        )
    if not allow_nan and not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise DataError(
            f"{name} contains NaN or inf (first at signal {bad[0]}, sample {bad[1]}); "
            f"remove or interpolate those samples"
        )
    if allow_nan and np.any(np.isinf(a)):
        raise DataError(f"{name} contains inf; measurements must be finite or NaN (missing)")
    if a.size and not (allow_nan and np.all(np.isnan(a))):
        _check_magnitude(a, name)
    return a


def check_same_length(*named: tuple[str, NDArray]) -> int:
    """Check that several (name, signal) pairs share their last-axis length."""
    lengths = {name: a.shape[-1] for name, a in named}
    if len(set(lengths.values())) > 1:
        desc = ", ".join(f"{k}: {v}" for k, v in lengths.items())
        raise DimensionError(f"signals have different numbers of samples ({desc}); they must match")
    return next(iter(lengths.values()))


def check_statespace(sys, name: str = "sys") -> ct.StateSpace:
    """Check that ``sys`` is a python-control StateSpace with finite matrices."""
    if not isinstance(sys, ct.StateSpace):
        raise ModelError(
            f"{name} must be a control.StateSpace; found {type(sys).__name__}. "
            f"Convert it with control.ss(...)"
        )
    for m in ("A", "B", "C", "D"):
        if not np.all(np.isfinite(getattr(sys, m))):
            raise DataError(f"{name}.{m} contains NaN or inf")
    return sys


def check_discrete(sys, name: str = "sys") -> ct.StateSpace:
    """Check that ``sys`` is a discrete-time StateSpace with a numeric sampling period."""
    check_statespace(sys, name)
    if sys.dt is None or sys.dt is False or sys.dt == 0:
        raise ModelError(
            f"{name} is a continuous-time model (dt={sys.dt!r}); a discrete-time model is "
            f"needed. Discretize it first, e.g. greybox.discretize(sys, dt) (ZOH)"
        )
    if sys.dt is True:
        raise ModelError(
            f"{name} has an unspecified sampling period (dt=True); give it a numeric dt [s]"
        )
    return sys


def resolve_channels(
    channels: int | str | Sequence[int | str] | None,
    labels: Sequence[str],
    name: str,
) -> list[int]:
    """Turn channel labels or indices into a sorted list of unique indices."""
    if channels is None:
        return []
    if isinstance(channels, (int, np.integer, str)):
        channels = [channels]
    if isinstance(channels, np.ndarray):
        channels = channels.reshape(-1).tolist()
    if not isinstance(channels, (list, tuple, range)):
        raise DimensionError(f"{name}: expected a label, an index or a list of them; found "
                             f"{channels!r}")
    out: list[int] = []
    for c in channels:
        if isinstance(c, str):
            if c not in labels:
                raise DimensionError(
                    f"{name}: no signal named {c!r}; available: {list(labels)}"
                )
            out.append(list(labels).index(c))
        elif isinstance(c, (int, np.integer)) and not isinstance(c, (bool, np.bool_)):
            if not 0 <= int(c) < len(labels):
                raise DimensionError(
                    f"{name}: index {int(c)} out of range; expected 0..{len(labels) - 1}"
                )
            out.append(int(c))
        else:
            raise DimensionError(f"{name}: entries must be labels or indices; found {c!r}")
    if len(set(out)) != len(out):
        raise DimensionError(f"{name}: channels repeated in {list(channels)}")
    return out


def check_input_record(u, ninputs: int, nsteps=None) -> np.ndarray:
    """The known-input record of a simulation, shape (ninputs, nsteps).

    ``u`` may be None only for a model without inputs (then ``nsteps`` sets
    the length); when both are given, ``nsteps`` must equal u's length.
    """
    if u is None:
        if ninputs:
            raise DataError(f"sys has {ninputs} inputs; pass u with shape ({ninputs}, nsteps)")
        nsteps = check_positive(nsteps, "nsteps", integer=True)
        return np.zeros((0, nsteps))
    u = check_signal(u, ninputs, "u")
    N = u.shape[1]
    if nsteps is not None and check_positive(nsteps, "nsteps", integer=True) != N:
        raise DimensionError(f"nsteps = {nsteps} but u has {N} samples; give u alone (its "
                             f"length sets nsteps) or u[:, :nsteps]")
    return u


def _is_frame(x) -> bool:
    """True for a pandas DataFrame (or anything with its labelled two axes), without pandas."""
    return not isinstance(x, np.ndarray) and hasattr(x, "columns") and hasattr(x, "index") \
        and hasattr(x, "to_numpy")


def _unmasked(y, name: str, allow_nan: bool):
    """A masked signal's data: masked samples as NaN (missing) where allowed, else refused."""
    if not isinstance(y, np.ma.MaskedArray) or not np.ma.count_masked(y):
        return np.ma.getdata(y) if isinstance(y, np.ma.MaskedArray) else y
    if allow_nan:
        return np.ma.filled(np.ma.asarray(y, dtype=float), np.nan)
    mask = np.atleast_2d(np.ma.getmaskarray(y))
    first = np.argwhere(mask)[0]
    raise DataError(f"{name} is a masked array with {int(mask.sum())} masked sample(s) (first "
                    f"at signal {first[0]}, sample {first[-1]}); greybox needs every sample "
                    f"here and does not skip masked ones: cut the record or interpolate them")


def _frame_rows(x, labels, name: str):
    """A DataFrame's signals as rows in the order of ``labels`` (its labels honoured).

    Signals may be its columns (samples as rows, as read from a CSV) or its
    index (the transpose). Anything that is not a DataFrame is returned as is.
    """
    if not _is_frame(x):
        return x
    cols, idx = [str(c) for c in x.columns], [str(i) for i in x.index]
    values = np.asarray(x.to_numpy())
    if labels and set(labels) <= set(cols):
        return values[:, [cols.index(c) for c in labels]].T
    if labels and set(labels) <= set(idx):
        return values[[idx.index(c) for c in labels], :]
    raise DimensionError(f"{name} is a DataFrame labelled {cols[:6]} (columns) and "
                         f"{idx[:3]}... (index); expected the model's signals {list(labels)} as "
                         f"its column (or index) labels: rename them, or pass an array "
                         f"with rows in that order")


_RECORDS = {"y": "estimation output", "u": "estimation input", "y_val": "validation output",
            "u_val": "validation input"}


def _check_record_scale(a, labels, name: str) -> None:
    """Refuse a measured signal whose peak magnitude lies outside RECORD_RANGE."""
    lo, hi = RECORD_RANGE
    what = f"the {_RECORDS[name]} {{!r}} ({name})"
    peak = np.max(np.abs(a), axis=1) if a.size else np.zeros(a.shape[0])
    for i, v in enumerate(peak):
        if v > hi or 0 < v < lo:
            raise DataError(f"{what.format(labels[i])} never exceeds {v:.3g} in magnitude; "
                            f"below {lo:g} the squares of its cubic law terms underflow: "
                            f"rescale it (change units)" if v < lo else
                            f"{what.format(labels[i])} reaches {v:.3g} in magnitude; above "
                            f"{hi:g} the cubic law terms and their sums of squares overflow: "
                            f"rescale it (change units)")


def _check_noise_scale(y, R, labels) -> None:
    """Refuse outputs that vary far less than the noise R gives them (units disagree)."""
    try:
        Rd = np.asarray(R, dtype=float)
        var = np.diag(Rd) if Rd.ndim == 2 else Rd.reshape(-1)
    except (TypeError, ValueError, OverflowError):
        return  # check_covariance refuses it
    if var.size != y.shape[0] or not np.all(np.isfinite(var) & (var > 0)):
        return  # check_covariance refuses it
    sd = np.sqrt(var)
    rms = np.sqrt(np.mean((y - y.mean(axis=1, keepdims=True)) ** 2, axis=1))
    for i in range(y.shape[0]):
        if 0 < rms[i] < MIN_SIGNAL_TO_NOISE * sd[i]:
            raise DataError(f"R gives output {labels[i]!r} a noise of standard deviation "
                            f"{sd[i]:.3g}, but its estimation record (y) varies by only "
                            f"{rms[i]:.3g} (RMS about its "
                            f"mean), {sd[i] / rms[i]:.2g} times less: the data and R are in "
                            f"different units; rescale one of them")


def check_records(sys, y, u, y_val, u_val, R, *, min_steps: int, min_val_steps: int):
    """The estimation and validation records of a close-the-loop run, checked.

    Converts and checks shapes (a DataFrame is matched to the model's signal
    names by its labels; a masked sample is refused), refuses records whose
    scale overflows the laws (:data:`RECORD_RANGE`) or disagrees with R
    (:data:`MIN_SIGNAL_TO_NOISE`), and warns (:class:`GreyboxWarning`) when
    the validation record is the estimation record, an input is zero
    throughout, or a validation output is constant.

    Parameters
    ----------
    sys : control.NonlinearIOSystem or control.StateSpace
        The model (its output and input labels name the signals).
    y, u, y_val, u_val : array_like or DataFrame
        Estimation and validation records, time along the last axis.
    R : array_like
        Measurement-noise covariance (checked later by :func:`check_covariance`).
    min_steps, min_val_steps : int
        Fewest samples of each record.

    Returns
    -------
    y, u, y_val, u_val : ndarray
    """
    outs, ins = list(sys.output_labels), list(sys.input_labels)
    same = y_val is y
    y = check_signal(_frame_rows(y, outs, "y"), len(outs), "y", min_steps=min_steps)
    u = check_signal(_frame_rows(u, ins, "u"), len(ins), "u")
    check_same_length(("y", y), ("u", u))
    y_val = check_signal(_frame_rows(y_val, outs, "y_val"), len(outs), "y_val",
                         min_steps=min_val_steps)
    u_val = check_signal(_frame_rows(u_val, ins, "u_val"), len(ins), "u_val")
    check_same_length(("y_val", y_val), ("u_val", u_val))
    for a, labels, name in ((y, outs, "y"), (u, ins, "u"), (y_val, outs, "y_val"),
                            (u_val, ins, "u_val")):
        _check_record_scale(a, labels, name)
    _check_noise_scale(y, R, outs)
    if same or (y.shape == y_val.shape and np.array_equal(y, y_val) and
                np.array_equal(u, u_val)):
        warnings.warn("the estimation and validation data are the same; the validation table "
                      "then measures the fit, not the prediction of fresh data", GreyboxWarning,
                      stacklevel=3)
    zero = [ins[i] for i in range(len(ins)) if not np.any(u[i])]
    if zero:
        warnings.warn(f"input(s) {zero} are zero throughout the estimation record: they do not "
                      f"excite the plant, so nothing can be learnt about their channels",
                      GreyboxWarning, stacklevel=3)
    flat = [outs[i] for i in range(len(outs)) if np.ptp(y_val[i]) == 0]
    if flat:
        warnings.warn(f"validation output(s) {flat} are constant: there is nothing to compare; "
                      f"their validation SE only measures the distance to that constant",
                      GreyboxWarning, stacklevel=3)
    return y, u, y_val, u_val


def check_parsimony(parsimony) -> float:
    """The retired ``parsimony`` argument of close the loop: still checked (>= 1), and a
    DeprecationWarning when set, since the choice no longer reads it."""
    parsimony = check_positive(parsimony, "parsimony")
    if not parsimony >= 1:
        raise DataError(f"need parsimony >= 1; found {parsimony} (it no longer has an "
                        f"effect: leave it out)")
    if parsimony != 1.1:
        warnings.warn("parsimony no longer has an effect: candidates are chosen by one "
                      "output-error criterion (greybox.metrics.criterion_scores); leave it out",
                      DeprecationWarning, stacklevel=3)
    return parsimony
