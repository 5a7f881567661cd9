"""What a subcommand shows and writes: its output folder, created and proven writable before any
work starts, and the progress bar on a terminal."""

from __future__ import annotations

import errno
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from tempfile import mkstemp

from piezo_cli.command import CommandLineError

__all__ = [
    "INCOMPLETE",
    "clear_incomplete",
    "mark_incomplete",
    "missing_folders",
    "prepare_output_dir",
    "remove_if_empty",
    "terminal_progress",
]

INCOMPLETE = "INCOMPLETE.txt"
"""The file in an output folder that says the command writing it did not finish."""

_REASONS = {
    errno.EACCES: "permission denied",
    errno.EPERM: "permission denied",
    errno.EROFS: "read-only file system",
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
    errno.ENAMETOOLONG: "the name is too long",
    errno.ELOOP: "too many symbolic links",
}


def prepare_output_dir(path: str | os.PathLike[str], *, option: str = "--out") -> Path:
    """Create the output folder (and its parents) and prove it writable, before any work.

    A probe file is created in the folder and deleted again, so a folder that exists but cannot
    be written to is refused here rather than after minutes of computation.

    Parameters
    ----------
    path : str or path-like
        The folder the subcommand will write into; it may exist already.
    option : str
        The option that named the folder, quoted in the error message.

    Returns
    -------
    pathlib.Path
        The folder, ready to write into.

    Raises
    ------
    CommandLineError
        ``cannot write to <path>: <reason>; choose another --out`` when the folder cannot be
        created or written (a file in the way, permission denied, read-only file system, ...).
    """
    text = os.fspath(path)
    folder = Path(text)
    try:
        if not text.strip():
            raise _Refused("the path is empty")
        if folder.exists() and not folder.is_dir():
            raise _Refused("it is a file, not a folder")
        folder.mkdir(parents=True, exist_ok=True)
        descriptor, probe = mkstemp(prefix=".piezo-write-check-", dir=folder)
        os.close(descriptor)
        os.unlink(probe)
    except _Refused as refused:
        raise CommandLineError(_message(text, str(refused), option)) from None
    except OSError as error:
        raise CommandLineError(_message(text, _reason(folder, error), option)) from None
    return folder


def missing_folders(path: str | os.PathLike[str] | None) -> list[Path]:
    """The folders of ``path`` (itself and its parents) that do not exist yet, deepest first."""
    if path is None or not os.fspath(path).strip():
        return []
    folder = Path(os.fspath(path)).absolute()
    return [p for p in (folder, *folder.parents) if not p.exists()]


def remove_if_empty(folders: list[Path]) -> None:
    """Remove the folders a failed command created (deepest first) while they are empty.

    A command refused after it created its output folder leaves nothing behind; a folder that
    holds anything (a model identified before the failure) stays.
    """
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


def mark_incomplete(
    path: str | os.PathLike[str] | None,
    command: str,
    what: str,
    *,
    hint: str = "",
    replace: bool = True,
) -> None:
    """Say in ``path``/:data:`INCOMPLETE` that ``command`` did not finish what it writes there.

    Written only into a folder that exists and holds something (a folder left empty is
    removed instead), so that no partial output looks like a finished one. A folder that cannot
    be written to any more is left as it is: the command's own error says why.

    Parameters
    ----------
    path : str or path-like or None
        The output folder (None: nothing to mark).
    command : str
        ``"piezo benchmark"``: :func:`clear_incomplete` of the same command removes the file.
    what : str
        What happened, ``"was interrupted by SIGTERM"``.
    hint : str
        How to go on, ``"run the same command with --resume to finish it"``.
    replace : bool
        Whether to replace a mark that is there (False keeps a subcommand's own, more
        precise one).
    """
    from benchmarks.checkpoint import write_text_atomic

    if path is None or not os.fspath(path).strip():
        return
    folder = Path(os.fspath(path))
    try:
        if not folder.is_dir() or not any(folder.iterdir()):
            return
        if not replace and (folder / INCOMPLETE).exists():
            return
        stamp = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
        text = f"{command} {what} ({stamp}): the files in this folder are not its result."
        write_text_atomic(folder / INCOMPLETE, text + (f"\n{hint}" if hint else "") + "\n")
    except OSError:
        return


def clear_incomplete(path: str | os.PathLike[str] | None, command: str) -> None:
    """Remove ``path``/:data:`INCOMPLETE` if ``command`` wrote it (it has now finished)."""
    if path is None or not os.fspath(path).strip():
        return
    marker = Path(os.fspath(path)) / INCOMPLETE
    try:
        if marker.read_text(encoding="utf-8").startswith(f"{command} "):
            marker.unlink()
    except OSError:
        return


class _Refused(Exception):
    pass


def _message(path: str, reason: str, option: str) -> str:
    return f"cannot write to {path or repr(path)}: {reason}; choose another {option}"


def _reason(folder: Path, error: OSError) -> str:
    if isinstance(error, (NotADirectoryError, FileExistsError)):
        blocking = _file_in_the_way(folder)
        if blocking is not None:
            return f"{blocking} is a file, not a folder"
    if error.errno in _REASONS:
        return _REASONS[error.errno]
    return (error.strerror or str(error)).lower()


def _file_in_the_way(folder: Path) -> Path | None:
    """The first existing ancestor of ``folder`` (or itself) that is not a folder."""
    for part in reversed((folder, *folder.parents)):
        if part.exists() and not part.is_dir():
            return part
    return None


def terminal_progress(quiet: bool) -> Callable[[int, int, str], None] | None:
    """A one-line progress bar on a terminal; None under CI, with ``quiet`` or when piped."""
    if quiet or os.environ.get("CI") or not sys.stderr.isatty():
        return None

    def show(done: int, total: int, label: str) -> None:
        width = 30
        filled = round(width * done / total)
        bar = "#" * filled + "." * (width - filled)
        sys.stderr.write(f"\r[{bar}] {done}/{total} {label[:40]:<40}")
        if done == total:
            sys.stderr.write("\n")
        sys.stderr.flush()

    return show
