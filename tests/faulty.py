"""Tasks and a controller whose worker process dies, as the out-of-memory killer would end it
(SIGKILL), and a task that fails: the backend and fault tests run them in spawned workers, which
import this module by name, so it imports nothing heavy at the top."""

from __future__ import annotations

import multiprocessing
import os
import signal
from pathlib import Path
from typing import Any

KILL_AT_STEP = 40


def die_once(i: int, folder: str) -> int:
    """``3 * i``; task 2's first attempt kills its worker (and leaves ``died-2`` in ``folder``)."""
    marker = Path(folder) / f"died-{i}"
    if i == 2 and not marker.exists():
        marker.touch()
        os.kill(os.getpid(), signal.SIGKILL)
    return 3 * i


def fail_first(i: int, folder: str) -> int:
    """``i`` after half a second; task 0 raises at once (each task leaves ``started-i`` in
    ``folder``)."""
    import time

    (Path(folder) / f"started-{i}").touch()
    if i == 0:
        raise ValueError("task 0 broke")
    time.sleep(0.5)
    return i


def always_die(i: int) -> int:
    """``i``; task 1 kills its worker on every attempt."""
    if i == 1:
        os.kill(os.getpid(), signal.SIGKILL)
    return i


class KilledWorker:
    """``mpc`` on the benchmark's model; in a worker process it sends itself SIGKILL at step
    :data:`KILL_AT_STEP` (inside its first episode, after the warm-up), on each attempt until
    ``kills`` attempts have died.

    Parameters
    ----------
    model, env
        As every controller factory gets them.
    marker : str
        A folder: one file per kill is left there, so a rerun of the same task (a new worker)
        knows how many attempts have died.
    kills : int
        How many attempts die.
    """

    def __init__(self, model: Any, env: Any, *, marker: str, kills: int = 1) -> None:
        import controllers

        self.inner = controllers.make("mpc", model, env)
        self.marker = Path(marker)
        self.kills = int(kills)
        self.steps = 0

    def reset(self, observation: Any) -> None:
        self.inner.reset(observation)

    def act(self, observation: Any) -> Any:
        self.steps += 1
        in_worker = multiprocessing.parent_process() is not None
        if in_worker and self.steps == KILL_AT_STEP:
            done = len(list(self.marker.iterdir()))
            if done < self.kills:
                (self.marker / f"killed-{done}").touch()
                os.kill(os.getpid(), signal.SIGKILL)
        return self.inner.act(observation)

    def describe(self) -> dict:
        return {"name": "KilledWorker", "inner": "mpc"}


class Broken:
    """A user's controller with one fault, chosen by ``fault``: ``"act"`` raises at step 30,
    ``"nan-action"`` returns NaN there, ``"build"`` raises when built, ``"describe"``
    describes itself with what JSON has no type for; any other value: none, and numpy values
    in its description (which are converted)."""

    def __init__(self, model: Any, env: Any, *, fault: str) -> None:
        if fault == "build":
            raise RuntimeError("cannot build")
        self.fault, self.steps = fault, 0

    def reset(self, observation: Any) -> None:
        self.steps = 0

    def act(self, observation: Any) -> Any:
        import numpy as np

        self.steps += 1
        if self.steps == 30 and self.fault == "act":
            raise RuntimeError("boom at step 30")
        if self.steps == 30 and self.fault == "nan-action":
            return np.array([np.nan])
        return np.zeros(1)

    def describe(self) -> dict:
        import numpy as np

        if self.fault == "describe":
            return {"handle": object()}
        return {"name": "Broken", "gains": np.arange(3), "ms": np.float32(1.5)}


def after_beside(folder: str, timeout_s: float = 60.0) -> str:
    """A prerequisite that finishes only once a task beside it has left ``beside`` in
    ``folder`` (so it can finish only if the pool runs that task while it runs), then leaves
    ``ready``; raises after ``timeout_s`` without it."""
    import time

    marker = Path(folder) / "beside"
    deadline = time.monotonic() + timeout_s
    while not marker.exists():
        if time.monotonic() > deadline:
            raise TimeoutError("no task ran beside the prerequisite")
        time.sleep(0.01)
    (Path(folder) / "ready").touch()
    return "ready"


def beside_or_after(i: int, folder: str, waits: bool) -> tuple[int, bool]:
    """``(i, whether the prerequisite had finished)``; each task leaves ``started-i`` in
    ``folder``, and one that does not wait also ``beside``."""
    (Path(folder) / f"started-{i}").touch()
    if not waits:
        (Path(folder) / "beside").touch()
    return i, (Path(folder) / "ready").exists()


def prerequisite_dies_once(folder: str) -> str:
    """``"ready"``; the first attempt kills its worker (leaving ``died-first`` in ``folder``)."""
    marker = Path(folder) / "died-first"
    if not marker.exists():
        marker.touch()
        os.kill(os.getpid(), signal.SIGKILL)
    (Path(folder) / "ready").touch()
    return "ready"


def always_die_first(folder: str) -> str:
    """A prerequisite that kills its worker on every attempt."""
    os.kill(os.getpid(), signal.SIGKILL)
    return "never"


def mark_ready(folder: str) -> str:
    """``"ready"``, leaving ``ready`` in ``folder``."""
    (Path(folder) / "ready").touch()
    return "ready"


def prerequisite_fails(folder: str) -> str:
    """Raises at once: an identification that breaks."""
    raise ValueError("the prerequisite broke")


def copy_model(source: str, target: str) -> dict[str, float]:
    """What ``piezo benchmark``'s identification leaves: a model folder (copied from
    ``source``) at ``target``; its timing as the identification returns it."""
    import shutil

    shutil.copytree(source, target)
    return {"identification_s": 0.0}


def process_id(*_: Any) -> int:
    """The id of the process that ran this call."""
    return os.getpid()


def mark_then(value: int, marker: str, seconds: float = 0.0) -> int:
    """``value``, after leaving the file ``marker`` and sleeping ``seconds`` (a helper's call
    whose running can be seen from outside)."""
    import time

    Path(marker).touch()
    time.sleep(seconds)
    return value


def raise_value_error(text: str) -> None:
    """Raise ``ValueError(text)`` (a helper's call that fails)."""
    raise ValueError(text)


def die() -> None:
    """Kill this process as the out-of-memory killer would."""
    os.kill(os.getpid(), signal.SIGKILL)


def always_fail() -> None:
    """A warm-up that fails."""
    raise OSError("no such thing on this worker")


def append(value: int, path: str) -> int:
    """``value``, after appending it as a line to the file ``path`` (the order calls ran in)."""
    with open(path, "a", encoding="utf-8") as file:
        file.write(f"{value}\n")
    return value


class TwoArgumentError(Exception):
    """An exception that cannot be unpickled: its ``__init__`` takes two arguments, and a
    pickle rebuilds it with the one message in ``args``."""

    def __init__(self, first: str, second: str) -> None:
        super().__init__(f"{first} {second}")


def raise_unpicklable() -> None:
    """Raise an exception whose pickle cannot be read back."""
    raise TwoArgumentError("cannot", "come back")
