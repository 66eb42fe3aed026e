"""The paper's metrics in pure JAX: point-set (JSD, COV, MMD, 1-NNA), SWD,
Chamfer distance, and depth errors."""
