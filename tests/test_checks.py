"""The shared argument checks: what passes, what is refused and what the message says."""

import numpy as np
import pytest

from piezo_env.checks import require_int, require_number


@pytest.mark.parametrize("value", [1, 7, np.int64(3)])
def test_require_int_accepts_integers(value):
    assert require_int("n", value) == int(value)
    assert type(require_int("n", value)) is int


@pytest.mark.parametrize("value", [0, -1, True, 1.0, "2", None])
def test_require_int_refuses_and_names_the_argument(value):
    with pytest.raises(ValueError, match=r"n must be an integer >= 1, got"):
        require_int("n", value)


def test_require_int_minimum():
    assert require_int("preview", 0, minimum=0) == 0
    with pytest.raises(ValueError, match=">= 0"):
        require_int("preview", -1, minimum=0)


@pytest.mark.parametrize("value", [np.nan, np.inf, True, "1", None])
def test_require_number_refuses_non_numbers(value):
    with pytest.raises(ValueError, match="x must be a finite number"):
        require_number("x", value)


def test_require_number_bounds():
    assert require_number("x", np.float32(0.5), low=0, high=1) == 0.5
    assert require_number("x", 0, low=0) == 0.0
    with pytest.raises(ValueError, match="> 0"):
        require_number("x", 0, low=0, low_open=True)
    with pytest.raises(ValueError, match="<= 1"):
        require_number("x", 1.5, low=0, high=1)
