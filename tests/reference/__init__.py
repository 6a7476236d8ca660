"""The pipeline of Fig. 1 written a second time, the way a careful NumPy user would write it: the
second implementation the tests check gtsjax's jitted step against (``tests/test_reference.py``,
``tests/test_track.py``), and the plain pipeline ``python -m benchmarks`` times it against
(``benchmarks/reference.py`` imports it from here).

What "a careful NumPy user" means here:

* one scan at a time, in float64; segmentation vectorised over the beams; a Python loop over the
  segments, each segment's ORS and profiles vectorised over its points; ragged lists instead of
  padded slots (only the candidates that exist are processed, only the kept ones classified);
* every GP is a scikit-learn ``GaussianProcessRegressor`` (``ConstantKernel × RBF`` with the
  model's hyperparameters, ``optimizer=None``), predicting in batch for the scan's candidates;
* one filterpy ``KalmanFilter`` per track, with the same constant-velocity model, Mahalanobis gating,
  heading gate, greedy one-to-one assignment and track life cycle as ``gtsjax.core.g_track``;
* the map transformation as centred OLS with NumPy's ``eigvalsh`` and ``solve``.

Everything is read from a trained :class:`gtsjax.Model` (front-end settings, GP hyperparameters and
predictor arrays, tracker tuning, site), so the reference follows the model when it is retrained.

One module per stage, in the order of data flow:

============ ==========================================================================================
segment      stage a: breaks between consecutive beams, the first ``K`` segments
features     stages b–c: each segment's ORS, characteristic vector and binary filters
gp           one of the model's GPs (exact or DTC) in scikit-learn: its kernel, and a fitted GPR
classify     stages c–d: shape envelopes, class scores, thresholds, the open-set test
pose         stage e: ORS-relative pose and variances from the pose GPs
maptransform stage f: landmark association and the centred least-squares transform
track        stage g: one filterpy ``KalmanFilter`` per track, gating, assignment, life cycle
pipeline     the stages in order for one scan, and the comparison with gtsjax's outputs
============ ==========================================================================================

Importing this package imports nothing heavy; each module imports what its stage needs (filterpy
for ``track``, scikit-learn for ``gp``).
"""
