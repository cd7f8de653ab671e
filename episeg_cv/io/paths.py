"""Paths the library writes to: clear one-line errors before anything is written."""

from __future__ import annotations

import contextlib
import json
import os
import threading
from pathlib import Path

__all__ = ["output_file", "output_folder", "input_file", "written_atomically", "read_json"]


def _first_file_on_the_way(folder: Path) -> Path | None:
    for p in [folder, *folder.parents]:
        if p.exists():
            return None if p.is_dir() else p
    return None


def output_file(path, what: str) -> Path:
    """``path`` as a :class:`~pathlib.Path` for a file to write, its folder created.

    Raises ``OSError`` naming ``what`` when ``path`` is a folder, when a file stands
    where a folder of the path should be, or when the folder cannot be created or
    written to.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{what} {str(path)!r} is a folder, expected a file path")
    parent = path.parent
    blocker = _first_file_on_the_way(parent)
    if blocker is not None:
        raise NotADirectoryError(f"{what} {str(path)!r}: {str(blocker)!r} is a file, so it cannot be a folder")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"{what} {str(path)!r}: cannot create the folder {str(parent)!r} ({exc.strerror})") from None
    if not os.access(parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise PermissionError(f"{what} {str(path)!r} is not writable")
    return path


def output_folder(path, what: str) -> Path:
    """``path`` as a folder to write into, created; ``OSError`` naming ``what`` when a file is in the way."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"{what} {str(path)!r} is a file, expected a folder")
    blocker = _first_file_on_the_way(path)
    if blocker is not None:
        raise NotADirectoryError(f"{what} {str(path)!r}: {str(blocker)!r} is a file, so it cannot be a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"{what} {str(path)!r}: cannot create the folder ({exc.strerror})") from None
    if not os.access(path, os.W_OK):
        raise PermissionError(f"{what} {str(path)!r} is not writable")
    return path


def input_file(path, what: str) -> Path:
    """``path`` of an existing regular file; ``FileNotFoundError`` or ``IsADirectoryError`` naming ``what``."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{what} {str(path)!r} is a folder, expected a file")
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    return path


@contextlib.contextmanager
def written_atomically(path: Path):
    """Yield a temporary path beside ``path`` (same suffix) to write; on success it replaces ``path``
    at once, on any error or interrupt it is removed. A reader never sees a half-written file."""
    if path.is_symlink():  # replace the file the link names, not the link
        path = path.resolve()
    if path.exists() and not path.is_file():  # a device, a pipe: written in place (nothing to replace)
        yield path
        return
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.{threading.get_ident()}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def read_json(path, what: str, max_bytes: int | None = None):
    """The JSON value of the file ``path`` (a UTF-8 BOM is accepted); a one-line ``ValueError`` naming
    ``what`` and the file for a folder, a non-text file, invalid JSON (with its line and column), JSON
    nested too deeply, or a file larger than ``max_bytes``."""
    path = input_file(path, what)
    size = path.stat().st_size
    if max_bytes is not None and size > max_bytes:
        raise ValueError(f"{what} {str(path)!r}: {size} bytes is too large (at most {max_bytes})")
    try:
        return json.loads(path.read_text(encoding="utf-8-sig"))
    except UnicodeDecodeError as e:
        raise ValueError(f"{what} {str(path)!r} is not a text file ({e.reason})") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{what} {str(path)!r}: invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    except RecursionError:
        raise ValueError(f"{what} {str(path)!r}: JSON nested too deeply") from None
