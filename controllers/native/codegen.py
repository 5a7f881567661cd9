"""Generated C for casadi Functions: compile once, cache on disk, verify, call through ctypes.

:func:`compile_function` writes a casadi Function as C (``casadi.CodeGenerator``), compiles it
with the machine's compiler (``$CC`` or ``cc``) into a shared library cached on disk, and loads
it as a :class:`CompiledFunction`: preallocated float64 buffers and one ctypes call per
evaluation. Compilation takes a few seconds and happens once per function and machine.

**Nothing falls back silently.** Every build returns a :class:`NativeBuild` record (compiled or
not, the compiler, the library and its digest, and when it fell back, why, with the compiler's
message); the controllers report them in ``describe()["native"]`` and the benchmark report
shows them. ``PIEZO_NATIVE`` sets the policy: ``auto`` (the default: compile, and fall back to
casadi's virtual machine or numpy, recorded, when compilation is impossible), ``off`` (never
compile) or ``require`` (raise :class:`NativeCodeError` instead of falling back).

**Results are bitwise reproducible** for a given native path, compiler, flags and
architecture: the generated C and numpy evaluate the same mathematics in a different order,
so a run that compiled and one that fell back differ by rounding (the MPC's voltages by up to
about 1e-5 V). The cache key holds the generated source, the flags, the compiler's identity,
the architecture and the casadi version, so a library is never reused across them.

**What is loaded is verified.** The cache (``$PIEZO_CACHE`` or ``~/.cache/piezo-testbed``)
must be a folder owned by the current user, not a symlink, and writable by no one else (it is
created with mode 0700; a folder that fails these checks is refused and the build falls back,
recorded). Each library is written under a temporary name and renamed into place (concurrent
builders never see half a file), with its SHA-256 in a file beside it; the digest is checked
before every load and a library that does not match is rebuilt, never loaded. The digest
catches corruption and stale or foreign files; the folder's permissions are what keep other
users out (anyone who can write your cache can replace both files, as with any cache of
executable code). Temporary folders left by crashed builds and libraries unused for
:data:`STALE_DAYS` days are removed when the cache is opened.
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import hashlib
import os
import platform
import shutil
import stat
import subprocess
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "CompiledFunction",
    "NativeBuild",
    "NativeCodeError",
    "as_numpy",
    "cache_dir",
    "compile_function",
    "native_policy",
]

DEFAULT_FLAGS = ("-O1", "-shared", "-fPIC")
"""Compiler flags of :func:`compile_function` unless the caller passes others."""


class CompiledFunction:
    """A casadi Function generated as C, compiled, and called through ctypes on numpy buffers.

    Inputs are copied into float64 buffers, outputs are written by the C code into dense
    float64 buffers (casadi's column-major order) that are returned without copies; the next
    call overwrites them. Callers on a hot path may write :attr:`inputs` themselves and call
    :meth:`run` (inputs that never change need writing once).

    Parameters
    ----------
    library : pathlib.Path
        Shared library holding the generated function.
    function : casadi.Function
        The function it was generated from (for names and dense output shapes).
    """

    def __init__(self, library: Path, function: Any) -> None:
        self.library = library
        lib = ctypes.CDLL(str(library))
        name = function.name()
        sizes = [ctypes.c_longlong() for _ in range(4)]
        getattr(lib, f"{name}_work")(*[ctypes.byref(s) for s in sizes])
        n_arg, n_res, n_iw, n_w = (max(s.value, 1) for s in sizes)
        self._iw = np.zeros(n_iw, dtype=np.int64)
        self._w = np.zeros(n_w)
        self.inputs = [np.zeros(function.numel_in(i)) for i in range(function.n_in())]
        # Column-major (rows, cols) is row-major (cols, rows).
        self.outputs = [
            np.zeros((function.size2_out(i), function.size1_out(i)))
            for i in range(function.n_out())
        ]
        pointer = ctypes.c_void_p
        self._arg = (pointer * n_arg)(*[b.ctypes.data for b in self.inputs])
        self._res = (pointer * n_res)(*[b.ctypes.data for b in self.outputs])
        self._fn = getattr(lib, name)
        self._fn.restype = ctypes.c_int
        self._fn.argtypes = [pointer] * 4 + [ctypes.c_int]
        self._lib = lib
        self._call_args = (
            ctypes.addressof(self._arg),
            ctypes.addressof(self._res),
            self._iw.ctypes.data,
            self._w.ctypes.data,
            0,
        )

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        """Evaluate; outputs as (cols, rows) arrays (the transpose of casadi's shapes)."""
        for buffer, value in zip(self.inputs, args, strict=True):
            buffer[:] = value
        self.run()
        return self.outputs

    def run(self) -> None:
        """Evaluate on the current :attr:`inputs`, writing :attr:`outputs`."""
        if self._fn(*self._call_args) != 0:
            raise RuntimeError(f"generated function in {self.library} returned an error")


class NativeCodeError(RuntimeError):
    """Compilation was required (``PIEZO_NATIVE=require``) and failed."""


@dataclass(frozen=True)
class NativeBuild:
    """What one native build did: the record a report shows.

    Attributes
    ----------
    function : str
        Name of the casadi Function.
    compiled : bool
        True: generated C is used; False: the caller's fallback (casadi VM or numpy) is.
    reason : str
        The library used, or why there is none.
    compiler : str
        The compiler's identity (its ``--version`` first line), or "" when none was found.
    library : str
        Path of the loaded library ("" when not compiled).
    sha256 : str
        Digest of the loaded library ("" when not compiled).
    compiler_output : str
        The compiler's stderr when it failed (trimmed), else "".
    """

    function: str
    compiled: bool
    reason: str
    compiler: str = ""
    library: str = ""
    sha256: str = ""
    compiler_output: str = ""

    def __str__(self) -> str:
        return self.reason

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe fields."""
        return dataclasses.asdict(self)


NATIVE_POLICIES = ("auto", "off", "require")
STALE_DAYS = 30
"""Libraries not used for this many days are removed from the cache."""


def native_policy() -> str:
    """``PIEZO_NATIVE`` (``auto``, ``off`` or ``require``; ValueError for anything else)."""
    policy = os.environ.get("PIEZO_NATIVE", "auto").strip().lower() or "auto"
    if policy not in NATIVE_POLICIES:
        raise ValueError(
            f"PIEZO_NATIVE must be one of {', '.join(NATIVE_POLICIES)}, got {policy!r}"
        )
    return policy


def cache_dir(name: str = "nmpc") -> Path:
    """Folder of the compiled libraries of one user (``$PIEZO_CACHE`` or the home cache)."""
    root = os.environ.get("PIEZO_CACHE") or Path.home() / ".cache" / "piezo-testbed"
    return Path(root) / name


def _private_folder(folder: Path) -> Path:
    """Create ``folder`` (mode 0700) and check that it is this user's own, or raise OSError."""
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    for path in (folder, folder.parent):
        info = path.lstat()
        if stat.S_ISLNK(info.st_mode) or not stat.S_ISDIR(info.st_mode):
            raise OSError(f"{path} is not a plain folder")
        if info.st_uid != os.getuid():
            raise OSError(f"{path} belongs to another user")
        if info.st_mode & 0o022:
            raise OSError(f"{path} is writable by other users (chmod go-w it, or set PIEZO_CACHE)")
    return folder


def _remove_stale(folder: Path, keep: Path) -> None:
    """Drop temporary folders of crashed builds and libraries unused for STALE_DAYS days."""
    now = time.time()
    for path in folder.iterdir():
        try:
            age = now - path.lstat().st_atime
            if path.is_dir() and path.name.startswith("tmp") and age > 3600:
                shutil.rmtree(path, ignore_errors=True)
            elif path.suffix in (".so", ".sha256") and path.stem != keep.stem:
                if age > STALE_DAYS * 86400:
                    path.unlink(missing_ok=True)
        except OSError:
            continue


@functools.lru_cache(maxsize=4)
def compiler_identity(compiler: str) -> str:
    """First line of ``compiler --version`` (part of the cache key and of the record)."""
    try:
        done = subprocess.run(
            [compiler, "--version"], capture_output=True, text=True, timeout=30, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return compiler
    lines = (done.stdout or done.stderr).strip().splitlines()
    return f"{compiler}: {lines[0]}" if lines else compiler


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _verified(library: Path) -> str | None:
    """The library's digest when it matches the one recorded beside it, else None."""
    recorded = library.with_suffix(".sha256")
    try:
        expected = recorded.read_text(encoding="ascii").strip()
        actual = _digest(library)
    except OSError:
        return None
    return actual if actual == expected else None


def _build(compiler: str, flags: Sequence[str], source: Path, library: Path, tmp: Path) -> str:
    """Compile ``source`` into ``library`` (atomically, digest beside it); the digest."""
    staged = tmp / library.name
    subprocess.run(
        [compiler, *flags, "-o", str(staged), str(source), "-lm"],
        check=True,
        capture_output=True,
        text=True,
        timeout=300,
    )
    digest = _digest(staged)
    digest_file = tmp / (library.stem + ".sha256")
    digest_file.write_text(digest + "\n", encoding="ascii")
    os.replace(staged, library)  # atomic: concurrent builders never see half a file
    os.replace(digest_file, library.with_suffix(".sha256"))
    return digest


def _fallback(name: str, reason: str, compiler: str = "", output: str = "") -> NativeBuild:
    if native_policy() == "require":
        detail = f": {output.strip()[-500:]}" if output.strip() else ""
        raise NativeCodeError(f"{name}: {reason} (PIEZO_NATIVE=require){detail}")
    return NativeBuild(name, False, reason, compiler, compiler_output=output[-2000:])


def compile_function(
    function: Any, *, flags: Sequence[str] = DEFAULT_FLAGS, cache: str = "nmpc"
) -> tuple[CompiledFunction | None, NativeBuild]:
    """Generate C for a casadi Function, compile it (cached, verified) and load it.

    Parameters
    ----------
    function : casadi.Function
        Function to generate (its name names the C symbol and the library file).
    flags : sequence of str
        Compiler flags; they are part of the cache key.
    cache : str
        Sub-folder of the cache (see :func:`cache_dir`).

    Returns
    -------
    compiled : CompiledFunction or None
        None when there is no native code (the caller then falls back).
    build : NativeBuild
        What happened, for reports (``str(build)`` is a one-line note).

    Raises
    ------
    NativeCodeError
        Under ``PIEZO_NATIVE=require``, instead of returning None.
    """
    import casadi

    name = function.name()
    if native_policy() == "off":
        return None, _fallback(name, "native code switched off (PIEZO_NATIVE=off)")
    compiler = shutil.which(os.environ.get("CC", "cc"))
    if compiler is None:
        return None, _fallback(name, "no C compiler found (set CC)")
    identity = compiler_identity(compiler)
    try:
        folder = _private_folder(cache_dir(cache))
        with tempfile.TemporaryDirectory(dir=folder) as tmp:
            generator = casadi.CodeGenerator(f"{name}.c", {"with_header": False})
            generator.add(function)
            generator.generate(f"{tmp}/")
            source = Path(tmp) / f"{name}.c"
            key = hashlib.sha256(source.read_bytes())
            for part in (*flags, identity, platform.machine(), casadi.__version__):
                key.update(b"\0" + part.encode())
            library = folder / f"{name}_{key.hexdigest()[:16]}.so"
            digest = _verified(library) if library.exists() else None
            if digest is None:  # missing, corrupt or foreign: build it afresh
                digest = _build(compiler, flags, source, library, Path(tmp))
            _remove_stale(folder, keep=library)
        loaded = CompiledFunction(library, function)
    except subprocess.CalledProcessError as exc:
        return None, _fallback(name, "compilation failed", identity, exc.stderr or "")
    except (OSError, subprocess.SubprocessError, RuntimeError, AttributeError) as exc:
        return None, _fallback(name, f"compilation failed ({type(exc).__name__}: {exc})", identity)
    build = NativeBuild(name, True, f"generated C, {library.name}", identity, str(library), digest)
    return loaded, build


def as_numpy(outputs: Any) -> list[np.ndarray]:
    """casadi VM outputs as (cols, rows) numpy arrays, like :class:`CompiledFunction` gives."""
    return [np.asarray(o.full()).T for o in outputs]
