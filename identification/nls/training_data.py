"""Steps b-d of :func:`identification.nls.fit_nls`: memory features, normalisation on the training
block, and the affine start (a weighted ridge fit of z on the features)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from identification.features import (
    BoucWenFeatures,
    FeatureMap,
    PastInputFeatures,
    PlayFeatures,
    default_bouc_wen_levels,
    default_play_radii,
)

__all__ = ["Normalised", "feature_map_for", "normalisation", "ridge_skip"]


def feature_map_for(
    features: str,
    u_range: tuple[float, float],
    *,
    n_play: int,
    radii: ArrayLike | None,
    n_past: int,
    n_bouc_wen: int,
    levels: ArrayLike | None,
    initial_input: float,
) -> FeatureMap:
    """The memory feature map named by ``features`` (parameters as in :func:`fit_nls`)."""
    if features == "play":
        r = default_play_radii(u_range, n_play) if radii is None else np.asarray(radii, float)
        return PlayFeatures(radii=tuple(np.sort(r)), initial_input=initial_input)
    if features == "bouc-wen":
        lv = default_bouc_wen_levels(u_range, n_bouc_wen) if levels is None else levels
        return BoucWenFeatures(
            levels=tuple(np.sort(np.asarray(lv, float))), initial_input=initial_input
        )
    return PastInputFeatures(n_past=n_past, initial_input=initial_input)


@dataclass(frozen=True, eq=False)
class Normalised:
    """Features and target in the network's normalized coordinates, with the normalization.

    Attributes
    ----------
    x : numpy.ndarray, shape (T, n_f)
        Normalized features ``(F - feature_mean) / feature_scale`` of the whole record.
    t : numpy.ndarray, shape (T,)
        Normalized target ``(z - z_mean) / z_scale``.
    feature_mean, feature_scale : numpy.ndarray, shape (n_f,)
        Feature mean and standard deviation on the training block (1 where constant), V.
    z_mean, z_scale : float
        Mean and standard deviation of ``z`` on the training block (1 if constant), equiv. V.
    """

    x: np.ndarray
    t: np.ndarray
    feature_mean: np.ndarray
    feature_scale: np.ndarray
    z_mean: float
    z_scale: float


def normalisation(
    feature_map: FeatureMap, u: np.ndarray, z: np.ndarray, n_train: int
) -> Normalised:
    """Features of ``u`` from rest, and features and ``z`` normalized on the training block."""
    feats, _ = feature_map.features(u, feature_map.initial_state())
    f_train, z_train = feats[:n_train], z[:n_train]
    feature_mean = f_train.mean(axis=0)
    feature_scale = f_train.std(axis=0)
    feature_scale[feature_scale < 1e-12] = 1.0
    z_mean = float(z_train.mean())
    z_scale = float(z_train.std()) or 1.0
    x = (feats - feature_mean) / feature_scale
    t = (z - z_mean) / z_scale
    return Normalised(x, t, feature_mean, feature_scale, z_mean, z_scale)


def ridge_skip(x: np.ndarray, t: np.ndarray, w: np.ndarray, ridge: float) -> np.ndarray:
    """Weighted ridge fit ``t ~ x @ coef[:-1] + coef[-1]``; column 0 (u) and the offset free."""
    n, n_f = x.shape
    design = np.column_stack([x, np.ones(n)])
    gram = design.T @ (design * w[:, None])
    rhs = design.T @ (w * t)
    penalty = np.full(n_f + 1, ridge * float(w.sum()))
    penalty[0] = penalty[-1] = 0.0
    return np.linalg.lstsq(gram + np.diag(penalty), rhs, rcond=None)[0]
