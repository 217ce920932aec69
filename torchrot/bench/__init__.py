"""Benchmark and report machinery of ``python -m torchrot bench``.

Two places hold benchmark code, by what they are for:

- ``torchrot.bench`` (this package, shipped with torchrot): the main job,
  ``python -m torchrot bench``, and everything it runs and reports with:
  timing, the methods and plans, the trust checks, tables, figures and
  result files. Anyone who installs ``torchrot[bench]`` can run it.
- ``benchmarks/*.py`` (in the repository only): standalone scripts for the
  project's own investigations (speed targets, instruction counts, the
  authors' kernel, the training benchmark, ...). They reuse this package's
  timing, tables and data rather than keeping copies of them.

Nothing in the library (``torchrot``, ``torchrot.apps``) imports this
package or ``benchmarks``; it imports the library, module by module (never
the package root). Its modules, each importing only those listed before it
(and the library):

- :mod:`~torchrot.bench.timing`: how calls are timed (``blocked_autorange``
  medians, interleaved samples) and the solvers' phase timer.
- :mod:`~torchrot.bench.machine`: the machine's description and its load.
- :mod:`~torchrot.bench.progress`: stage k of n, elapsed time; progress bars
  that redraw only on a terminal.
- :mod:`~torchrot.bench.recording`: the solvers' local-step recorder, and recorded-data loading.
- :mod:`~torchrot.bench.sessions`: scripted ARAP editing / elasticity drop sessions.
- :mod:`~torchrot.bench.statistics`: the paper's Fig. 5 statistics of a recording.
- :mod:`~torchrot.bench.data`: the cached recorded data sets ``"arap"`` and
  ``"elasticity"`` and :func:`~torchrot.bench.data.pairs` (recorded or generated
  ``(M, init)``; configurations and cache folder are arguments).
- :mod:`~torchrot.bench.options`: the command-line vocabulary shared with ``benchmarks/``.
- :mod:`~torchrot.bench.registry`: the methods the microbenchmark times.
- :mod:`~torchrot.bench.accuracy`: errors against float64 SVD.
- :mod:`~torchrot.bench.rows`: a table row and how rows group into tables.
- :mod:`~torchrot.bench.trust`: which rows not to trust; their re-timing.
- :mod:`~torchrot.bench.cases`: timing one table (``run_case``, ``run_checked_case``).
- :mod:`~torchrot.bench.plans`: the quick and full plans, as stages.
- :mod:`~torchrot.bench.workloads`: single-matrix call, rotation layer, registration.
- :mod:`~torchrot.bench.tables`: the microbenchmark's Markdown tables.
- :mod:`~torchrot.bench.experiments`: the solver experiments (Figs. 6, 7, libigl).
- :mod:`~torchrot.bench.report`: Markdown tables (Tables 1-2, Figs. 5-6 numbers).
- :mod:`~torchrot.bench.figures`: the scaling plot and Figs. 5-7 as PNG.
- :mod:`~torchrot.bench.results`: ``bench.json``, ``bench.md``, ``bench_scaling.png``.
- :mod:`~torchrot.bench.summary`: the run's closing headline.
- :mod:`~torchrot.bench.apps`: the applications part (stages, results, files).
- :mod:`~torchrot.bench.cli`: ``python -m torchrot bench``.
"""

__all__: list[str] = []  # a namespace of modules: import them by name
