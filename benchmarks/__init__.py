"""gtsjax benchmarks: one command, side by side with what users would otherwise use.

    python -m benchmarks [--quick] [--out benchmarks/results.json] [--threads 1] [--only SECTION ...]

writes ``results.json``, ``results.md`` (the Markdown tables, targets and profiles) and
``scaling.png`` next to ``--out``, and prints the summary. ``--quick`` is the smoke run (small sizes,
few repetitions) that CI runs; CI checks the file is well formed, never a timing.

Sections (modules ``bench_<name>.py``, each ``run(ctx)``):

========== =========================================================================================
pipeline   per-stage and end-to-end step latency (URG-04LX, UTM-30LX), batch replay throughput
reference  same tracks as, and time per scan against, the NumPy/scikit-learn/filterpy reference
gp         GP fit time and LML against scikit-learn and tinygp
kalman     Kalman step against filterpy and dynamax; one scan's tracking with 8 tracks
smooth     RTS smoother of one track over 10⁵ scans: sequential (lax.scan) against associative scan
grade      grade() of 10 robots against a 10-minute two-laser ground truth (target: ≤ 30 s)
scaling    latency vs beams, K, M, training-set size; fit time vs N; throughput vs chunk; the plot
scip       SCIP 2.0 decode of a UTM-30LX frame
live       frame-to-GTD latency over a pseudo-terminal with the real live loop
========== =========================================================================================

``results.json`` schema (``"schema": "gtsjax-benchmarks/1"``):

* ``quick`` (bool); ``machine``: ``cpu_model``, ``cores``, ``cores_usable``, ``platform``,
  ``python``, ``numpy``, ``scipy``, ``scikit_learn``, ``jax``, ``jaxlib``, ``backend``, ``devices``,
  ``gpu`` (whether GPU figures were taken), ``thread_pools``, ``date`` (UTC, ISO 8601),
  ``load_average_start``, ``load_average_end``;
* ``settings``: ``threads`` (per library, both sides), ``command``, ``sections``, ``compile_cache``,
  ``malloc_tuned``, ``xla_flags``;
* ``measurements``: a list of ``{name, section, label, unit, median, p99, n, min, params}``; ``unit``
  is ``us``, ``ms``, ``s`` (durations) or ``scans/s`` (rates: ``median`` is the rate at the median
  run time, ``p99`` at the 99th-percentile run time); ``n`` the number of timed samples;
* ``ratios``: ``{name, numerator, denominator, stat, value, meaning}``, numerator and denominator
  naming two measurements of one unit (a ratio above 1 means gtsjax is faster);
* ``peers``: version of each peer library, or ``"skipped: not installed"``;
* ``checks``: agreement figures (reference tracks, Kalman means, GP LMLs, live frame counts);
* ``scaling``: the plotted series; ``targets``: ``{name, target, measured, unit, met, why, profile}``;
* ``profiles``: what explains each target's figure (stage breakdown, reference time shares, GP
  evaluation costs); ``sections``: per section its settings, ``seconds``, and ``error`` if it failed.
"""
