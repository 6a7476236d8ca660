"""Command line: ``gtsjax COMMAND ...``. One module per command; parsing, progress, tables and exit
codes live here and nowhere else."""

import sys

from ..errors import InputError
from ._app import app

# Each import registers its command(s) on ``app``.
# from . import simulate as _simulate  # noqa: E402,F401  (registered once gtsjax.sim lands)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``gtsjax`` console script. A user's mistake (:class:`InputError`) is one
    line on stderr and exit status 2, never a traceback."""
    try:
        app(args=argv, prog_name="gtsjax", standalone_mode=False)
    except InputError as err:
        print(f"gtsjax: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("gtsjax: interrupted", file=sys.stderr)
        return 130
    except SystemExit as exc:  # typer.Exit / click exits
        return int(exc.code or 0) if not isinstance(exc.code, str) else 2
    except Exception as exc:  # click usage errors
        import click

        if isinstance(exc, click.exceptions.Exit):
            return exc.exit_code
        if isinstance(exc, click.ClickException):
            exc.show()
            return 2
        if isinstance(exc, click.exceptions.Abort):
            print("gtsjax: aborted", file=sys.stderr)
            return 130
        raise
    return 0
