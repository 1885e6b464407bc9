"""File input and output: safe output folders and atomic writes.

Nothing here computes; it only reads and writes records.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

from .exceptions import OutputExistsError

__all__ = ["OutputExistsError", "prepare_output_dir", "check_output_dir", "record_outputs", "atomic_write_text",
           "atomic_write_json", "save_figure"]

_MARKER = ".greybox-output"


def prepare_output_dir(path: str | os.PathLike, *, force: bool = False,
                       kind: str = "report") -> Path:
    """Create (or reuse) an output folder without clobbering a user's files.

    A folder that greybox created carries a marker file (its first line the
    kind of output, then the files it wrote) and may be reused: the files of
    the previous run are removed so that no stale figure survives. An
    existing non-empty folder without the marker is refused unless ``force``;
    a previous report is replaced only with ``force``. Call this after all
    computing is done, so that a failure leaves nothing behind.
    """
    p = Path(path)
    previous = check_output_dir(p, force=force, kind=kind)
    p.mkdir(parents=True, exist_ok=True)
    for name in previous:  # only files greybox itself listed, inside this folder
        f = p / Path(name).name
        if f.is_file():
            f.unlink()
    (p / _MARKER).write_text(kind + "\n")
    return p


def check_output_dir(path: str | os.PathLike, *, force: bool = False,
                     kind: str = "report") -> list[str]:
    """Raise :class:`OutputExistsError` if :func:`prepare_output_dir` would refuse.

    Creates nothing: call it before a long computation to fail fast. Returns
    the files a previous greybox run listed in the folder's marker.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutputExistsError(f"{p} exists and is not a folder; choose another --out")
    marker = p / _MARKER
    previous: list[str] = []
    if p.exists() and any(p.iterdir()):
        lines = marker.read_text().splitlines() if marker.exists() else []
        own = bool(lines) and lines[0].strip() == kind
        if not own and not force:
            raise OutputExistsError(
                f"{p} already exists and holds files greybox did not write as a {kind}; "
                f"choose another --out or pass --force to overwrite"
            )
        if own and kind == "report" and not force:
            raise OutputExistsError(
                f"{p} already holds a greybox report; pass --force to overwrite it"
            )
        previous = [ln.strip() for ln in lines[1:] if ln.strip()] if own else []
    return previous


def record_outputs(path: str | os.PathLike, kind: str, names) -> None:
    """List the files written into a greybox output folder in its marker."""
    p = Path(path)
    atomic_write_text(p / _MARKER, "\n".join([kind, *sorted(Path(n).name for n in names)])
                      + "\n")


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write a text file atomically (temporary file, then rename)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_json(path: str | os.PathLike, obj) -> None:
    """Write JSON atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2) + "\n")


def save_figure(fig, path: str | os.PathLike, *, dpi: int = 120) -> None:
    """Save a matplotlib figure atomically as PNG."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".png")
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=dpi, format="png")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
