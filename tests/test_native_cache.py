"""The compiled-code cache: verified loads, visible fallbacks, concurrent cold builds.

Tests may run as root, where a read-only mode does not stop writes: the read-only case is
also simulated by making the staging folder's creation fail as a read-only file system would.
"""

from __future__ import annotations

import ctypes
import errno
import json
import multiprocessing
import os
import time
from pathlib import Path

import casadi
import gymnasium as gym
import numpy as np
import pytest

import controllers
from controllers.native import codegen
from controllers.native.codegen import NativeCodeError, cache_key, compile_function

MODEL_DIR = str(Path(__file__).resolve().parents[1] / "docs" / "identify" / "model")
INPUT = np.array([0.1, 0.2, 0.3])


def _function(name: str = "cache_probe") -> casadi.Function:
    x = casadi.SX.sym("x", 3)
    return casadi.Function(name, [x], [casadi.sin(x) * 2.0 + casadi.sumsqr(x)])


def _evaluate(compiled) -> np.ndarray:
    return compiled(INPUT)[0].ravel().copy()


@pytest.fixture
def cache(tmp_path, monkeypatch):
    root = tmp_path / "cache"
    monkeypatch.setenv("PIEZO_CACHE", str(root))
    monkeypatch.delenv("PIEZO_NATIVE", raising=False)
    monkeypatch.delenv("CC", raising=False)
    return root


@pytest.fixture
def loads(monkeypatch) -> list[str]:
    """SHA-256 of every library file at the moment it is loaded."""
    seen: list[str] = []

    class Spy(codegen.CompiledFunction):
        def __init__(self, library: Path, function) -> None:
            seen.append(codegen._digest(library))
            super().__init__(library, function)

    monkeypatch.setattr(codegen, "CompiledFunction", Spy)
    return seen


def test_a_build_is_recorded_then_found_in_the_cache(cache):
    compiled, build = compile_function(_function(), cache="t")
    assert compiled is not None and build.compiled and build.path == "compiled"
    library = Path(build.library)
    assert library.parent == cache / "t" and library.name == f"cache_probe_{build.key[:16]}.so"
    assert library.with_suffix(".sha256").read_text().strip() == build.sha256
    assert build.reason.startswith("built") and build.compiler and "-fPIC" in build.flags
    assert oct((cache / "t").stat().st_mode & 0o777) == "0o700"
    np.testing.assert_allclose(_evaluate(compiled), np.sin(INPUT) * 2.0 + 0.14, rtol=1e-15)
    _, cached = compile_function(_function(), cache="t")
    assert cached.reason == f"cached {library.name}, digest verified"
    assert (cached.key, cached.sha256) == (build.key, build.sha256)
    assert json.loads(json.dumps(cached.to_dict()))["compiled"] is True


def test_call_buffers_by_nonzeros_on_given_inputs_equal_casadi(cache):
    """A sparse output (a diagonal Jacobian) called through the pointer tables, its nonzeros
    against casadi's virtual machine; the inputs given are the ones read."""
    x = casadi.SX.sym("x", 3)
    function = casadi.Function("sparse_probe", [x], [casadi.jacobian(casadi.sin(x), x)])
    compiled, build = compile_function(function, cache="t")
    assert build.compiled, build
    given = [INPUT.copy()]
    buffers = codegen.call_buffers(compiled._lib, function, given, nonzeros=True)
    assert buffers.inputs[0] is given[0] and buffers.outputs[0].shape == (3,)
    call = compiled._lib.sparse_probe
    call.argtypes, call.restype = [ctypes.c_void_p] * 4 + [ctypes.c_int], ctypes.c_int
    assert call(*buffers.addresses, 0) == 0
    np.testing.assert_allclose(buffers.outputs[0], function(INPUT).nonzeros(), rtol=1e-15)
    dense = codegen.call_buffers(compiled._lib, function)
    assert dense.outputs[0].shape == (3, 3) and dense.inputs[0].shape == (3,)
    with pytest.raises(ValueError, match="input 0 needs a C-contiguous float64 array of 3"):
        codegen.call_buffers(compiled._lib, function, [np.zeros(4)], nonzeros=True)


def _replace(path: Path, data: bytes) -> None:
    """A new file in place of ``path`` (the process may have the old one mapped)."""
    staged = path.with_name("replacement.tmp")
    staged.write_bytes(data)
    os.replace(staged, path)


@pytest.mark.parametrize("damage", ["library", "digest", "no digest"])
def test_a_corrupt_library_is_rebuilt_never_loaded(cache, loads, damage):
    _, first = compile_function(_function(), cache="t")
    library = Path(first.library)
    data = bytearray(library.read_bytes())
    data[len(data) // 2] ^= 0xFF
    if damage == "library":
        _replace(library, bytes(data))
    elif damage == "digest":
        _replace(library.with_suffix(".sha256"), b"0" * 64 + b"\n")
    else:
        library.with_suffix(".sha256").unlink()
    compiled, second = compile_function(_function(), cache="t")
    assert second.compiled and second.reason.startswith("built")
    assert "the cached library" in second.reason
    assert second.sha256 == first.sha256  # rebuilt: the original bytes
    assert loads == [first.sha256, first.sha256]  # the damaged bytes were never loaded
    assert _evaluate(compiled)[0] == pytest.approx(2 * np.sin(0.1) + 0.14)


def test_an_unusable_cache_falls_back_visibly(monkeypatch):
    monkeypatch.setenv("PIEZO_CACHE", "/dev/null/x")  # a path under a file: never writable
    monkeypatch.delenv("PIEZO_NATIVE", raising=False)
    compiled, build = compile_function(_function(), cache="t")
    assert compiled is None and not build.compiled and build.path == "numpy"
    assert "Not a directory" in build.reason
    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    native = controllers.make("mpc", MODEL_DIR, env).describe()["native"]
    assert native["nls_inverse"]["path"] == "numpy"
    assert "compilation failed" in native["nls_inverse"]["reason"]
    assert json.loads(json.dumps(native)) == native
    native = controllers.make("nmpc", MODEL_DIR, env).describe()["native"]
    assert native["nmpc_features"]["path"] == "casadi-vm"


@pytest.mark.parametrize("code", [errno.EROFS, errno.EACCES])
def test_a_read_only_cache_falls_back_visibly(cache, monkeypatch, code):
    def refuse(*args: object, **kwargs: object) -> None:
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(codegen.tempfile, "TemporaryDirectory", refuse)
    compiled, build = compile_function(_function(), cache="t")
    assert compiled is None and build.path == "numpy"
    assert os.strerror(code) in build.reason


@pytest.mark.skipif(
    hasattr(os, "geteuid") and os.geteuid() == 0,
    reason="root writes into read-only folders; the monkeypatched variant covers this case",
)
def test_a_read_only_cache_folder_falls_back_visibly(cache):
    (cache / "t").mkdir(parents=True, mode=0o700)
    (cache / "t").chmod(0o500)
    try:
        compiled, build = compile_function(_function(), cache="t")
    finally:
        (cache / "t").chmod(0o700)
    assert compiled is None and "Permission denied" in build.reason


@pytest.mark.parametrize(
    ("layout", "message"),
    [
        ("leaf writable by others", "writable by other users"),
        ("root writable by others", "writable by other users"),
        ("leaf is a symlink", "not a plain folder"),
    ],
)
def test_a_cache_others_could_write_is_refused(cache, tmp_path, layout, message):
    cache.mkdir(mode=0o700)
    if layout == "leaf writable by others":
        (cache / "t").mkdir()
        os.chmod(cache / "t", 0o777)
    elif layout == "root writable by others":
        os.chmod(cache, 0o777)
    else:
        (tmp_path / "elsewhere").mkdir(mode=0o700)
        (cache / "t").symlink_to(tmp_path / "elsewhere")
    compiled, build = compile_function(_function(), cache="t")
    assert compiled is None and message in build.reason


def test_a_fresh_cache_root_and_its_parents_are_private(tmp_path, monkeypatch):
    root = tmp_path / "new" / "cache"
    monkeypatch.setenv("PIEZO_CACHE", str(root))
    monkeypatch.delenv("PIEZO_NATIVE", raising=False)
    old = os.umask(0o022)  # the usual umask, under which mkdir(parents=True) makes 0755 parents
    try:
        compile_function(_function(), cache="t")
    finally:
        os.umask(old)
    for folder in (tmp_path / "new", root, root / "t"):
        assert oct(folder.stat().st_mode & 0o777) == "0o700", folder


def test_a_readable_cache_is_tightened_and_a_sticky_root_accepted(cache):
    cache.mkdir()
    os.chmod(cache, 0o1777)  # like /tmp: others may add entries but not replace ours
    (cache / "t").mkdir()
    os.chmod(cache / "t", 0o755)
    compiled, build = compile_function(_function(), cache="t")
    assert compiled is not None, build.reason
    assert oct((cache / "t").stat().st_mode & 0o777) == "0o700"


def test_the_policy_switch(cache, monkeypatch):
    monkeypatch.setenv("PIEZO_NATIVE", "off")
    compiled, build = compile_function(_function(), cache="t", fallback="casadi-vm")
    assert compiled is None and build.path == "casadi-vm" and "PIEZO_NATIVE=off" in build.reason
    assert not (cache / "t").exists()
    monkeypatch.setenv("PIEZO_NATIVE", "require")
    compiled, build = compile_function(_function(), cache="t")
    assert build.compiled  # require compiles as auto does when it can
    monkeypatch.setenv("PIEZO_CACHE", "/dev/null/x")
    with pytest.raises(NativeCodeError, match="PIEZO_NATIVE=require"):
        compile_function(_function(), cache="t")
    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    with pytest.raises(NativeCodeError, match="nls_inverse"):
        controllers.make("mpc", MODEL_DIR, env)
    monkeypatch.setenv("PIEZO_NATIVE", "sometimes")
    with pytest.raises(ValueError, match="PIEZO_NATIVE must be one of"):
        compile_function(_function(), cache="t")


def test_a_failing_compiler_leaves_its_message_in_the_record(cache, monkeypatch, tmp_path):
    fake = tmp_path / "broken-cc"
    fake.write_text(
        '#!/bin/sh\nif [ "$1" = --version ]; then echo broken 1.0; exit 0; fi\n'
        "echo 'error: this compiler is broken' >&2\nexit 1\n"
    )
    fake.chmod(0o755)
    monkeypatch.setenv("CC", str(fake))
    compiled, build = compile_function(_function("broken_probe"), cache="t")
    assert compiled is None and build.path == "numpy" and build.compiler.endswith("broken 1.0")
    assert build.reason == "the compiler failed (exit status 1)"
    assert "this compiler is broken" in build.compiler_output
    monkeypatch.setenv("PIEZO_NATIVE", "require")
    with pytest.raises(NativeCodeError, match="this compiler is broken"):
        compile_function(_function("broken_probe"), cache="t")
    assert not [p for p in (cache / "t").iterdir() if p.suffix == ".so"]


def test_the_cache_key_holds_compiler_flags_and_architecture(monkeypatch):
    base = cache_key(b"int f;", ("-O1",), "cc 12")
    assert base != cache_key(b"int f;", ("-O2",), "cc 12")
    assert base != cache_key(b"int f;", ("-O1",), "cc 13")
    assert base != cache_key(b"int g;", ("-O1",), "cc 12")
    monkeypatch.setattr(codegen.platform, "machine", lambda: "aarch64")
    assert base != cache_key(b"int f;", ("-O1",), "cc 12")


def _age(path: Path, days: float) -> None:
    then = time.time() - days * 86400
    os.utime(path, (then, then))


def test_stale_builds_are_removed(cache):
    _, build = compile_function(_function("stale_probe"), cache="t")  # creates the folder
    folder = cache / "t"
    for stem, days in (("old_0000000000000000", 31.0), ("recent_0000000000000000", 1.0)):
        for suffix in (".so", ".sha256"):
            (folder / (stem + suffix)).write_text("x")
            _age(folder / (stem + suffix), days)
    (folder / "orphan_0000000000000000.so").write_text("x")
    (folder / "tmpcrashed").mkdir()
    _age(folder / "tmpcrashed", 0.1)
    _age(Path(build.library), 40.0)  # the library in use is kept whatever its age
    compile_function(_function("stale_probe"), cache="t")
    names = {p.name for p in folder.iterdir()}
    assert {"recent_0000000000000000.so", "recent_0000000000000000.sha256"} <= names
    assert Path(build.library).name in names
    assert not names & {"old_0000000000000000.so", "old_0000000000000000.sha256"}
    assert not names & {"orphan_0000000000000000.so", "tmpcrashed"}


def _build_in_child(root: str, queue) -> None:
    os.environ["PIEZO_CACHE"] = root
    compiled, build = compile_function(_function("concurrent_probe"), cache="t")
    queue.put((build.compiled, build.reason, build.sha256, _evaluate(compiled).tolist()))


def test_concurrent_cold_builds_both_succeed(cache):
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    workers = [context.Process(target=_build_in_child, args=(str(cache), queue)) for _ in "ab"]
    for w in workers:
        w.start()
    results = [queue.get(timeout=120) for _ in workers]
    for w in workers:
        w.join(timeout=60)
    assert all(r[0] for r in results)
    assert results[0][2:] == results[1][2:]  # the same library, the same outputs
    assert sorted(r[1].split()[0] for r in results) == ["built", "cached"]  # compiled once
    assert not [p for p in (cache / "t").iterdir() if p.name.startswith("tmp")]
