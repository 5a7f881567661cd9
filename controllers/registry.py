"""``controllers.make``: one constructor for every controller, by name."""

from __future__ import annotations

import dataclasses
import importlib
from pathlib import Path
from typing import Any

from controllers.prediction import PredictionModel
from controllers.protocol import (
    check_factory_options,
    check_protocol,
    is_entry_point,
    load_entry_point,
)
from controllers.task import ControlTask

__all__ = ["CONTROLLERS", "check_model_fits_env", "make", "prediction_model", "resolve_controller"]

CONTROLLERS: dict[str, tuple[str, str, dict[str, Any]]] = {
    "pid": ("controllers.pid", "PIDController", {"notch": False, "feedforward": False}),
    "pid-notch": ("controllers.pid", "PIDController", {"notch": True, "feedforward": False}),
    "pid-ff": ("controllers.pid", "PIDController", {"notch": True, "feedforward": True}),
    "mpc": ("controllers.mpc", "LinearMPC", {}),
    "mpc-adaptive": ("controllers.adaptive", "AdaptiveMPC", {}),
    "nmpc": ("controllers.nmpc", "NonlinearMPC", {}),
    "nmpc-ipopt": ("controllers.nmpc", "NonlinearMPC", {"solver": "ipopt"}),
    "policy": ("controllers.policy", "PolicyController", {}),
}
"""Name -> (module, class, preset options). Each class has a ``Settings`` dataclass."""


def prediction_model(model: Any, env: Any) -> PredictionModel:
    """The prediction model a controller runs on.

    Parameters
    ----------
    model : HammersteinModel, str, pathlib.Path, PredictionModel or "plant"
        An identified model (or the folder it was saved in), a ready prediction model, or
        ``"plant"`` for the oracle built from the env's true plant (``env.unwrapped.model``,
        seen through the env's sensor: :meth:`PredictionModel.from_plant`).
    env : gymnasium.Env
        The env (its drive range bounds the nonlinearity's search range).
    """
    if isinstance(model, PredictionModel):
        return model
    if isinstance(model, str) and model == "plant":
        return PredictionModel.from_plant(env.unwrapped.model, sensor=env.unwrapped.config.sensor)
    u_max = float(env.action_space.high[0])
    if isinstance(model, (str, Path)):
        if not Path(model).is_dir():
            raise ValueError(
                f"model {str(model)!r} is not a folder holding a saved model (model.json + "
                "weights.npz); pass a HammersteinModel, a model folder or 'plant'"
            )
        from identification.hammerstein import HammersteinModel

        model = HammersteinModel.load(model)
    if hasattr(model, "arx") and hasattr(model, "nls"):
        check_model_fits_env(getattr(model, "metadata", {}), env)
        return PredictionModel.from_hammerstein(model, u_max)
    raise ValueError(
        f"model must be a HammersteinModel, a model folder, a PredictionModel or 'plant'; "
        f"got {type(model).__name__}"
    )


def check_model_fits_env(metadata: dict[str, Any], env: Any) -> None:
    """Refuse a model identified on another bender or task than ``env``'s (ValueError, one line).

    Compares what the model files record (the bender's datasheet, else its name, and the
    sample time) with the env's nominal plant. A model on another bender would run, and fail
    quietly: the message says which differs and how to get the right model.
    """
    base = env.unwrapped
    plant, task = base.task.model, metadata.get("task", {})
    sheet = metadata.get("datasheet")
    mine = dataclasses.asdict(plant.params.datasheet)
    if sheet is not None:
        same_bender = sheet == mine
    else:  # model files written before the datasheet was recorded: the name
        same_bender = metadata.get("bender") in (None, plant.name)
    if not same_bender:
        raise ValueError(
            f"the model was identified on {metadata.get('bender', 'another bender')} but the env "
            f"is a {plant.name}; identify this bender first (piezo identify --bender "
            f"{plant.name.split('.')[0]}) or make the env with bender="
            f"{str(metadata.get('bender', '?')).split('.')[0]!r}"
        )
    dt = task.get("dt_s", metadata.get("dt"))
    if dt is not None and abs(float(dt) - float(plant.dt)) > 1e-12 * float(plant.dt):
        raise ValueError(
            f"the model was identified at dt = {dt} s but the env steps at dt = {plant.dt} s; "
            "identify at the env's sample time"
        )


def make(name: str, model: Any, env: Any, **options: Any) -> Any:
    """Build the controller ``name`` on ``model`` for the task of ``env``.

    Parameters
    ----------
    name : str
        One of :data:`CONTROLLERS`: ``"pid"``, ``"pid-notch"``, ``"pid-ff"``, ``"mpc"``,
        ``"mpc-adaptive"``, ``"nmpc"``, ``"nmpc-ipopt"``, ``"policy"``; or a user's factory
        as an entry point, ``"package.module:Name"``, called as
        ``Name(prediction_model, env, **options)`` and checked against the protocol
        (:mod:`controllers.protocol`).
    model : HammersteinModel, str, pathlib.Path, PredictionModel or "plant"
        See :func:`prediction_model`; for ``"policy"``, the folder of a trained policy
        (:func:`controllers.policy.save_policy`).
    env : gymnasium.Env
        The env it will run on; read once for dt, drive range, stroke and preview.
    **options
        Fields of the controller's ``Settings`` dataclass (a factory's own keywords).

    Raises
    ------
    ValueError
        For an unknown name or option (the message lists the valid ones) or a bad value.
    """
    if is_entry_point(name):  # a user's factory, named as gymnasium names envs
        factory = load_entry_point(name)
        check_factory_options(name, options)
        return check_protocol(factory(prediction_model(model, env), env, **options), name)
    cls, settings = resolve_controller(name, options)
    task = ControlTask.from_env(env)
    if name != "policy":  # a policy's model is its folder; it has no prediction model
        model = prediction_model(model, env)
    return cls(model, task, settings, name=name)


def resolve_controller(name: str, options: dict[str, Any]) -> tuple[type, Any]:
    """The controller class of ``name`` and its validated ``Settings`` for ``options``.

    Raises
    ------
    ValueError
        For an unknown name or option (the message lists the valid ones) or a bad value.
    """
    if name not in CONTROLLERS:
        raise ValueError(f"unknown controller {name!r}; valid: {', '.join(CONTROLLERS)}")
    module, cls_name, preset = CONTROLLERS[name]
    cls = getattr(importlib.import_module(module), cls_name)
    valid = {f.name for f in dataclasses.fields(cls.Settings)} - set(preset)
    unknown = sorted(set(options) - valid)
    if unknown:
        raise ValueError(
            f"unknown option(s) {unknown} for controller {name!r}; "
            f"valid: {', '.join(sorted(valid))}"
        )
    return cls, cls.Settings(**{**preset, **options})
