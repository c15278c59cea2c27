import jax

# float64 available for the high-precision comparisons; float32 tests pass float32 arrays
# explicitly (dtype follows the inputs, so x64 being on does not change them).
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

from hypothesis import settings  # noqa: E402 (after the config updates above)

# Deterministic property tests: CI runs the same examples every time (no flaky reds).
settings.register_profile("ci", derandomize=True, max_examples=200, deadline=None, print_blob=True)
settings.load_profile("ci")
