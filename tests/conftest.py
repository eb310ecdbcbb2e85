"""Test configuration.

* float32 is JAX's default; tests that compare against tight tolerances request the ``x64``
  fixture (or are marked ``@pytest.mark.usefixtures("x64")``), which enables float64 for that test.
* Dtype promotion is strict: mixing float32 and float64 arrays, or ints and floats, is an error
  rather than a silent upcast.
* Warnings are errors (pyproject.toml).
"""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

jax.config.update("jax_numpy_dtype_promotion", "strict")

settings.register_profile("ci", max_examples=30, deadline=None, derandomize=True)
settings.register_profile("dev", max_examples=15, deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "dev")

BATCH_SHAPES = [(), (1,), (3, 1, 2)]


@pytest.fixture
def x64():
    """Run the test with float64 enabled."""
    with jax.enable_x64(True):
        yield


@pytest.fixture
def rng():
    """A seeded numpy generator (tests are deterministic)."""
    return np.random.default_rng(12345)


def random_dirs(rng, shape, dtype=np.float64):
    """Uniform unit vectors of shape (*shape, 3)."""
    v = rng.normal(size=(*shape, 3))
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(dtype)
