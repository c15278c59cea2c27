import gc
import os

# The suite compiles for a short compile, not for speed: XLA's CPU backend with its classic
# elemental emitters instead of the fusion emitters (the same programs compile in about half the
# time and run as fast: the stack's 10-layer kernel and its gradient, 1e5 points, 525 and 813-882
# ns per point either way), and LLVM's optimization level 0, the options the fits already choose
# for small problems (`jaxoptics._runtime._options.QUICK_COMPILE`): compiling is most of the
# suite's time, and level 0 takes a third of it off (test_stack.py and test_gradients.py: 343 s
# of test time at the default level, 241 s at level 0). Elementary functions give bit-identical
# results; composite kernels differ by rounding (float64 R to 3e-14 relative), as they would on
# another processor. Set before JAX starts its backend, and inherited by the subprocesses the suite
# starts (notebooks, command line, bench). Users run XLA's defaults: `test_cli.py::
# test_kernels_under_xla_default_emitters` runs the kernels under them, and the stress tool's
# documented tables (`python -m jaxoptics stress`) are measured under them; the suite's reduced
# sweep checks the same ulp limits at level 0.
SUITE_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=0")
_given = os.environ.get("XLA_FLAGS", "").split()
os.environ["XLA_FLAGS"] = " ".join(_given + [f for f in SUITE_FLAGS if f.split("=")[0] not in " ".join(_given)])

import jax  # noqa: E402 (after XLA_FLAGS)
import pytest  # noqa: E402

# float64 available for the high-precision comparisons; float32 tests pass float32 arrays
# explicitly (dtype follows the inputs, so x64 being on does not change them).
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

import mpmath as mp  # noqa: E402
from hypothesis import settings  # noqa: E402 (after the config updates above)

from jaxoptics.tools import mpref  # noqa: E402

# Deterministic property tests: CI runs the same examples every time (no flaky reds).
settings.register_profile("ci", derandomize=True, max_examples=200, deadline=None, print_blob=True)
settings.load_profile("ci")


_SESSION_CONFIG = {k: getattr(jax.config, k) for k in ("jax_enable_x64", "jax_numpy_rank_promotion", "jax_numpy_dtype_promotion")}


@pytest.fixture(autouse=True)
def _session_config():
    """Every test starts with the session's configuration, and a test that changes it (float32
    runs with `jax_enable_x64` off; mpmath's global precision, which some oracles set for a
    quadrature) cannot leak the change into the tests that pytest-xdist schedules after it on the
    same worker. mpmath starts at the oracles' precision (`mpref.DIGITS`, 50 digits): tests do
    their own mpmath arithmetic (derivatives by `mp.diff`, closed forms) at the global precision."""
    mp.mp.dps = mpref.DIGITS
    yield
    for key, value in _SESSION_CONFIG.items():
        if getattr(jax.config, key) != value:
            jax.config.update(key, value)


# Compiled programs a pytest worker keeps before it drops them (see `_free_compiled_programs`).
MAX_MAPPINGS = 25_000


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """After a test module, drop every compiled program if the worker holds many. XLA's CPU
    executables each hold many memory mappings (their code is linked as many small objects: the
    thin-film part of the stress test alone leaves about 6,800 and peaks near 10,900), and a pytest
    worker that keeps every program of the suite alive runs into the kernel's limit on mappings per
    process (`vm.max_map_count`, 65,530 by default), where the next compilation's `mmap` fails and
    XLA crashes. Below `MAX_MAPPINGS` the programs stay: the next modules on the worker reuse those
    they share (the same fit of the same model on the same grid) instead of compiling them again."""
    yield
    try:
        with open("/proc/self/maps") as f:
            mappings = sum(1 for _ in f)
    except OSError:  # no /proc (macOS): drop them after every module
        mappings = MAX_MAPPINGS + 1
    if mappings > MAX_MAPPINGS:
        jax.clear_caches()
        gc.collect()


# The test modules of the longest single tests (the notebooks, the stress sweep, the bench's
# sections, the multi-process and multi-device runs: each 10 s to 2 min), collected first: they
# start while the other worker has its half of the suite to run and then tests to take over
# (`--dist worksteal`, pyproject.toml), instead of one of them running alone at the end.
LONGEST_FIRST = ("test_notebooks.py", "test_stress.py", "test_bench.py", "test_distributed.py", "test_sharding.py")


def pytest_collection_modifyitems(items):
    rank = lambda item: LONGEST_FIRST.index(item.path.name) if item.path.name in LONGEST_FIRST else len(LONGEST_FIRST)
    items.sort(key=rank)  # stable: the order within each module, and of the other modules, stays
