import atexit
import os
import shutil
import tempfile

import jax
import pytest

# A fresh, empty compilation cache for this test session (and the CLI subprocesses it
# starts), so no test depends on what earlier runs left in the user's cache. Under
# pytest-xdist the controller makes the folder and its workers share it (they start with
# the controller's environment), so a program compiled by one worker serves the others.
if "PYTEST_XDIST_WORKER" in os.environ and os.environ.get("SCHEIMFLUX_TEST_CACHE"):
    _CACHE = os.environ["SCHEIMFLUX_TEST_CACHE"]
else:
    _CACHE = tempfile.mkdtemp(prefix="scheimflux-test-jax-cache-")
    os.environ["SCHEIMFLUX_TEST_CACHE"] = _CACHE
    atexit.register(shutil.rmtree, _CACHE, True)
os.environ["SCHEIMFLUX_CACHE_DIR"] = _CACHE

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture
def getkey():
    """Return a function that hands out fresh PRNG keys."""
    keys = iter(jax.random.split(jax.random.key(5124), 10_000))
    return lambda: next(keys)
