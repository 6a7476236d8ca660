"""The plain pipeline ``python -m benchmarks`` times gtsjax against: the NumPy / scikit-learn /
filterpy reference of ``tests/reference/`` (one module per stage, the second implementation the tests
check gtsjax's step against), gathered under the names the benchmark sections use. Run from the
repository root, where ``tests`` is importable."""

from tests.reference.gp import SklearnGP, sklearn_gp
from tests.reference.pipeline import ReferencePipeline, RefOutput, compare_tracks, scans_to_numpy
from tests.reference.track import Tracker

__all__ = ["RefOutput", "ReferencePipeline", "SklearnGP", "Tracker", "compare_tracks", "scans_to_numpy", "sklearn_gp"]
