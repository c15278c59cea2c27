import gc
import os

# XLA's CPU backend compiles with its classic elemental emitters instead of the fusion emitters:
# the same programs compile in about half the time and run as fast (the stack's 10-layer kernel
# and its gradient, 1e5 points: 525 and 813-882 ns per point either way), and elementary functions
# give bit-identical results; composite kernels differ by rounding (float64 R to 3e-14 relative),
# as they would on another processor. Compiling is most of the suite's time. Set before JAX starts
# its backend, and inherited by the subprocesses the suite starts (notebooks, command line, bench);
# `test_cli.py::test_kernels_under_xla_default_emitters` runs the kernels under XLA's defaults.
XLA_FLAG = "--xla_cpu_use_fusion_emitters=false"
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {XLA_FLAG}".strip()

import jax  # noqa: E402 (after XLA_FLAGS)
import pytest  # noqa: E402

# float64 available for the high-precision comparisons; float32 tests pass float32 arrays
# explicitly (dtype follows the inputs, so x64 being on does not change them).
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

from hypothesis import settings  # noqa: E402 (after the config updates above)

# Deterministic property tests: CI runs the same examples every time (no flaky reds).
settings.register_profile("ci", derandomize=True, max_examples=200, deadline=None, print_blob=True)
settings.load_profile("ci")


_SESSION_CONFIG = {k: getattr(jax.config, k) for k in ("jax_enable_x64", "jax_numpy_rank_promotion", "jax_numpy_dtype_promotion")}


@pytest.fixture(autouse=True)
def _session_config():
    """Every test starts with the session's configuration, and a test that changes it (float32
    runs with `jax_enable_x64` off) cannot leak the change into the tests that pytest-xdist
    schedules after it on the same worker."""
    yield
    for key, value in _SESSION_CONFIG.items():
        if getattr(jax.config, key) != value:
            jax.config.update(key, value)


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drop every compiled program after each test module. XLA's CPU executables each hold many
    memory mappings (their code is linked as many small objects: the thin-film part of the
    stress test alone leaves about 6,800 and peaks near 10,900), and a pytest worker that keeps
    every program of the suite alive runs into the kernel's limit on mappings per process
    (`vm.max_map_count`, 65,530 by default), where the next compilation's `mmap` fails and XLA
    crashes."""
    yield
    jax.clear_caches()
    gc.collect()
