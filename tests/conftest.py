"""Shared test set-up: float64 on, CPU only."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import gc  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_code():
    """Drop every compiled executable after each test module. Each one holds memory
    mappings of its machine code, and the whole suite compiles enough of them to pass the
    kernel's limit of 65,530 mappings per process (vm.max_map_count), where XLA's next
    compile aborts or segfaults. Modules share compiled fixtures within themselves only."""
    yield
    jax.clear_caches()
    gc.collect()
