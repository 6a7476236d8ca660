"""The GP library's exceptions. The library is core code: it knows nothing of the command line, so
the host side that calls it (``gtsjax.train``) turns a :class:`GPArgumentError` into the CLI's
:class:`gtsjax.errors.InputError` with the same message."""


class GPArgumentError(ValueError):
    """An argument the GP library cannot use (bad shapes, no valid rows, a count below 1).

    ``str(err)`` is one line, ``"<where>: <what is wrong>"``, as an ``InputError``'s is.
    """

    def __init__(self, where: str, problem: str):
        self.where = where
        self.problem = problem
        super().__init__(f"{where}: {problem}")


class GPFitError(RuntimeError):
    """Every restart of the hyperparameter optimisation failed (non-finite or not converged)."""
