"""The compiled-code cache: verified loads, visible fallbacks, concurrent cold builds."""

from __future__ import annotations

import multiprocessing
import os
from pathlib import Path

import casadi
import gymnasium as gym
import numpy as np
import pytest

import controllers
from controllers.native.codegen import NativeCodeError, compile_function

MODEL_DIR = str(Path(__file__).resolve().parents[1] / "docs" / "identify" / "model")


def _function(name: str = "cache_probe") -> casadi.Function:
    x = casadi.SX.sym("x", 3)
    return casadi.Function(name, [x], [casadi.sin(x) * 2.0 + casadi.sumsqr(x)])


def _evaluate(compiled) -> np.ndarray:
    return compiled(np.array([0.1, 0.2, 0.3]))[0].ravel().copy()


@pytest.fixture
def cache(tmp_path, monkeypatch):
    root = tmp_path / "cache"
    monkeypatch.setenv("PIEZO_CACHE", str(root))
    monkeypatch.delenv("PIEZO_NATIVE", raising=False)
    return root


def test_a_build_is_recorded_with_its_digest(cache):
    compiled, build = compile_function(_function(), cache="t")
    assert compiled is not None and build.compiled
    library = Path(build.library)
    assert library.parent == cache / "t" and library.exists()
    assert library.with_suffix(".sha256").read_text().strip() == build.sha256
    assert oct((cache / "t").stat().st_mode & 0o777) == "0o700"
    expected = np.sin([0.1, 0.2, 0.3]) * 2.0 + 0.14
    np.testing.assert_allclose(_evaluate(compiled), expected, rtol=1e-15)


def test_a_corrupt_library_is_rebuilt_never_loaded(cache):
    _, first = compile_function(_function(), cache="t")
    library = Path(first.library)
    data = bytearray(library.read_bytes())
    data[len(data) // 2] ^= 0xFF
    # A new file in its place (this process has the original mapped: never write into it).
    damaged = library.with_name("damaged.tmp")
    damaged.write_bytes(bytes(data))
    os.replace(damaged, library)
    compiled, second = compile_function(_function(), cache="t")
    assert second.compiled and second.sha256 == first.sha256  # rebuilt: the original bytes
    assert library.read_bytes() != bytes(data)
    assert _evaluate(compiled)[0] == pytest.approx(2 * np.sin(0.1) + 0.14)


def test_an_unusable_cache_falls_back_visibly(monkeypatch):
    monkeypatch.setenv("PIEZO_CACHE", "/dev/null/x")  # a path under a file: never writable
    monkeypatch.delenv("PIEZO_NATIVE", raising=False)
    compiled, build = compile_function(_function(), cache="t")
    assert compiled is None and not build.compiled
    assert "Not a directory" in build.reason
    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    native = controllers.make("mpc", MODEL_DIR, env).describe()["native"]
    assert native and not any(b["compiled"] for b in native.values())


def test_a_cache_other_users_can_write_is_refused(cache):
    cache.mkdir(mode=0o700)
    (cache / "t").mkdir()
    os.chmod(cache / "t", 0o777)
    compiled, build = compile_function(_function(), cache="t")
    assert compiled is None and "writable by other users" in build.reason


def test_the_policy_switch(cache, monkeypatch):
    monkeypatch.setenv("PIEZO_NATIVE", "off")
    compiled, build = compile_function(_function(), cache="t")
    assert compiled is None and "PIEZO_NATIVE=off" in build.reason
    monkeypatch.setenv("PIEZO_NATIVE", "require")
    monkeypatch.setenv("PIEZO_CACHE", "/dev/null/x")
    with pytest.raises(NativeCodeError, match="PIEZO_NATIVE=require"):
        compile_function(_function(), cache="t")
    monkeypatch.setenv("PIEZO_NATIVE", "sometimes")
    with pytest.raises(ValueError, match="PIEZO_NATIVE must be one of"):
        compile_function(_function(), cache="t")


def test_a_failing_compiler_leaves_its_message_in_the_record(cache, monkeypatch, tmp_path):
    fake = tmp_path / "broken-cc"
    fake.write_text("#!/bin/sh\nif [ \"$1\" = --version ]; then echo broken 1.0; exit 0; fi\n"
                    "echo 'error: this compiler is broken' >&2\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setenv("CC", str(fake))
    compiled, build = compile_function(_function("broken_probe"), cache="t")
    assert compiled is None and build.compiler.endswith("broken 1.0")
    assert "this compiler is broken" in build.compiler_output


def _build_in_child(root: str, queue) -> None:
    os.environ["PIEZO_CACHE"] = root
    compiled, build = compile_function(_function("concurrent_probe"), cache="t")
    queue.put((build.compiled, build.sha256, _evaluate(compiled).tolist()))


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
    assert results[0][1] == results[1][1] and results[0][2] == results[1][2]
    assert not [p for p in (cache / "t").iterdir() if p.name.startswith("tmp")]
