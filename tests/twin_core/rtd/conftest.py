"""Shared helpers of the RTD tests."""

import pytest

from twin_core.rtd.likelihood import DeviationTest, LackOfFit, NoiseModel


@pytest.fixture
def shape_exchange_lof():
    """A factory of the lack of fit of one record from its shape and exchange tests' p-values
    (overall level 1 %; the statistics and degrees of freedom are placeholders)."""

    def make(p_shape: float, p_exchange: float) -> LackOfFit:
        tests = (
            DeviationTest("shape", 1.0, (6, 30.0), p_shape),
            DeviationTest("exchange", 1.0, (1, 30.0), p_exchange),
        )
        return LackOfFit(tests, 0.01, NoiseModel(1.0, 0.0, 0.0))

    return make
