import jax

# Tests run with float64 available; float32 cases pass dtype=jnp.float32 explicitly.
jax.config.update("jax_enable_x64", True)
