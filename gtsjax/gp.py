"""Public surface of the GP regressor (paper section 3b, eqs 3-7); implementation in ``_gp.py``."""

from ._gp import (
    GP as GP,
)
from ._gp import (
    GPFitError as GPFitError,
)
from ._gp import (
    Hyperparameters as Hyperparameters,
)
from ._gp import (
    SparseGP as SparseGP,
)
from ._gp import (
    condition as condition,
)
from ._gp import (
    fit as fit,
)
from ._gp import (
    gram as gram,
)
from ._gp import (
    kernel as kernel,
)
from ._gp import (
    log_marginal_likelihood as log_marginal_likelihood,
)
