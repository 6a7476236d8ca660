"""Gaussian-process regression (paper section 3b, eqs 3-7): squared-exponential ARD kernel, type-II
maximum likelihood with Optimistix, exact and bounded-cost (DTC) prediction.

One concept per module, in the order of use:

- :mod:`gtsjax.gp.kernel`: log-space :class:`Hyperparameters`, the kernel (eq 3) and the log marginal
  likelihood (eq 5) with its closed-form gradient; the padding conventions.
- :mod:`gtsjax.gp.exact`: the exact :class:`GP` (conditioning, eqs 6-7).
- :mod:`gtsjax.gp.sparse`: the DTC :class:`SparseGP` the shipped models hold;
  :class:`SharedSparseGP`, several outputs of one kernel predicted from one kernel row; and
  ``CommonInputsGP``, separate GPs over one set of inducing inputs, held and read once.
- :mod:`gtsjax.gp.fit`: :func:`fit`, maximising eq 5 (eq 4) over the hyperparameters; :func:`fit_shared`,
  several outputs with shared length scales on the sum of their LMLs.
"""

from .errors import GPArgumentError as GPArgumentError
from .errors import GPFitError as GPFitError
from .exact import GP as GP
from .exact import condition as condition
from .exact import predict_mean as predict_mean
from .fit import fit as fit
from .fit import fit_shared as fit_shared
from .kernel import Hyperparameters as Hyperparameters
from .kernel import gram as gram
from .kernel import kernel as kernel
from .kernel import log_marginal_likelihood as log_marginal_likelihood
from .sparse import SharedSparseGP as SharedSparseGP
from .sparse import SparseGP as SparseGP
