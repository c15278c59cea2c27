import jax

# float64 available for the high-precision comparisons; float32 tests pass float32 arrays
# explicitly (dtype follows the inputs, so x64 being on does not change them).
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")
