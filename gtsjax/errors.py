"""The one exception type for a user's mistake.

Everything a user can get wrong (a file that is not what it claims, a missing key, a sensor model
that does not match) raises :class:`InputError` with a one-line message that names the file (or
frame) and the problem. The command line turns it into that line on stderr and exit status 2; no
traceback is ever shown for an ``InputError``.
"""


class InputError(ValueError):
    """Bad input from the user: a file, a frame or an argument.

    ``str(err)`` is a single line, ``"<where>: <what is wrong>"``.
    """

    def __init__(self, where: object, problem: str):
        self.where = str(where)
        self.problem = " ".join(str(problem).split())
        super().__init__(f"{self.where}: {self.problem}")


class InputWarning(UserWarning):
    """Something in the user's input was left out or repaired, and the work goes on: a text log's last
    line cut short (as a crash leaves it). ``str(warning)`` is one line, ``"<where>: <what>"``; the
    command line prints it as ``gtsjax: warning: <where>: <what>``."""

    def __init__(self, where: object, problem: str):
        self.where = str(where)
        self.problem = " ".join(str(problem).split())
        super().__init__(f"{self.where}: {self.problem}")
