"""File input and output: safe output folders and atomic writes.

Nothing here computes; it only reads and writes records.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

from .exceptions import GreyboxError

__all__ = ["OutputExistsError", "prepare_output_dir", "atomic_write_text", "save_figure"]

_MARKER = ".greybox-output"


class OutputExistsError(GreyboxError, FileExistsError):
    """An output would overwrite files that greybox did not write."""


def prepare_output_dir(path: str | os.PathLike, *, force: bool = False,
                       kind: str = "report") -> Path:
    """Create (or reuse) an output folder without clobbering a user's files.

    A folder that greybox created carries a marker file and may be reused. An
    existing non-empty folder without the marker is refused unless ``force``.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutputExistsError(f"{p} exists and is not a folder; choose another --out")
    if p.exists() and any(p.iterdir()):
        marker = p / _MARKER
        own = marker.exists() and marker.read_text().strip() == kind
        if not own and not force:
            raise OutputExistsError(
                f"{p} already exists and holds files greybox did not write as a {kind}; "
                f"choose another --out or pass --force to overwrite"
            )
        if own and kind == "report" and not force:
            raise OutputExistsError(
                f"{p} already holds a greybox report; pass --force to overwrite it"
            )
    p.mkdir(parents=True, exist_ok=True)
    (p / _MARKER).write_text(kind + "\n")
    return p


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
