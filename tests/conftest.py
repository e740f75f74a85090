"""Shared test set-up: float64 on, CPU only, a persistent compilation cache."""

import os
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# Compiled executables go to a cache on disk that the xdist workers, the notebook kernels
# (tests/test_notebooks.py passes the environment on) and later runs share: the modules
# below drop their in-memory executables (see _release_compiled_code) and several compile
# the same segments, which then load from disk (the suite runs about a quarter faster on a
# clean checkout, more on a warm one). Tests that count compilations count cache hits too.
# Set JAX_COMPILATION_CACHE_DIR to move it, or JAX_ENABLE_COMPILATION_CACHE=false to turn
# it off; `pytest --cache-clear` empties it with the rest of .pytest_cache.
os.environ.setdefault(
    "JAX_COMPILATION_CACHE_DIR",
    str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "d" / "jax-compilation"),
)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(2**30))  # bytes, LRU beyond

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import gc  # noqa: E402

import pytest  # noqa: E402

# Compilations seen by the tests that count them (the `compile_log` fixture). JAX's
# monitoring has no way to remove a listener, so one pair is registered here for the
# whole session and hands each event to the logs that are open.
_open_compile_logs: list[list] = []


def _on_compile(event, duration, **kwargs):
    if event == "/jax/core/compile/backend_compile_duration":
        for log in _open_compile_logs:
            log.append((str(kwargs.get("fun_name", "?")), duration))


def _on_cache_hit(event, **kwargs):
    # an executable loaded from the persistent cache above is a compilation too
    if event == "/jax/compilation_cache/cache_hits":
        for log in _open_compile_logs:
            log.append(("persistent cache hit", 0.0))


jax.monitoring.register_event_duration_secs_listener(_on_compile)
jax.monitoring.register_event_listener(_on_cache_hit)


@pytest.fixture
def compile_log():
    """A list that receives ``(function name, seconds)`` for every XLA compilation during
    the test (persistent-cache hits as ``("persistent cache hit", 0.0)``); ``clear()`` it
    where the counting should start."""
    log: list[tuple[str, float]] = []
    _open_compile_logs.append(log)
    yield log
    _open_compile_logs.remove(log)


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_code():
    """Drop every compiled executable after each test module. Each one holds memory
    mappings of its machine code, and the whole suite compiles enough of them to pass the
    kernel's limit of 65,530 mappings per process (vm.max_map_count), where XLA's next
    compile aborts or segfaults. Modules share compiled fixtures within themselves only."""
    yield
    jax.clear_caches()
    gc.collect()


# The slowest scopes (a module, or a class where a module is split in classes: what
# `pytest -n 2 --dist loadscope` hands to one worker), slowest first, from the suite's
# profile on 2 CPU cores (2026-12-06, a cold compilation cache: simulate 200 s, the second
# half of the notebooks 183 s, bem 151 s, the first half of the notebooks 147 s, interface
# scenes 132 s, calibration 115 s, the labtests' Brazilian disc 100 s, dsm 84 s, breakage
# scenes 83 s, bonded scenes 75 s; the labtests' biaxial block, 122 s then, takes 52 s on
# its own since its Jacobian is taken in forward mode). They are queued first so that no
# long scope starts last while the other worker sits idle; xdist's own order (most tests
# first) put the notebooks last.
# Only the order changes: a stale list costs time, never a test.
_SLOW_FIRST = (
    "tests/test_simulate.py",
    "tests/test_notebooks.py::TestNotebooksSecondHalf",
    "tests/test_bem.py",
    "tests/test_notebooks.py::TestNotebooksFirstHalf",
    "tests/test_interface_scenes.py",
    "tests/test_calibration.py",
    "tests/test_labtests.py::TestBrazilianDisc",
    "tests/test_dsm.py",
    "tests/test_breakage_scenes.py",
    "tests/test_bonded_scenes.py",
    "tests/test_labtests.py::TestBiaxialBlock",
)


def _slowness_rank(item) -> int:
    for k, scope in enumerate(_SLOW_FIRST):
        if item.nodeid.startswith(scope + "::"):
            return k
    return len(_SLOW_FIRST)


def pytest_configure(config):
    if hasattr(config.option, "loadscopereorder"):  # pytest-xdist: keep the order below
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items):
    items.sort(key=_slowness_rank)  # stable: the rest keep their order
