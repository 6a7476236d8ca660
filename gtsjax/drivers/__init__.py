"""The drivers: what runs the pipeline's ``step`` over scans and owns its jit. The command line only
calls them.

* :mod:`~gtsjax.drivers.live`: frames from a sensor link, one compiled call per frame.
* :mod:`~gtsjax.drivers.replay`: a logged scan file in compiled chunks, into the GTD CSV.
* :mod:`~gtsjax.drivers.evaluation`: a labelled log replayed and scored against its truth.
"""
