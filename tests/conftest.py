"""Shared test settings. ADSEISMIC_TEST_DEVICE=cuda:0 runs the propagator and gradient tests on a GPU
(CI runs them on the CPU)."""

import os

import pytest

DEVICE = os.environ.get("ADSEISMIC_TEST_DEVICE", "cpu")


def slow(*values):
    """A parametrize case of the slow pass: .ci/run runs it (`pytest -m slow`), the README's command skips it."""
    return pytest.param(*values, marks=pytest.mark.slow)


@pytest.fixture
def device():
    return DEVICE
