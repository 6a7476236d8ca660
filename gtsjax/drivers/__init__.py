"""The drivers: what runs the pipeline's ``step`` over scans and owns its jit. The command line only
calls them.

* :mod:`~gtsjax.drivers.live`: frames from a sensor link, one compiled call per frame.
* :mod:`~gtsjax.drivers.batch`: the batch engine, stacks of scans in compiled chunks (one laser,
  several lasers merged, several logs side by side).
* :mod:`~gtsjax.drivers.replay`, :mod:`~gtsjax.drivers.several`: logged scan files through it.
* :mod:`~gtsjax.drivers.sink`: where a run's scans go (GTD CSV, sensor-pose CSV, bag, view, counts),
  batch and live alike.
* :mod:`~gtsjax.drivers.evaluation`: a labelled log replayed and scored against its truth.
"""
