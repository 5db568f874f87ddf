"""Shared test settings. ADSEISMIC_TEST_DEVICE=cuda:0 runs the propagator and gradient tests on a GPU
(CI runs them on the CPU)."""

import os

import pytest

DEVICE = os.environ.get("ADSEISMIC_TEST_DEVICE", "cpu")


@pytest.fixture
def device():
    return DEVICE
