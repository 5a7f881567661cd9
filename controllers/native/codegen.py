"""Generated C for casadi Functions (and hand-written C kernels): compile once, cache on disk,
verify, call through ctypes.

:func:`compile_function` writes a casadi Function as C (``casadi.CodeGenerator``), compiles it
with the machine's compiler (``$CC`` or ``cc``) into a shared library cached on disk, and loads
it as a :class:`CompiledFunction`: preallocated float64 buffers and one ctypes call per
evaluation. Compilation happens once per function and machine (the cache below).

**Nothing falls back silently.** Every build returns a :class:`NativeBuild` record: what was
built, which path evaluates it (``compiled``, or the caller's fallback, ``numpy`` or
``casadi-vm``), why, the compiler's identity and stderr, the cache key, the library loaded and
its SHA-256. The objects that use native code keep theirs in a ``native`` list
(:class:`controllers.native.compiled_inverse.CompiledInverse`, the NMPC horizons; a horizon
whose build is deferred to its first use keeps none until then and says so), and
:meth:`controllers.base.Controller.native_code` collects them into ``describe()["native"]``,
which the benchmark report shows. The environment variable ``PIEZO_NATIVE`` sets the policy:

- ``auto`` (the default): compile, and fall back (recorded) when compilation is impossible:
  no compiler, a compiler error, an unusable cache folder (e.g. ``PIEZO_CACHE=/dev/null/x``);
- ``off``: never compile (numpy or casadi's virtual machine, recorded as switched off);
- ``require``: raise :class:`NativeCodeError`, with the compiler's message, instead of
  falling back.

**When results are bitwise equal.** Runs are bitwise equal, for any number of jobs and any
backend, when every process takes the same native path (all ``compiled`` or all fallen back)
with the same compiler, flags and architecture; the benchmark report says which path each
function took. The paths differ: the compiled NLS inverse is a Newton iteration that agrees
with the numpy inverse to about 1e-7 V, not to the bit, and the closed loop carries that on:
the MPC's and ``pid-ff``'s voltages differ from those with ``PIEZO_NATIVE=off`` by small
amounts, the NMPC's not at all (its horizon's feature recursion in C and in casadi's virtual
machine round alike without fused multiply-adds, see :data:`DEFAULT_FLAGS`). One such
comparison on the shipped model is recorded in ``benchmarks/results/design_measurements.md``.
An unusable cache (``PIEZO_CACHE=/dev/null/x``) gives exactly the ``off`` results. The
cache key (:func:`cache_key`) holds the generated source, the flags, the compiler's resolved
path and ``--version``, the architecture and OS, the casadi version and the Python ABI, so a
library is never reused across any of them.

**What is loaded is verified.** The cache (a sub-folder of ``$PIEZO_CACHE`` or
``~/.cache/piezo-testbed`` per kind of function) must be a plain folder owned by the current
user and writable by no one else (it is created with mode 0700 and tightened to it; its parent
must be this user's or root's and not writable by others unless sticky). A folder that fails
these checks is refused and the build falls back, recorded. Builds and loads take the folder's
lock (``flock``), so concurrent cold builders compile once and the others load that library. A
library is compiled under a temporary name, its SHA-256 is written beside it, and both are
renamed into place (atomic: no reader sees half a file, and a crash leaves a mismatch, never a
library trusted under an old digest). Before every load the library must be this user's regular
file matching its recorded digest; one that does not is rebuilt, never loaded.

What the digest protects against: truncated or corrupted files (a crashed or interrupted
write, disk errors, a copy from elsewhere under the same name), libraries left by older
builds or versions. What it does not: someone who can
write your cache folder can replace the library and its digest together (that is why the
folder must be private), and someone with your user's rights can run code anyway. Staging
folders left by crashed builds (after an hour), libraries without a digest, and libraries of
other keys unused for :data:`STALE_DAYS` days are removed when a build takes the lock.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import functools
import hashlib
import io
import os
import platform
import shlex
import shutil
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from piezo_env.memo import ContentCache

__all__ = [
    "CASADI_VM",
    "COMPILED",
    "NUMPY",
    "SOURCES_KEPT",
    "CallBuffers",
    "CompiledFunction",
    "NativeBuild",
    "NativeCodeError",
    "as_numpy",
    "cache_dir",
    "cache_key",
    "call_buffers",
    "compile_function",
    "compile_source",
    "generated_c",
    "generated_text",
    "native_policy",
]

DEFAULT_FLAGS = ("-O1", "-shared", "-fPIC", "-ffp-contract=off")
"""Compiler flags of :func:`compile_function` unless the caller passes others. No fused
multiply-adds: where the compiler would fuse them by default (e.g. aarch64), the generated C
would round differently from casadi's virtual machine."""


SOURCES_KEPT = 48
"""Generated C files kept by content (:func:`generated_c`). A benchmark worker meets up to six
identified models, each with four functions of its own (the NLS inverse, its reachable range,
the MPC's fused step and the NMPC's partials: 24), the oracles' inverse, reachable range and
fused step of each hysteresis model (the strength is an input: three for each of the two with
a generated inverse) and the unrolled horizons of a group's drawn oracles (10 at most): 40."""

_sources = ContentCache(SOURCES_KEPT)


def generated_c(file_name: str, functions: Sequence[Any]) -> bytes:
    """The C file ``casadi.CodeGenerator`` writes for ``functions`` (without a header), as
    bytes.

    Generating C is most of a native build whose library is already cached on disk; a
    benchmark builds the same functions for every plant. So the file is kept by content
    (:data:`SOURCES_KEPT`, :mod:`piezo_env.memo`): the file name and the SHA-256 of each
    function's serialization, which is the whole of its definition.
    """
    import casadi

    def compute() -> bytes:
        with tempfile.TemporaryDirectory() as folder:
            generator = casadi.CodeGenerator(file_name, {"with_header": False})
            for function in functions:
                generator.add(function)
            generator.generate(f"{folder}/")
            return (Path(folder) / file_name).read_bytes()

    definitions = [hashlib.sha256(f.serialize().encode()).digest() for f in functions]
    return _sources.get([file_name, *definitions], compute)


def generated_text(file_name: str, functions: Sequence[Any]) -> str:
    """:func:`generated_c` as text, read as ``Path.read_text(encoding="utf-8")`` reads it."""
    with io.TextIOWrapper(io.BytesIO(generated_c(file_name, functions)), encoding="utf-8") as f:
        return f.read()


@dataclass(frozen=True)
class CallBuffers:
    """The arrays one call of a generated casadi Function reads and writes, and the pointer
    tables the call takes (the C code holds their addresses: keep this object alive as long
    as it may run).

    Attributes
    ----------
    inputs, outputs : list of numpy.ndarray
        float64 buffers, one per input and output, in casadi's column-major order.
    arg, res : ctypes array of c_void_p
        Pointers to the inputs and to the outputs, as long as the generated code's
        ``<name>_work`` asks (at least 1).
    iw, w : numpy.ndarray
        Integer (int64) and float64 work arrays of the lengths ``<name>_work`` asks (at
        least 1).
    """

    inputs: list[np.ndarray]
    outputs: list[np.ndarray]
    arg: Any
    res: Any
    iw: np.ndarray
    w: np.ndarray

    @property
    def addresses(self) -> tuple[int, int, int, int]:
        """Addresses of ``arg``, ``res``, ``iw`` and ``w``: the generated function's first
        four arguments."""
        return (
            ctypes.addressof(self.arg),
            ctypes.addressof(self.res),
            self.iw.ctypes.data,
            self.w.ctypes.data,
        )


def call_buffers(
    library: ctypes.CDLL,
    function: Any,
    inputs: Sequence[np.ndarray] | None = None,
    *,
    nonzeros: bool = False,
) -> CallBuffers:
    """Input, output, pointer and work arrays for calling a generated casadi Function through
    ctypes.

    Parameters
    ----------
    library : ctypes.CDLL
        A library holding the Function's generated C (its ``<name>_work`` gives the lengths
        of the pointer tables and work arrays the generated code uses).
    function : casadi.Function
        The Function it was generated from (numbers and sizes of inputs and outputs).
    inputs : sequence of numpy.ndarray, optional
        Buffers the inputs are read from (C-contiguous float64, one per input, each as long
        as the input: its nonzeros with ``nonzeros``, else all its entries). Zeroed buffers
        are allocated when None.
    nonzeros : bool
        Size each input and output by its nonzeros (outputs flat, shape (nnz,)) instead of
        dense (outputs shaped (cols, rows): casadi's column-major (rows, cols) read row by
        row).

    Returns
    -------
    CallBuffers
        The buffers and pointer tables; its ``inputs`` are ``inputs`` when given.
    """
    count = function.nnz_in if nonzeros else function.numel_in
    if inputs is None:
        inputs = [np.zeros(count(i)) for i in range(function.n_in())]
    if len(inputs) != function.n_in():
        raise ValueError(f"{function.name()}: needs {function.n_in()} inputs, got {len(inputs)}")
    for i, buffer in enumerate(inputs):
        if buffer.size != count(i) or buffer.dtype != np.float64 or not buffer.flags.c_contiguous:
            raise ValueError(
                f"{function.name()}: input {i} needs a C-contiguous float64 array of {count(i)}"
            )
    if nonzeros:
        outputs = [np.zeros(function.nnz_out(i)) for i in range(function.n_out())]
    else:
        outputs = [
            np.zeros((function.size2_out(i), function.size1_out(i)))
            for i in range(function.n_out())
        ]
    sizes = [ctypes.c_longlong() for _ in range(4)]
    getattr(library, f"{function.name()}_work")(*[ctypes.byref(s) for s in sizes])
    n_arg, n_res, n_iw, n_w = (max(s.value, 1) for s in sizes)
    pointer = ctypes.c_void_p
    return CallBuffers(
        inputs=list(inputs),
        outputs=outputs,
        arg=(pointer * n_arg)(*[b.ctypes.data for b in inputs]),
        res=(pointer * n_res)(*[b.ctypes.data for b in outputs]),
        iw=np.zeros(n_iw, dtype=np.int64),
        w=np.zeros(n_w),
    )


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
        self._buffers = call_buffers(lib, function)
        self.inputs, self.outputs = self._buffers.inputs, self._buffers.outputs
        self._fn = getattr(lib, function.name())
        self._fn.restype = ctypes.c_int
        self._fn.argtypes = [ctypes.c_void_p] * 4 + [ctypes.c_int]
        self._lib = lib
        self._call_args = (*self._buffers.addresses, 0)

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


COMPILED, NUMPY, CASADI_VM = "compiled", "numpy", "casadi-vm"
"""Values of :attr:`NativeBuild.path`: what evaluates the function."""


@dataclass(frozen=True)
class NativeBuild:
    """What one native build did: the record a report shows.

    Attributes
    ----------
    function : str
        Name of the casadi Function built.
    path : str
        What evaluates it: :data:`COMPILED` (the generated C), or the caller's fallback,
        :data:`NUMPY` or :data:`CASADI_VM` (casadi's virtual machine).
    reason : str
        Whether the library was built now or found in the cache, or why there is none.
    compiler : str
        The compiler's resolved path and the first line of its ``--version`` ("" when none
        was found).
    flags : str
        Compiler flags, space-separated.
    key : str
        Cache key: SHA-256 of the generated source, flags, compiler, architecture, casadi
        version and Python ABI ("" when not reached).
    library : str
        Path the library was loaded from ("" when not compiled).
    sha256 : str
        Digest of the loaded library, verified before loading ("" when not compiled).
    compiler_output : str
        The compiler's stderr (its last 2000 characters) when it ran: the error when it
        failed, warnings when it built; "" for a library found in the cache.
    """

    function: str
    path: str
    reason: str
    compiler: str = ""
    flags: str = ""
    key: str = ""
    library: str = ""
    sha256: str = ""
    compiler_output: str = ""

    @property
    def compiled(self) -> bool:
        """Whether the generated C evaluates the function."""
        return self.path == COMPILED

    def __str__(self) -> str:
        return f"{self.path} ({self.reason})"

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe fields, and ``compiled``."""
        return {**dataclasses.asdict(self), "compiled": self.compiled}


NATIVE_POLICIES = ("auto", "off", "require")
STALE_DAYS = 30
"""Libraries of other keys not used for this many days are removed from the cache."""
_CRASH_AGE_S = 3600.0  # staging folders older than this belong to builds that died
_OUTPUT_CHARS = 2000


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
    """Create ``folder`` (mode 0700) and check that only this user can write it, or raise.

    Every folder created on the way (the cache root ``$PIEZO_CACHE`` and its missing
    parents) is made 0700 too; a folder that exists keeps its mode.

    The folder must be a plain folder (not a symlink) owned by this user and writable by no
    one else; one that others may only read is tightened to 0700. Its parent (the cache root)
    must be owned by this user or root and writable by no one else unless sticky (like
    /tmp), so that nobody can swap the folder for another.
    """
    for path in reversed((folder, *folder.parents)):
        # mkdir(parents=True) would make the parents 0777 minus the umask (0755 under 022),
        # and the umask may also take bits off 0700: each new folder is made and set here.
        if not path.exists():
            path.mkdir(mode=0o700, exist_ok=True)
            path.chmod(0o700)
    uid = os.getuid()
    for path, owners, sticky_ok in ((folder, {uid}, False), (folder.parent, {uid, 0}, True)):
        info = path.lstat()
        if stat.S_ISLNK(info.st_mode) or not stat.S_ISDIR(info.st_mode):
            raise OSError(f"{path} is not a plain folder (a symlink or a file)")
        if info.st_uid not in owners:
            raise OSError(f"{path} belongs to another user (uid {info.st_uid})")
        sticky = sticky_ok and info.st_mode & stat.S_ISVTX
        if info.st_mode & 0o022 and not sticky:
            raise OSError(f"{path} is writable by other users (set PIEZO_CACHE elsewhere)")
    if folder.lstat().st_mode & 0o077:
        folder.chmod(0o700)
    return folder


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """Hold the folder's build lock: one process at a time verifies, builds or cleans up."""
    import fcntl  # POSIX only: elsewhere the folder checks (os.getuid) already refused

    handle = os.open(folder / ".lock", os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
    try:
        fcntl.flock(handle, fcntl.LOCK_EX)
        yield
    finally:
        os.close(handle)  # closing releases the lock


def _remove_stale(folder: Path, keep: Path) -> None:
    """Drop staging folders of crashed builds, libraries without a digest (never loadable)
    and libraries of other keys unused for :data:`STALE_DAYS` days (call under the lock)."""
    now = time.time()
    for path in folder.iterdir():
        try:
            age = now - path.lstat().st_mtime
            if path.name.startswith("tmp") and path.is_dir():
                if age > _CRASH_AGE_S:
                    shutil.rmtree(path, ignore_errors=True)
            elif path.suffix == ".so" and path.stem != keep.stem:
                if age > STALE_DAYS * 86400 or not path.with_suffix(".sha256").exists():
                    path.unlink()
                    path.with_suffix(".sha256").unlink(missing_ok=True)
            elif path.suffix == ".sha256" and not path.with_suffix(".so").exists():
                path.unlink()
        except OSError:
            continue


@functools.lru_cache(maxsize=4)
def compiler_identity(command: tuple[str, ...]) -> str:
    """Resolved path and first line of ``--version`` of a compiler command (cache key, record)."""
    resolved = " ".join((os.path.realpath(command[0]), *command[1:]))
    try:
        done = subprocess.run(
            [*command, "--version"], capture_output=True, text=True, timeout=30, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return resolved
    lines = (done.stdout or done.stderr).strip().splitlines()
    return f"{resolved}: {lines[0]}" if lines else resolved


def cache_key(source: bytes, flags: Sequence[str], compiler: str) -> str:
    """SHA-256 (hex) naming a library: what else would change the bytes it holds.

    Parameters
    ----------
    source : bytes
        The generated C.
    flags : sequence of str
        Compiler flags.
    compiler : str
        :func:`compiler_identity` of the compiler.
    """
    import casadi

    key = hashlib.sha256(source)
    parts = (*flags, compiler, platform.machine(), sys.platform, casadi.__version__)
    for part in (*parts, sys.implementation.cache_tag or ""):
        key.update(b"\0" + part.encode())
    return key.hexdigest()


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _verified(library: Path) -> tuple[str | None, str]:
    """(digest, "") when the library is this user's regular file and matches the digest
    recorded beside it, else (None, what is wrong)."""
    try:
        info = library.lstat()
    except FileNotFoundError:
        return None, "not in the cache"
    if not stat.S_ISREG(info.st_mode) or info.st_uid != os.getuid():
        return None, "the cached library was not this user's regular file"
    try:
        expected = library.with_suffix(".sha256").read_text(encoding="ascii").strip()
    except OSError:
        return None, "the cached library had no digest"
    actual = _digest(library)
    if actual != expected:
        return None, "the cached library did not match its digest"
    return actual, ""


def _build(
    command: Sequence[str], flags: Sequence[str], source: Path, library: Path
) -> tuple[str, str]:
    """Compile ``source`` into ``library`` and its digest beside it, each written under a
    temporary name and renamed into place; (digest, compiler's stderr)."""
    staged = source.parent / library.name
    done = subprocess.run(
        [*command, *flags, "-o", str(staged), str(source), "-lm"],
        check=True,
        capture_output=True,
        text=True,
        timeout=300,
    )
    digest = _digest(staged)
    digest_file = staged.with_suffix(".sha256")
    digest_file.write_text(digest + "\n", encoding="ascii")
    os.chmod(staged, 0o700)
    # Renames are atomic: a reader sees the old file or the new one, never half of one. The
    # digest goes first so that a crash in between leaves a mismatch (rebuilt), never a
    # library trusted under an old digest.
    os.replace(digest_file, library.with_suffix(".sha256"))
    os.replace(staged, library)
    return digest, done.stderr[-_OUTPUT_CHARS:]


def _generate(function: Any, folder: Path) -> Path:
    """Write the C of a casadi Function into ``folder`` (:func:`generated_c`); the source
    file."""
    path = folder / f"{function.name()}.c"
    path.write_bytes(generated_c(path.name, [function]))
    return path


def _load(
    name: str,
    write_source: Callable[[Path], Path],
    load: Callable[[Path], Any],
    command: Sequence[str],
    identity: str,
    flags: Sequence[str],
    folder: Path,
) -> tuple[Any, NativeBuild]:
    """Write the C, then under the folder's lock find a verified library or build one, and
    load it with ``load(library)`` (raises OSError, subprocess and casadi errors for the
    caller to record)."""
    with tempfile.TemporaryDirectory(dir=folder) as staging:
        source = write_source(Path(staging))
        key = cache_key(source.read_bytes(), flags, identity)
        library = folder / f"{name}_{key[:16]}.so"
        with _locked(folder):
            digest, problem = _verified(library)
            output = ""
            if digest is None:
                digest, output = _build(command, flags, source, library)
                reason = f"built {library.name} ({problem})"
            else:
                reason = f"cached {library.name}, digest verified"
            loaded = load(library)
            os.utime(library)  # last use, for the stale-build clean-up
            _remove_stale(folder, keep=library)
    build = NativeBuild(
        name, COMPILED, reason, identity, " ".join(flags), key, str(library), digest, output
    )
    return loaded, build


def _fallback(
    name: str, path: str, reason: str, compiler: str = "", flags: str = "", output: str = ""
) -> NativeBuild:
    """The record of a build that fell back to ``path``; NativeCodeError under require."""
    if native_policy() == "require":
        detail = f": {output.strip()[-500:]}" if output.strip() else ""
        raise NativeCodeError(f"{name}: {reason} (PIEZO_NATIVE=require){detail}")
    return NativeBuild(name, path, reason, compiler, flags, compiler_output=output[-_OUTPUT_CHARS:])


def compile_function(
    function: Any,
    *,
    flags: Sequence[str] = DEFAULT_FLAGS,
    cache: str = "nmpc",
    fallback: str = NUMPY,
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
    fallback : str
        What the caller runs without native code (:data:`NUMPY` or :data:`CASADI_VM`), for
        the record.

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
    return _compile(
        function.name(),
        lambda folder: _generate(function, folder),
        lambda library: CompiledFunction(library, function),
        flags,
        cache,
        fallback,
    )


def compile_source(
    name: str,
    source: str,
    *,
    flags: Sequence[str] = DEFAULT_FLAGS,
    cache: str = "kernels",
    fallback: str = NUMPY,
) -> tuple[ctypes.CDLL | None, NativeBuild]:
    """Compile hand-written C (cached, verified, as :func:`compile_function`) and load it.

    Parameters
    ----------
    name : str
        Names the source file, the library and the record.
    source : str
        The C translation unit.
    flags, cache, fallback
        As :func:`compile_function`'s.

    Returns
    -------
    library : ctypes.CDLL or None
        The loaded library (the caller declares its functions' argument types); None when
        there is no native code.
    build : NativeBuild
        What happened, for reports.

    Raises
    ------
    NativeCodeError
        Under ``PIEZO_NATIVE=require``, instead of returning None.
    """

    def write(folder: Path) -> Path:
        path = folder / f"{name}.c"
        path.write_text(source, encoding="utf-8")
        return path

    return _compile(name, write, lambda library: ctypes.CDLL(str(library)), flags, cache, fallback)


def _compile(
    name: str,
    write_source: Callable[[Path], Path],
    load: Callable[[Path], Any],
    flags: Sequence[str],
    cache: str,
    fallback: str,
) -> tuple[Any, NativeBuild]:
    """The native policy, the compiler's lookup and the cached build of one library; every
    failure recorded as a fallback (or raised under ``require``)."""
    flag_text = " ".join(flags)
    if native_policy() == "off":
        return None, _fallback(name, fallback, "native code switched off (PIEZO_NATIVE=off)")
    command = shlex.split(os.environ.get("CC") or "cc")
    found = shutil.which(command[0]) if command else None
    if found is None:
        reason = f"no C compiler found (CC={os.environ.get('CC', 'cc')!r}; set CC)"
        return None, _fallback(name, fallback, reason, flags=flag_text)
    command[0] = found
    identity = compiler_identity(tuple(command))
    try:
        folder = _private_folder(cache_dir(cache))
        return _load(name, write_source, load, command, identity, flags, folder)
    except subprocess.CalledProcessError as exc:
        reason = f"the compiler failed (exit status {exc.returncode})"
        return None, _fallback(name, fallback, reason, identity, flag_text, exc.stderr or "")
    except (OSError, subprocess.SubprocessError, RuntimeError, AttributeError) as exc:
        reason = f"compilation failed ({type(exc).__name__}: {exc})"
        return None, _fallback(name, fallback, reason, identity, flag_text)


def as_numpy(outputs: Any) -> list[np.ndarray]:
    """casadi VM outputs as (cols, rows) numpy arrays, like :class:`CompiledFunction` gives."""
    return [np.asarray(o.full()).T for o in outputs]
