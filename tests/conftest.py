"""Test configuration.

* float32 is JAX's default; tests that compare against tight tolerances request the ``x64``
  fixture (or are marked ``@pytest.mark.usefixtures("x64")``), which enables float64 for that test.
* Dtype promotion is strict: mixing float32 and float64 arrays, or ints and floats, is an error
  rather than a silent upcast.
* Warnings are errors (pyproject.toml).
* XLA's persistent compilation cache is on, in a folder made for this test run and shared by its
  xdist workers (see ``_compilation_cache``).
* JAX's in-memory caches are dropped after each test module (``_release_compiled_code``).
* ``JSHADOW_COMPILE_REPORT=FOLDER`` writes, per test, the seconds of tracing, lowering and XLA
  compilation (``_CompileReport``; ``python scripts/compile_report.py FOLDER`` sums them up).
"""

import gc
import json
import os
import shutil
import tempfile
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

jax.config.update("jax_numpy_dtype_promotion", "strict")

_CACHE_ENV = "JSHADOW_TEST_XLA_CACHE"
_OWN_CACHE = _CACHE_ENV not in os.environ  # this process (the xdist controller, or a lone pytest) made it


def _compilation_cache() -> None:
    """Turn on XLA's persistent compilation cache for this test run.

    Most of the suite's time is compilation, and many tests compile the same computation again
    (a new ``Renderer`` or closure of the same config is a new ``jax.jit`` to JAX's in-memory cache,
    but the same HLO). The persistent cache is keyed by the HLO, so those become file reads where
    JAX writes them: not for a program with a host callback, which every ``eqx.error_if`` check
    compiles to, so most of jshadow's programs are compiled anew in each process that needs them
    (2026-12-07, a full run: of 1545 s of XLA compilation, 158 s went to programs a process had
    compiled before, 21 s of it one stress program compiled again after its module's caches were
    dropped; a test helper that made a new closure per call now keeps one ``jax.jit`` per mesh). The
    folder is made by the first process that imports this file — xdist's controller, before it
    starts the workers, which inherit its path through ``JSHADOW_TEST_XLA_CACHE`` — and removed
    by that process at the end, so every run starts empty and no stale entry outlives it. A size
    limit is set because only then does JAX take a file lock around reads and writes, which two
    workers writing one entry need. ``JSHADOW_TEST_XLA_CACHE=off`` turns the cache off.
    """
    if _OWN_CACHE:
        os.environ[_CACHE_ENV] = tempfile.mkdtemp(prefix="jshadow-xla-cache-")
    path = os.environ[_CACHE_ENV]
    if path == "off":
        return
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.1)
    jax.config.update("jax_compilation_cache_max_size", 8 << 30)


_compilation_cache()


def subprocess_env(*, xla_flags: str = "") -> dict[str, str]:
    """The environment for a test's child Python process: CPU only, this run's XLA flags with
    ``xla_flags`` appended, and this run's compilation cache, so that a child compiling what an
    earlier one (or this process) compiled reads it from the cache instead."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    if xla_flags:
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {xla_flags}".strip()
    path = os.environ[_CACHE_ENV]
    if path != "off":
        env.update(
            JAX_COMPILATION_CACHE_DIR=path,
            JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=str(
                jax.config.jax_persistent_cache_min_compile_time_secs
            ),
            JAX_COMPILATION_CACHE_MAX_SIZE=str(jax.config.jax_compilation_cache_max_size),
        )
    return env


class _CompileReport:
    """Where a test's time goes: seconds of tracing, lowering and XLA compilation per test (from
    :mod:`jax.monitoring`'s duration events), with its wall time, written as JSON per process when
    ``JSHADOW_COMPILE_REPORT`` names a folder (``python scripts/compile_report.py FOLDER`` sums
    them up). Compilation includes reads of the persistent cache; ``saved`` is the compile time
    those reads saved. Off unless asked for."""

    EVENTS = {
        "/jax/core/compile/jaxpr_trace_duration": "trace",
        "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
        "/jax/core/compile/backend_compile_duration": "compile",
        "/jax/compilation_cache/compile_time_saved_sec": "saved",
    }

    def __init__(self, folder: str):
        self.folder = folder
        self.current = "(outside tests)"
        self.rows: dict[str, dict[str, float]] = {}
        jax.monitoring.register_event_duration_secs_listener(self._on_duration)

    def _row(self, test):
        return self.rows.setdefault(test, dict.fromkeys(("wall", *self.EVENTS.values()), 0.0))

    def _on_duration(self, event, duration, **_):
        if event in self.EVENTS:
            self._row(self.current)[self.EVENTS[event]] += duration

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item, nextitem):
        self.current = item.nodeid
        start = time.perf_counter()
        yield
        self._row(item.nodeid)["wall"] += time.perf_counter() - start
        self.current = "(outside tests)"

    def pytest_sessionfinish(self, session):
        os.makedirs(self.folder, exist_ok=True)
        name = os.environ.get("PYTEST_XDIST_WORKER", "main")
        with open(os.path.join(self.folder, f"compile_{name}.json"), "w") as f:
            json.dump(self.rows, f, indent=0)


def pytest_configure(config):
    folder = os.environ.get("JSHADOW_COMPILE_REPORT")
    # xdist's controller runs no tests: only the processes that do (workers, or a lone pytest)
    if folder and (os.environ.get("PYTEST_XDIST_WORKER") or not config.getoption("numprocesses", None)):
        config.pluginmanager.register(_CompileReport(folder), "jshadow-compile-report")


# Modules that hold the suite's slowest tests (25-75 s each in a full run, mostly compilation),
# slowest first. They are run first so that the two xdist workers end together on short tests,
# instead of one worker starting a minute-long test while the other has nothing left (in
# alphabetical order, several of them came last). That needs scripts/test.sh's ``--dist
# worksteal``: xdist starts each worker on a run of consecutive tests, so this block goes to one.
_SLOW_FIRST = (
    "test_sharding",
    "test_codegen",
    "test_stress",
    "test_edgescan_grad",
    "test_image_lookup_grad",
    "test_self_visibility",
    "test_render_grad",
    "test_determinism",
    "test_light_images",
    "test_environment_lights",
    "test_scene",
    "test_edgescan",
)


def pytest_collection_modifyitems(config, items):
    def rank(item):
        name = item.path.stem  # every kind of item has a path; not every kind has a module
        return _SLOW_FIRST.index(name) if name in _SLOW_FIRST else len(_SLOW_FIRST)

    items.sort(key=rank)  # stable: the order within a module is kept


def pytest_unconfigure(config):
    if _OWN_CACHE:  # the folder this process made (never "off": that comes from outside)
        shutil.rmtree(os.environ[_CACHE_ENV], ignore_errors=True)


settings.register_profile("ci", max_examples=30, deadline=None, derandomize=True)
settings.register_profile("dev", max_examples=15, deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "dev")

BATCH_SHAPES = [(), (1,), (3, 1, 2)]


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop JAX's in-memory caches of compiled programs after each test module. A worker that keeps
    every program of the suite runs out of memory maps for compiled code (``vm.max_map_count``,
    65530 here: LLVM "Cannot allocate memory", then a segmentation fault in XLA's compilation, seen
    on 2026-12-06 at 91 % of a full run); programs shared within a module are kept, and the
    persistent cache turns recompiling the others into file reads."""
    yield
    jax.clear_caches()
    gc.collect()


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
