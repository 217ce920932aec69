"""Applications of torchrot: local-global solvers whose local step is a
batched rotation fit.

- :mod:`~torchrot.apps.meshes`: built-in meshes generated in code (a 57k-vertex
  capsule surface, a 24k-tet octopus) and user OBJ/PLY/OFF surfaces.
- :mod:`~torchrot.apps.arap`: as-rigid-as-possible deformation (Sorkine & Alexa 2007).
- :mod:`~torchrot.apps.elasticity`: co-rotational elasticity (Chao et al. 2010),
  implicit time stepping on a ground plane.
- :mod:`~torchrot.apps.local_step`: :class:`~torchrot.apps.local_step.LocalStep`,
  the local step's rotation fit (SVD, torchrot one-step warm start, torchrot
  converged).
- :mod:`~torchrot.apps.sparse`: torch CSR operators and a factor-once SPD solve.

The solvers take their instrumentation as arguments (a ``recorder`` that sees
every local step, a ``timer`` whose ``phase(name)`` times each phase); the
benchmark and report machinery that uses them (scripted sessions, recorded
data sets, the paper's tables and figures) lives in :mod:`torchrot.bench`,
which nothing here imports.

Requires SciPy and libigl (``pip install torchrot[bench]``).
Convention everywhere: R maximises tr(R^T M) (column vectors; M = sum_i w_i
y_i x_i^T gives R x_i ~ y_i).
"""

__all__ = ["arap", "elasticity", "local_step", "meshes", "sparse"]
