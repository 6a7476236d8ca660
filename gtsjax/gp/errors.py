"""The GP library's exceptions."""


class GPFitError(RuntimeError):
    """Every restart of the hyperparameter optimisation failed (non-finite or not converged)."""
