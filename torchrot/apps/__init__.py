"""Applications of torchrot: the local-global solvers of the paper's
experiments, their recorded data and the paper's tables and figures.

- :mod:`~torchrot.apps.meshes`: built-in meshes generated in code (a 57k-vertex
  capsule surface, a 24k-tet octopus) and user OBJ/PLY/OFF surfaces.
- :mod:`~torchrot.apps.arap`: as-rigid-as-possible deformation (Sorkine & Alexa 2007).
- :mod:`~torchrot.apps.elasticity`: co-rotational elasticity (Chao et al. 2010),
  implicit time stepping on a ground plane.
- :mod:`~torchrot.apps.local_step`: the local step's rotation fit (SVD, torchrot
  one-step warm start, torchrot converged).
- :mod:`~torchrot.apps.sessions`: scripted editing / drop sessions.
- :mod:`~torchrot.apps.recording`, :mod:`~torchrot.apps.datasets`: recorded
  local steps (M, warm start, M with it factored out), cached data sets
  ``"arap"`` and ``"elasticity"``.
- :mod:`~torchrot.apps.statistics`: the paper's Fig. 5 statistics.

Requires SciPy and libigl (``pip install torchrot[bench]``); tqdm optional.
Convention everywhere: R maximises tr(R^T M) (column vectors; M = sum_i w_i
y_i x_i^T gives R x_i ~ y_i).
"""
