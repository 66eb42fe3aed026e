"""The paper's metrics in pure JAX: point-set (JSD, COV, MMD, 1-NNA), SWD,
Chamfer distance, depth errors, the per-scan reconstruction errors of Table
III (reconstruction.py) and scores against a simulator's ground truth
(ground_truth.py).

``compare(real, fake, angles, *, protocol, num_points, seed, ...)`` gives all
of Table II between two sets of scans; ``protocol='paper'`` computes as the
authors' code does (see protocol.py).
"""

from dusty_jax.metrics.protocol import PROTOCOLS, compare

__all__ = ['PROTOCOLS', 'compare']
