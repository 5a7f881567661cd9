"""The controller protocol, and controllers named by entry point (``"package.module:Name"``).

A controller is any object with

- ``reset(observation)``: start an episode from its first observation, and
- ``act(observation) -> numpy.ndarray`` of shape (1,): the drive voltage (V),

where the observation is the raw ``PiezoBender-v0`` one, ``[y_t, r_t, r_t+1 .. r_t+P]`` (um).
``stats`` (with ``fallbacks``) and ``describe() -> dict`` are optional; the benchmark measures
compute time, deadline misses and tracking itself, for every controller the same way.

A user's controller enters through a factory, called as ``factory(model, env, **options)``:
``model`` is the :class:`~controllers.prediction.PredictionModel` the benchmark runs on (the
identified Hammerstein model, or the true plant's for an oracle row), ``env`` the nominal env
(read it once; do not step it), ``options`` the keyword options given for the row. The factory
is named in gymnasium's entry-point convention, ``"package.module:attr"``, so that any process
(a spawned worker, a Ray node) can import it by its string; a class whose constructor takes
those arguments is a factory. Modules are imported as ``python -m`` would: from the current
folder first, then the installed packages.
"""

from __future__ import annotations

import importlib
import inspect
import os
import sys
from collections.abc import Callable
from typing import Any

__all__ = [
    "check_factory_options",
    "check_protocol",
    "entry_point_label",
    "is_entry_point",
    "load_entry_point",
]


def is_entry_point(name: str) -> bool:
    """Whether ``name`` names a factory by entry point (``"module:attr"``)."""
    return ":" in name


def entry_point_label(name: str) -> str:
    """The row name of an entry point: its attribute (``"pkg.mod:Name"`` -> ``"Name"``)."""
    return name.rsplit(":", 1)[1].rsplit(".", 1)[-1]


def load_entry_point(spec: str) -> Callable[..., Any]:
    """The factory ``spec`` names (``"package.module:attr"``), imported now.

    Raises
    ------
    ValueError
        One line saying what is wrong: a malformed spec, a module that does not import (with
        its error), a missing attribute, or an attribute that cannot be called.
    """
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr or ":" in attr:
        raise ValueError(
            f"controller entry point {spec!r} must read 'package.module:factory', e.g. "
            "'examples.feedforward_pi:FeedforwardPI'"
        )
    if os.getcwd() not in sys.path:  # as `python -m` does: the current folder first
        sys.path.insert(0, os.getcwd())
    try:
        obj: Any = importlib.import_module(module_name)
    except Exception as error:  # any import failure is the user's module's, reported as such
        raise ValueError(
            f"controller entry point {spec!r}: module {module_name!r} does not import "
            f"({type(error).__name__}: {error})"
        ) from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ValueError(
                f"controller entry point {spec!r}: {module_name!r} has no attribute {attr!r}"
            )
        obj = getattr(obj, part)
    if not callable(obj):
        raise ValueError(f"controller entry point {spec!r} is not callable (a factory is)")
    return obj


def check_protocol(controller: Any, name: str) -> Any:
    """``controller`` if it has callable ``reset`` and ``act``, else a one-line ValueError."""
    missing = [m for m in ("reset", "act") if not callable(getattr(controller, m, None))]
    if missing:
        raise ValueError(
            f"controller {name!r} ({type(controller).__name__}) breaks the controller protocol: "
            f"no callable {' or '.join(missing)}; it needs reset(observation) and "
            "act(observation) -> array of shape (1,) in volts"
        )
    return controller


def check_factory_options(spec: str, options: dict[str, Any]) -> None:
    """Refuse ``options`` that the factory ``spec`` names cannot take, before it is called.

    The factory is called as ``factory(model, env, **options)``: its signature is bound to two
    positional placeholders and the options, so an unknown or misspelt keyword is refused
    here (a factory taking ``**kwargs`` accepts any, and checks them itself when called).

    Raises
    ------
    ValueError
        One line naming the factory, the options it does not take and the ones it does.
    """
    factory = load_entry_point(spec)
    try:
        signature = inspect.signature(factory)
    except (TypeError, ValueError):  # a builtin without a signature: it checks when called
        return
    try:
        signature.bind(None, None, **options)
    except TypeError as error:
        params = list(signature.parameters.values())
        named = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
        taken = [p.name for p in params[2:] if p.kind in named]
        unknown = sorted(set(options) - set(taken))
        if unknown:
            raise ValueError(
                f"unknown option(s) {unknown} for controller {spec!r}; valid: "
                f"{', '.join(taken) or 'none (its factory takes no options)'}"
            ) from None
        raise ValueError(
            f"controller {spec!r} cannot be called as factory(model, env, **options): {error}"
        ) from None
