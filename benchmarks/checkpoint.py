"""The checkpoint of a benchmark run: each finished group kept as it ends, so a run resumes.

A benchmark is a list of groups (one controller on one plant over its references,
:meth:`benchmarks.runner.BenchmarkConfig.groups`), each a deterministic function of the run's
identity. :class:`Checkpoint` keeps them in ``OUT/checkpoint.jsonl`` (JSON lines):

- line 1, the header: ``{"schema", "version", "digest", "identity"}``, where ``identity``
  (:func:`run_identity`) holds everything that decides a group's result: the configuration
  (without ``jobs`` and ``backend``, which do not change results), the SHA-256 of the model's
  files and of each policy's and user controller's files, the package version and the SHA-256
  of every module of the packages that compute an episode, the numerical libraries' versions,
  and the native code's identity (``PIEZO_NATIVE``, compiler, flags, architecture, casadi and
  Python ABI: what :func:`controllers.native.codegen.cache_key` names a compiled library by);
  ``digest`` is the SHA-256 of the identity;
- then one line per finished group: ``{"digest", "group": [plant, controller], "output"}``
  (``[plant, controller, model index]`` when the run has several identification seeds).

Each group's line is written by a single ``write`` to the file opened for appending, then
``fsync``: a crash leaves at most one unterminated last line, which a resume drops. The header
is written to a temporary file renamed into place (``os.replace``). A resume refuses a
checkpoint whose digest differs from the run's, in one line saying what changed.

Outputs go through JSON both when written and when resumed (:meth:`Checkpoint.append` returns
the decoded line), and Python's JSON writes every float with the shortest repr that reads back
to the same bits, so a resumed run is bitwise the run it continues.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform
import shlex
import shutil
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "CHECKPOINT",
    "SCHEMA",
    "Checkpoint",
    "CheckpointMismatch",
    "plain_json",
    "run_identity",
    "write_text_atomic",
]

CHECKPOINT = "checkpoint.jsonl"
"""The checkpoint's file name in the output folder."""

SCHEMA = "piezo-testbed/benchmark-checkpoint"
"""The header's ``schema`` field."""

_VERSION = 1

CODE_PACKAGES = ("piezo_env", "identification", "controllers", "benchmarks", "piezo_parallel")
"""The packages whose modules compute a group: their sources are part of the identity (of
``benchmarks``, the harness's own modules, not its studies and speed scripts)."""

_SOURCES = (".py", ".c", ".h")

LIBRARIES = ("numpy", "scipy", "casadi", "osqp", "torch", "gymnasium", "control")
"""Numerical libraries whose versions are part of the identity."""

_WHAT = {
    "configuration": "the configuration",
    "model": "the model files",
    "policies": "the policy files",
    "controllers": "the files of your controllers",
    "package": "the package version",
    "code": "the code",
    "libraries": "the numerical libraries",
    "native": "the native-code identity",
}


class CheckpointMismatch(ValueError):
    """A checkpoint that belongs to another run (or is damaged): one line saying what differs."""


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and a rename.

    A reader (or a run interrupted while writing) sees the old file or the new one, never half
    of one.
    """
    path = Path(path)
    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(descriptor, "w", encoding="utf-8") as file:
            file.write(text)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _folder_digests(folder: str | os.PathLike[str]) -> dict[str, str]:
    """SHA-256 of every file under ``folder``, by relative path."""
    root = Path(folder)
    return {str(p.relative_to(root)): _sha256(p) for p in sorted(root.rglob("*")) if p.is_file()}


def _models_digests(model_dir: Any) -> Any:
    """One model folder's digests, a list of them for one folder per identification seed, or
    a mapping of either per plant (:func:`benchmarks.runner.model_folders`)."""
    if isinstance(model_dir, (str, os.PathLike)):
        return _folder_digests(model_dir)
    if isinstance(model_dir, Mapping):
        return {plant: _models_digests(folders) for plant, folders in model_dir.items()}
    return [_folder_digests(folder) for folder in model_dir]


def _code_digests() -> dict[str, str]:
    """SHA-256 of every source file (Python and C) of :data:`CODE_PACKAGES`, by path relative
    to the project."""
    import importlib.util

    digests = {}
    for package in CODE_PACKAGES:
        spec = importlib.util.find_spec(package)
        folder = Path(spec.origin).parent
        found = folder.glob("*") if package == "benchmarks" else folder.rglob("*")
        for path in sorted(p for p in found if p.suffix in _SOURCES and p.is_file()):
            digests[str(path.relative_to(folder.parent))] = _sha256(path)
    return digests


def _module_digest(spec: str) -> str:
    """SHA-256 of the source of a user's controller module (``module:attr``)."""
    import importlib.util

    found = importlib.util.find_spec(spec.rpartition("=")[2].partition(":")[0])
    if found is None or not found.origin or not os.path.isfile(found.origin):
        return "source not found"
    return _sha256(Path(found.origin))


def _package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("piezo-testbed")
    except PackageNotFoundError:
        return "not installed"


def _library_versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    versions = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def _native_identity() -> dict[str, str]:
    """What names a compiled library besides its source (see
    :func:`controllers.native.codegen.cache_key`), and the policy that decides whether one
    runs."""
    from controllers.native.codegen import DEFAULT_FLAGS, compiler_identity, native_policy

    command = shlex.split(os.environ.get("CC") or "cc")
    found = shutil.which(command[0]) if command else None
    compiler = compiler_identity((found, *command[1:])) if found else "no C compiler found"
    try:
        from importlib.metadata import version

        casadi = version("casadi")
    except Exception:  # casadi is a dependency; a broken install is named, not hidden
        casadi = "not installed"
    return {
        "policy": native_policy(),
        "compiler": compiler,
        "flags": " ".join(DEFAULT_FLAGS),
        "platform": f"{platform.machine()} {sys.platform}",
        "python_abi": sys.implementation.cache_tag or "",
        "casadi": casadi,
    }


def run_identity(config: Any, model_dir: Any) -> dict[str, Any]:
    """Everything that decides a group's result, as plain JSON data (see the module docstring).

    Parameters
    ----------
    config : benchmarks.runner.BenchmarkConfig
        The run's configuration.
    model_dir : str, path-like, sequence of them, or mapping
        The identified model's folder, one per identification seed, or either per plant.

    Returns
    -------
    dict
        ``configuration``, ``model``, ``policies``, ``controllers``, ``package``, ``code``,
        ``libraries`` and ``native``.
    """
    fields = dataclasses.asdict(config)
    for name in ("jobs", "backend", "policies"):
        fields.pop(name)
    identity = {
        "configuration": json.loads(json.dumps(fields, sort_keys=True)),
        "model": _models_digests(model_dir),
        "policies": {
            label: _folder_digests(folder) for label, folder in config.policy_folders.items()
        },
        "controllers": {label: _module_digest(spec) for label, spec in config.entry_points.items()},
        "package": _package_version(),
        "code": _code_digests(),
        "libraries": _library_versions(),
        "native": _native_identity(),
    }
    return identity


def _digest(identity: dict[str, Any]) -> str:
    text = json.dumps(identity, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _changes(old: dict[str, Any], new: dict[str, Any]) -> str:
    """What differs between two identities, for one line: ``the configuration (steps: 100 ->
    200)``, ``the code (controllers/mpc.py)``."""
    parts = []
    for part, what in _WHAT.items():
        a, b = old.get(part), new.get(part)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            keys = [k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
            if part in ("configuration", "libraries", "native", "controllers"):
                shown = [f"{k}: {_short(a.get(k))} -> {_short(b.get(k))}" for k in keys[:3]]
            else:
                shown = list(keys[:3])
            more = f" and {len(keys) - 3} more" if len(keys) > 3 else ""
            parts.append(f"{what} ({'; '.join(shown)}{more})")
        else:
            parts.append(f"{what} ({_short(a)} -> {_short(b)})")
    return ", ".join(parts) or "its digest"


def _short(value: Any) -> str:
    if value is None:
        return "missing"
    text = value if isinstance(value, str) else json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


class Checkpoint:
    """The finished groups of one run, in ``folder``/:data:`CHECKPOINT`.

    Open one with :meth:`start` (a new run) or :meth:`resume` (the same run, continued).

    Attributes
    ----------
    path : pathlib.Path
        The checkpoint file.
    digest : str
        SHA-256 of the run's identity.
    finished : dict
        ``(plant, controller)`` -> the group's output, as JSON decoded it.
    """

    def __init__(self, path: Path, digest: str, finished: dict[tuple[str, str], Any]) -> None:
        self.path = path
        self.digest = digest
        self.finished = finished

    @classmethod
    def start(cls, folder: str | os.PathLike[str], identity: dict[str, Any]) -> Checkpoint:
        """A new checkpoint (one that was there is replaced): the header, nothing finished."""
        path = Path(folder) / CHECKPOINT
        digest = _digest(identity)
        header = {"schema": SCHEMA, "version": _VERSION, "digest": digest, "identity": identity}
        write_text_atomic(path, json.dumps(header, sort_keys=True) + "\n")
        return cls(path, digest, {})

    @classmethod
    def resume(cls, folder: str | os.PathLike[str], identity: dict[str, Any]) -> Checkpoint:
        """The checkpoint in ``folder`` with its finished groups, for the same run.

        An unterminated last line (a write cut short) is dropped from the file. With no
        checkpoint in ``folder`` this is :meth:`start`.

        Raises
        ------
        CheckpointMismatch
            The checkpoint is of another run (the message names what changed), or damaged.
        """
        path = Path(folder) / CHECKPOINT
        if not path.exists():
            return cls.start(folder, identity)
        data = path.read_bytes()
        complete = data[: data.rfind(b"\n") + 1]
        lines = complete.decode("utf-8", errors="replace").splitlines()
        header = _parse(lines[0] if lines else "", path, 1)
        if header.get("schema") != SCHEMA or header.get("version") != _VERSION:
            raise CheckpointMismatch(
                f"{path} is not a checkpoint this version of piezo benchmark writes; run "
                "without --resume to start afresh, or choose another --out"
            )
        digest = _digest(identity)
        if header.get("digest") != digest:
            raise CheckpointMismatch(
                f"the checkpoint {path} is of another run: "
                f"{_changes(header.get('identity', {}), identity)} changed since; run without "
                "--resume to start afresh, or choose another --out"
            )
        finished = {}
        for number, line in enumerate(lines[1:], start=2):
            entry = _parse(line, path, number)
            if entry.get("digest") != digest:
                raise CheckpointMismatch(
                    f"line {number} of {path} is of another run; run without --resume to "
                    "start afresh, or choose another --out"
                )
            finished[tuple(entry["group"])] = entry["output"]
        if len(complete) < len(data):
            with path.open("r+b") as file:
                file.truncate(len(complete))
        return cls(path, digest, finished)

    def append(self, group: tuple[Any, ...], output: Any) -> Any:
        """Add a finished group (one ``write`` of one line, then ``fsync``).

        Returns
        -------
        object
            ``output`` as it reads back from the checkpoint: what a resumed run gets too.
        """
        record = {"digest": self.digest, "group": list(group), "output": output}
        line = (json.dumps(record, separators=(",", ":"), default=plain_json) + "\n").encode()
        descriptor = os.open(self.path, os.O_WRONLY | os.O_APPEND)
        try:
            written = os.write(descriptor, line)
            while written < len(line):  # a regular file writes it all or fails; to be sure
                written += os.write(descriptor, line[written:])
            os.fsync(descriptor)
        finally:
            os.close(descriptor)
        self.finished[tuple(group)] = decoded = json.loads(line)["output"]
        return decoded

    def kept(self) -> int:
        """Groups the file holds: what :attr:`finished` holds, and also a group whose line was
        written when an interruption stopped :meth:`append` before it returned."""
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            return 0
        return max(0, data.count(b"\n") - 1)

    def remove(self) -> None:
        """Delete the file (a run that finished nothing leaves nothing behind)."""
        self.path.unlink(missing_ok=True)


def _parse(line: str, path: Path, number: int) -> dict[str, Any]:
    try:
        value = json.loads(line)
    except ValueError:
        value = None
    if not isinstance(value, dict):
        raise CheckpointMismatch(
            f"line {number} of {path} is damaged; run without --resume to start afresh, or "
            "choose another --out"
        )
    return value


def plain_json(value: Any) -> Any:
    """A numpy value as the Python one it holds (a user's ``describe()`` may return
    ``numpy.float32(1.5)`` or an array); anything else that JSON has no type for is refused,
    naming the type."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(
        f"{type(value).__name__} {value!r} is not JSON: a controller's describe() returns "
        "numbers, strings, booleans, None, lists and dicts (numpy values are converted)"
    )
