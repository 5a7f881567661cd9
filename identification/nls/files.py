"""The NLS as plain data: a JSON-safe dict and a dict of float64 arrays (model files).

``HammersteinModel.save`` writes them as ``model.json`` and ``weights.npz``; :meth:`from_dict`
rebuilds the NLS and raises a ValueError naming whatever is missing or malformed.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from identification.features import feature_map_from_dict

__all__ = ["ARRAY_NAMES", "NLS_FORMAT", "NLS_FORMAT_VERSION", "FilesMixin"]

NLS_FORMAT = "piezo-nls"
NLS_FORMAT_VERSION = 1

ARRAY_NAMES = (
    "feature_mean",
    "feature_scale",
    "z_mean",
    "z_scale",
    "skip_weight",
    "skip_bias",
    "out_weight",
    "out_bias",
)


"""Network arrays besides the hidden layers' ``layer{i}_weight`` and ``layer{i}_bias``."""


class FilesMixin:
    """Serialization methods of :class:`identification.nls.NLS`."""

    feature_map: Any
    u_range: tuple[float, float]
    training: dict
    hidden: tuple
    _params: dict

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe configuration (format, features, widths, input range, training record)."""
        return {
            "format": NLS_FORMAT,
            "version": NLS_FORMAT_VERSION,
            "features": self.feature_map.to_dict(),
            "hidden": list(self.hidden),
            "u_range": list(self.u_range),
            "training": self.training,
        }

    def arrays(self) -> dict[str, np.ndarray]:
        """Network parameters as a dict of float64 arrays (copies), for ``np.savez``."""
        return {name: value.copy() for name, value in self._params.items()}

    @classmethod
    def from_dict(cls, config: dict[str, Any], arrays: dict[str, np.ndarray]) -> Any:
        """Rebuild an NLS from :meth:`to_dict` and :meth:`arrays` output.

        Raises
        ------
        ValueError
            If the format or version does not match, a key is missing, or an array has the
            wrong shape for the configuration.
        """
        if not isinstance(config, dict):
            raise ValueError(f"NLS config must be a dict; got {type(config).__name__}")
        if config.get("format") != NLS_FORMAT:
            raise ValueError(
                f"NLS config format is {config.get('format')!r}; expected {NLS_FORMAT!r}"
            )
        if config.get("version") != NLS_FORMAT_VERSION:
            raise ValueError(
                f"NLS config version is {config.get('version')!r}; this code reads version "
                f"{NLS_FORMAT_VERSION}"
            )
        missing = [k for k in ("features", "hidden", "u_range") if k not in config]
        if missing:
            raise ValueError(f"NLS config is missing key(s) {missing}")
        try:
            feature_map = feature_map_from_dict(config["features"])
        except (KeyError, TypeError) as exc:
            raise ValueError(f"NLS config 'features' is incomplete: {exc!r}") from None
        nls = cls(
            feature_map,
            dict(arrays),
            u_range=config["u_range"],
            training=config.get("training") or {},
        )
        if list(nls.hidden) != list(config["hidden"]):
            raise ValueError(
                f"NLS weights have hidden widths {list(nls.hidden)} but the config says "
                f"{config['hidden']}"
            )
        return nls
