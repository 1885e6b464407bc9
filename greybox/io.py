"""File input and output: safe output folders, atomic writes, strict JSON.

Nothing here computes; it only reads and writes records.

A report folder is written in one piece: :func:`check_output_dir` checks,
before any computing, that the folder may be written (creating nothing);
:func:`stage_output_dir` makes a hidden temporary folder beside the target
into which the files are written; :func:`commit_output_dir` puts it in
place with renames while Ctrl-C is held back, so that an interrupted run
leaves either the old report or the new one, never a mix. Files and
folders get the permissions the user's umask allows.

Every JSON document greybox writes passes a strict parser: non-finite
numbers become ``null`` and the object holding them gets a ``<key>_reason``
field (:func:`json_safe`, :func:`dumps_json`).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path

import numpy as np

from .exceptions import OutputExistsError

__all__ = ["OutputExistsError", "prepare_output_dir", "check_output_dir", "output_target",
           "record_outputs", "atomic_write_text", "atomic_write_json", "save_figure",
           "json_safe", "dumps_json", "stage_output_dir", "commit_output_dir",
           "discard_output_dir", "deferred_interrupt"]

_MARKER = ".greybox-output"
_STAGE = ".greybox-staging-"
_OLD = ".greybox-old-"


def _umask() -> int:
    """The process umask, read without a window in which it is changed (Linux)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):  # pragma: no cover - not Linux
        pass
    old = os.umask(0o022)  # pragma: no cover
    os.umask(old)  # pragma: no cover
    return old  # pragma: no cover


def _normal_mode(path, *, folder: bool = False) -> None:
    """Give a file made by ``mkstemp``/``mkdtemp`` (mode 0600/0700) the umask's mode."""
    os.chmod(path, (0o777 if folder else 0o666) & ~_umask())


def prepare_output_dir(path: str | os.PathLike, *, force: bool = False,
                       kind: str = "report") -> Path:
    """Create (or reuse) an output folder without clobbering a user's files.

    A folder that greybox created carries a marker file (its first line the
    kind of output, then the files it wrote) and may be reused: the files of
    the previous run are removed so that no stale figure survives. An
    existing non-empty folder without the marker is refused, even with
    ``force``; a previous report is replaced only with ``force`` (see
    :func:`check_output_dir` for every rule). Writing straight into
    the folder is not atomic: the command line uses :func:`stage_output_dir`
    and :func:`commit_output_dir` instead.

    Parameters
    ----------
    path : str or path-like
        The output folder.
    force : bool
        Replace a previous greybox output.
    kind : str
        Kind of output ("report", "demo"), recorded in the marker.

    Returns
    -------
    pathlib.Path
    """
    previous = check_output_dir(path, force=force, kind=kind)
    p = output_target(path)
    p.mkdir(parents=True, exist_ok=True)
    for name in previous:  # only files greybox itself listed, inside this folder
        f = p / Path(name).name
        if f.is_file():
            f.unlink()
    atomic_write_text(p / _MARKER, kind + "\n")
    return p


def _nearest_existing(p: Path) -> Path:
    q = p.absolute()
    while not q.exists() and q != q.parent:
        if os.path.lexists(q):  # a link to nothing: creating below it would fail late
            raise OutputExistsError(f"cannot create {p}: {q} is a symbolic link to "
                                    f"{os.readlink(q)}, which does not exist; choose another "
                                    f"--out")
        q = q.parent
    return q


def output_target(path: str | os.PathLike) -> Path:
    """The output folder as an absolute path with every symbolic link resolved.

    A link to a folder is followed (the folder it points to is written and
    the link kept); an empty name, a link to nothing and a loop of links are
    refused with :class:`OutputExistsError`.

    Parameters
    ----------
    path : str or path-like
        The output folder as the user wrote it.

    Returns
    -------
    pathlib.Path
    """
    if not os.fspath(path).strip():
        raise OutputExistsError("--out is empty; give the name of a new folder for the output")
    p = Path(path).absolute()
    try:
        return p.resolve(strict=True)
    except FileNotFoundError:
        if os.path.lexists(p):
            raise OutputExistsError(f"{path} is a symbolic link to {os.readlink(p)}, which "
                                    f"does not exist; give a folder (new or greybox's) as "
                                    f"--out") from None
    except NotADirectoryError:
        pass  # below a file: check_output_dir names it
    except (RuntimeError, OSError) as e:  # ELOOP (RuntimeError before Python 3.13)
        raise OutputExistsError(f"{path} is a symbolic link that leads back to itself (a "
                                f"loop); give a folder as --out") from e
    return Path(os.path.realpath(p))


def _protected(p: Path, inputs) -> str:
    """Why writing ``p`` would move the working folder or an input file ('' if it would not)."""
    try:
        here = Path.cwd().resolve()
    except OSError:  # the working folder was removed: nothing of it to protect
        here = None
    if here is not None and (p == here or p in here.parents):
        return "the current folder" if p == here else "a folder holding the current folder"
    for f in inputs:
        try:
            real = Path(f).resolve()
        except (OSError, RuntimeError):
            continue
        if p in real.parents:
            return f"the folder of the input file {f}"
    return ""


def _marker_lines(p: Path) -> list[str]:
    try:
        return (p / _MARKER).read_text().splitlines() if (p / _MARKER).is_file() else []
    except (OSError, UnicodeDecodeError):
        return []


def check_output_dir(path: str | os.PathLike, *, force: bool = False,
                     kind: str = "report", inputs=()) -> list[str]:
    """Raise :class:`OutputExistsError` if the output folder may not be written.

    Creates nothing: call it before a long computation to fail fast. The
    folder (symbolic links resolved, see :func:`output_target`) must be new,
    empty, or one greybox wrote (its marker file lists the files written):

    * a folder holding files greybox did not write, and no marker, is
      refused, even with ``force``;
    * a previous report is replaced only with ``force`` (a demo replaces a
      demo); another kind of greybox output (a demo over a report) only with
      ``force``, and then only the files greybox listed are removed;
    * files a user added to a greybox folder are kept (moved into the new
      one), except in the current folder, a folder holding it, or a folder
      holding an input file: those are replaced only if every file in them is
      greybox's;
    * the parent (or nearest existing ancestor) must be a writable folder.

    Parameters
    ----------
    path : str or path-like
        The output folder.
    force : bool
        Allow replacing a previous greybox output.
    kind : str
        Kind of output ("report", "demo").
    inputs : sequence of str or path-like
        The input files of the run (never moved or removed).

    Returns
    -------
    list of str
        The files a previous greybox run listed in the folder's marker.
    """
    p = output_target(path)
    if p.exists() and not p.is_dir():
        raise OutputExistsError(f"{path} exists and is not a folder; choose another --out")
    previous: list[str] = []
    entries = sorted(f.name for f in p.iterdir()) if p.exists() else []
    if entries:
        lines = _marker_lines(p)
        was = lines[0].strip() if lines else ""
        listed = [ln.strip() for ln in lines[1:] if ln.strip()]
        foreign = [f for f in entries if f != _MARKER and f not in listed]
        if not was:
            raise OutputExistsError(
                f"{path} already exists and holds files greybox did not write ("
                f"{', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}); choose a new "
                f"or empty folder as --out (--force replaces only a folder greybox wrote)")
        if was != kind and not force:
            raise OutputExistsError(f"{path} holds a greybox {was}, not a {kind}: writing a "
                                    f"{kind} there would mix the two; choose another --out or "
                                    f"pass --force to replace the {was}")
        if was == kind == "report" and not force:
            raise OutputExistsError(
                f"{path} already holds a greybox report; pass --force to overwrite it"
            )
        why = _protected(p, inputs) if foreign else ""
        if why:
            raise OutputExistsError(f"{path} is {why} and holds files greybox did not write ("
                                    f"{', '.join(foreign[:3])}); greybox replaces such a folder "
                                    f"only when every file in it is greybox's: choose a new "
                                    f"--out")
        previous = listed
    parent = _nearest_existing(p.parent if not p.exists() else p)
    if not parent.is_dir():
        raise OutputExistsError(f"cannot create {path}: {parent} is not a folder; choose "
                                f"another --out")
    if not os.access(parent, os.W_OK | os.X_OK) or (
            p.exists() and not os.access(p.parent, os.W_OK | os.X_OK)):
        where = parent if not p.exists() else p.parent
        raise OutputExistsError(f"cannot write {path}: no write permission in {where}; "
                                f"choose another --out")
    return previous


def stage_output_dir(path: str | os.PathLike) -> Path:
    """Create the hidden temporary folder, beside ``path``, that a report is written into.

    Parameters
    ----------
    path : str or path-like
        The final output folder (its parents are created if missing).

    Returns
    -------
    pathlib.Path
        The temporary folder; pass it to :func:`commit_output_dir` or
        :func:`discard_output_dir`.
    """
    p = output_target(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(dir=p.parent, prefix=f".{p.name}{_STAGE}"))
    _normal_mode(stage, folder=True)
    return stage


def discard_output_dir(stage: str | os.PathLike | None) -> None:
    """Remove a temporary folder made by :func:`stage_output_dir` (if it still exists).

    Parameters
    ----------
    stage : str, path-like or None
        The temporary folder; None does nothing.
    """
    if stage is not None and _STAGE in Path(stage).name:
        shutil.rmtree(stage, ignore_errors=True)


@contextlib.contextmanager
def deferred_interrupt():
    """Hold back Ctrl-C (SIGINT) inside the block and raise it at its end.

    A no-op outside the main thread (signal handlers can only be set there).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    hits = []
    try:
        previous = signal.signal(signal.SIGINT, lambda signum, frame: hits.append(signum))
    except ValueError:  # pragma: no cover - e.g. an embedded interpreter
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if hits:
            raise KeyboardInterrupt


def commit_output_dir(stage: str | os.PathLike, path: str | os.PathLike, *, kind: str,
                      names, force: bool = False, inputs=()) -> Path:
    """Put a staged report in place of ``path`` in one step.

    The marker (kind and the files written) is added to ``stage``; files of
    the old folder that greybox did not write (a user's notes, allowed with
    ``force``) are moved into the new one; then the old folder is renamed
    away, the new one renamed into place and the old one removed. Ctrl-C is
    held back during these renames.

    Parameters
    ----------
    stage : str or path-like
        Folder from :func:`stage_output_dir`, holding the new files.
    path : str or path-like
        Final output folder.
    kind : str
        Kind of output ("report", "demo").
    names : iterable of str
        The files greybox wrote (listed in the marker).
    force : bool
        As for :func:`check_output_dir`.
    inputs : sequence of str or path-like
        As for :func:`check_output_dir`.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    stage, p = Path(stage), output_target(path)
    atomic_write_text(stage / _MARKER, "\n".join([kind, *sorted(Path(n).name for n in names)])
                      + "\n")
    with deferred_interrupt():
        previous = check_output_dir(p, force=force, kind=kind, inputs=inputs)
        if not p.exists():
            os.rename(stage, p)
            return Path(path)
        ours = {Path(n).name for n in previous} | {_MARKER}
        theirs = [f for f in p.iterdir() if f.name not in ours]
        clash = [f.name for f in theirs if (stage / f.name).exists()]
        if clash:
            raise OutputExistsError(f"{path} holds a file greybox did not write, {clash[0]}, "
                                    f"with the name of a new output file; move it away or "
                                    f"choose another --out")
        moved, old = [], None
        try:
            for f in theirs:
                os.rename(f, stage / f.name)
                moved.append(f.name)
            old = Path(tempfile.mkdtemp(dir=p.parent, prefix=f".{p.name}{_OLD}"))
            os.rename(p, old / "previous")
            os.rename(stage, p)
        except OSError:
            if old is not None and (old / "previous").exists() and not p.exists():
                os.rename(old / "previous", p)  # the old report back in place
            for name in moved:  # and the user's files back into it
                if (stage / name).exists() and p.exists():
                    os.rename(stage / name, p / name)
            raise
        finally:
            if old is not None and p.exists():  # never delete the only copy
                shutil.rmtree(old, ignore_errors=True)
    return Path(path)


def record_outputs(path: str | os.PathLike, kind: str, names) -> None:
    """List the files written into a greybox output folder in its marker.

    Parameters
    ----------
    path : str or path-like
        The output folder.
    kind : str
        Kind of output ("report", "demo").
    names : iterable of str
        The files written.
    """
    p = Path(path)
    atomic_write_text(p / _MARKER, "\n".join([kind, *sorted(Path(n).name for n in names)])
                      + "\n")


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write a UTF-8 text file atomically (temporary file, then rename), umask permissions.

    Parameters
    ----------
    path : str or path-like
        Target file.
    text : str
        Its content.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        _normal_mode(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _finite_or_reason(v):
    """(JSON value, reason or None) of one number."""
    if isinstance(v, (bool, np.bool_)):
        return bool(v), None
    if isinstance(v, (int, np.integer)):
        return int(v), None
    f = float(v)
    if math.isfinite(f):
        return f, None
    return None, ("not a number (nan)" if math.isnan(f) else
                  f"{'+' if f > 0 else '-'}infinite (diverged or undefined)")


def json_safe(obj):
    """A copy of ``obj`` that strict JSON parsers accept.

    numpy arrays and scalars become lists and numbers; tuples lists; every
    non-finite number ``null``. A dict entry ``key`` that is (or holds) a
    non-finite number gets a companion ``key + "_reason"`` saying why, unless
    the dict already has one.

    Parameters
    ----------
    obj : dict, list, tuple, ndarray, number, str, bool or None
        The record to convert.

    Returns
    -------
    dict, list, number, str, bool or None
    """
    out, _ = _safe(obj)
    return out


def _safe(obj):
    if isinstance(obj, dict):
        out = {}
        reasons = {}
        for k, v in obj.items():
            out[str(k)], r = _safe(v)
            if r is not None:
                reasons[f"{k}_reason"] = r
        for k, r in reasons.items():
            if k not in out or out[k] in (None, ""):
                out[k] = r
        return out, None
    if isinstance(obj, np.ndarray):
        obj = obj.tolist()
    if isinstance(obj, (list, tuple)):
        items = [_safe(v) for v in obj]
        bad = [r for _, r in items if r is not None]
        reason = None
        if bad:
            reason = f"{len(bad)} non-finite value(s) written as null: {bad[0]}"
        return [v for v, _ in items], reason
    if isinstance(obj, (float, int, np.floating, np.integer, np.bool_, bool)):
        return _finite_or_reason(obj)
    if obj is None or isinstance(obj, str):
        return obj, None
    if isinstance(obj, os.PathLike):
        return str(obj), None
    return str(obj), None


def dumps_json(obj, *, indent: int | None = 2) -> str:
    """Strict JSON text of ``obj`` (see :func:`json_safe`; never NaN or Infinity).

    Parameters
    ----------
    obj : dict, list, number, str, bool or None
        The record.
    indent : int or None
        Indentation, as for :func:`json.dumps`.

    Returns
    -------
    str
    """
    return json.dumps(json_safe(obj), indent=indent, allow_nan=False)


def atomic_write_json(path: str | os.PathLike, obj) -> None:
    """Write strict JSON atomically (see :func:`dumps_json`).

    Parameters
    ----------
    path : str or path-like
        Target file.
    obj : dict or list
        The record.
    """
    atomic_write_text(path, dumps_json(obj) + "\n")


def save_figure(fig, path: str | os.PathLike, *, dpi: int = 120) -> None:
    """Save a matplotlib figure atomically as PNG, with umask permissions.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.
    path : str or path-like
        Target file.
    dpi : int
        Resolution.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".png")
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=dpi, format="png")
        _normal_mode(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
