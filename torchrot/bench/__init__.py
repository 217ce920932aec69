"""Benchmark and report machinery of ``python -m torchrot bench``.

Nothing in the library (``torchrot``, ``torchrot.apps``) imports this
package; it imports the library. Its modules, each importing only those
listed before it (and the library):

- :mod:`~torchrot.bench.timing`: :class:`~torchrot.bench.timing.PhaseTimer`,
  the solvers' phase timer.
- :mod:`~torchrot.bench.recording`: :class:`~torchrot.bench.recording.Recorder`,
  the solvers' local-step recorder, and recorded-data loading.
- :mod:`~torchrot.bench.sessions`: scripted ARAP editing / elasticity drop sessions.
- :mod:`~torchrot.bench.statistics`: the paper's Fig. 5 statistics of a recording.
- :mod:`~torchrot.bench.data`: the cached recorded data sets ``"arap"`` and
  ``"elasticity"`` and :func:`~torchrot.bench.data.pairs` (recorded or generated
  ``(M, init)``; configurations and cache folder are arguments).
- :mod:`~torchrot.bench.micro`: the microbenchmark (methods, rows, plans, tables).
- :mod:`~torchrot.bench.experiments`: the solver experiments (Figs. 6, 7, libigl).
- :mod:`~torchrot.bench.report`: Markdown tables (Tables 1-2, Figs. 5-6 numbers).
- :mod:`~torchrot.bench.figures`: Figs. 5-7 as PNG.
- :mod:`~torchrot.bench.apps`: the applications part (stages, results, files).
- :mod:`~torchrot.bench.progress`: stage k of n, elapsed time.
- :mod:`~torchrot.bench.cli`: ``python -m torchrot bench``.
"""
