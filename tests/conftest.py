"""Shared fixtures: a small demo survey built once per test session."""
import pytest


@pytest.fixture(scope="session")
def small_survey(tmp_path_factory):
    """A 320x320 4-band demo field with a tiny grid; returns the config path."""
    from glaciar.demo import build_demo_survey

    out = tmp_path_factory.mktemp("survey")
    return build_demo_survey(out, shape=(320, 320), seed=11, n_galaxies=12, n_iterations=2,
                             z_values=(8.0, 10.4), mag_values=(24.0, 27.5))
