"""Command line: ``gtsjax COMMAND ...``. One module per command; parsing, progress, tables and exit
codes live here and nowhere else."""

import sys

from ..errors import InputError

# Each import registers its command(s) on ``app``.
from . import convert as _convert  # noqa: E402,F401
from . import demo as _demo  # noqa: E402,F401
from . import evaluate as _evaluate  # noqa: E402,F401
from . import export as _export  # noqa: E402,F401
from . import info as _info  # noqa: E402,F401
from . import plot as _plot  # noqa: E402,F401
from . import replay as _replay  # noqa: E402,F401
from . import run as _run  # noqa: E402,F401
from . import simulate as _simulate  # noqa: E402,F401
from . import train as _train  # noqa: E402,F401
from ._app import app


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``gtsjax`` console script. A user's mistake (:class:`InputError`) is one
    line on stderr and exit status 2, never a traceback; usage errors are Click's, also status 2."""
    import jax

    # Stamps and GP fitting need float64; the real-time core is float32 by explicit dtypes.
    jax.config.update("jax_enable_x64", True)
    try:
        app(args=argv, prog_name="gtsjax")
    except InputError as err:
        print(f"gtsjax: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("gtsjax: interrupted", file=sys.stderr)
        return 130
    except SystemExit as exc:
        code = exc.code
        return code if isinstance(code, int) else (0 if code is None else 2)
    return 0
