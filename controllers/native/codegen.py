"""Generated C for casadi Functions: compile once, cache on disk, call through ctypes.

:func:`compile_function` writes a casadi Function as C (``casadi.CodeGenerator``), compiles it
with the machine's compiler (``$CC`` or ``cc``) into a shared library cached on disk
(``$PIEZO_CACHE`` or ``~/.cache/piezo-testbed``, one folder per user of this module, the file
keyed by the hash of the generated source and the flags), and loads it as a
:class:`CompiledFunction`: preallocated float64 buffers and one ctypes call per evaluation.
Without a working compiler it returns None and says why, so callers can fall back (casadi's
virtual machine, or numpy). Compilation takes a few seconds and happens once per function.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["CompiledFunction", "as_numpy", "cache_dir", "compile_function"]

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


def cache_dir(name: str = "nmpc") -> Path:
    """Folder of the compiled libraries of one user (``$PIEZO_CACHE`` or the home cache)."""
    root = os.environ.get("PIEZO_CACHE") or Path.home() / ".cache" / "piezo-testbed"
    return Path(root) / name


def compile_function(
    function: Any, *, flags: Sequence[str] = DEFAULT_FLAGS, cache: str = "nmpc"
) -> tuple[CompiledFunction | None, str]:
    """Generate C for a casadi Function, compile it (cached on disk) and load it.

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
        None when no compiler works (the caller then falls back).
    note : str
        What happened (the library, or why compilation failed), for reports.
    """
    import casadi

    compiler = shutil.which(os.environ.get("CC", "cc"))
    if compiler is None:
        return None, "no C compiler found (set CC)"
    name = function.name()
    try:
        folder = cache_dir(cache)
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=folder) as tmp:
            generator = casadi.CodeGenerator(f"{name}.c", {"with_header": False})
            generator.add(function)
            generator.generate(f"{tmp}/")
            source = Path(tmp) / f"{name}.c"
            key = hashlib.sha256(source.read_bytes() + " ".join(flags).encode())
            library = folder / f"{name}_{key.hexdigest()[:16]}.so"
            if not library.exists():
                staged = Path(tmp) / library.name
                subprocess.run(
                    [compiler, *flags, "-o", str(staged), str(source), "-lm"],
                    check=True,
                    capture_output=True,
                    timeout=300,
                )
                os.replace(staged, library)  # atomic: concurrent builders never see half a file
        return CompiledFunction(library, function), f"generated C, {library.name}"
    except (OSError, subprocess.SubprocessError, RuntimeError, AttributeError) as exc:
        return None, f"compilation failed ({type(exc).__name__})"


def as_numpy(outputs: Any) -> list[np.ndarray]:
    """casadi VM outputs as (cols, rows) numpy arrays, like :class:`CompiledFunction` gives."""
    return [np.asarray(o.full()).T for o in outputs]
