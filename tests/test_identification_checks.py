"""Integer and number settings of the identification package refuse bools, floats and NaN alike.

Every check goes through ``piezo_env.checks`` (one wording: "<name> must be an integer >= n").
"""

from __future__ import annotations

import numpy as np
import pytest

from identification.bayes_uniform import BayesUniformEstimator
from identification.config import IdentificationConfig
from identification.features import (
    PastInputFeatures,
    default_bouc_wen_levels,
    default_play_radii,
)
from identification.nls import TrainingSettings


@pytest.mark.parametrize(
    ("build", "name"),
    [
        (lambda v: BayesUniformEstimator(na=v, nb=2), "na"),
        (lambda v: BayesUniformEstimator(na=2, nb=v), "nb"),
        (lambda v: BayesUniformEstimator(na=2, nb=2, window=v), "window"),
        (lambda v: PastInputFeatures(n_past=v), "n_past"),
        (lambda v: default_play_radii((-30.0, 30.0), v), "n_play"),
        (lambda v: default_bouc_wen_levels((-30.0, 30.0), v), "n_bouc_wen"),
        (lambda v: TrainingSettings(batch_size=v), "batch_size"),
        (lambda v: TrainingSettings(hidden=(8, v)), "hidden width"),
        (lambda v: IdentificationConfig(validation_hold=v), "validation_hold"),
        (lambda v: IdentificationConfig(orders=(v,)), "ARX order"),
    ],
)
@pytest.mark.parametrize("value", [True, 2.0, -1, float("nan")])
def test_integer_settings_refuse_bools_floats_and_negatives(build, name, value):
    with pytest.raises(ValueError, match=f"{name} must be an integer >= "):
        build(value)


def test_numpy_integers_are_accepted_as_integers():
    assert PastInputFeatures(n_past=np.int64(3)).n_past == 3
    assert TrainingSettings(hidden=(np.int32(8),)).hidden == (8,)
    assert BayesUniformEstimator(na=np.int64(2), nb=np.int64(2)).n == 5


@pytest.mark.parametrize("value", [True, float("nan"), float("inf"), 0.0, "0.01"])
def test_learning_rate_must_be_a_positive_finite_number(value):
    with pytest.raises(ValueError, match="learning_rate must be a finite number > 0"):
        TrainingSettings(learning_rate=value)
