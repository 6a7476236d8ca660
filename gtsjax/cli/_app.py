"""The Typer application every command module registers on, and the guard that turns a user's
mistake into one line on stderr and exit status 2."""

import sys

import typer

from ..errors import InputError

app = typer.Typer(
    name="gtsjax",
    help="Portable laser ground truth for mobile robots: simulate, train, replay, run live.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            print(f"gtsjax {version('gtsjax')}")
        except PackageNotFoundError:  # run from a source tree that was never installed
            print("gtsjax (not installed: version unknown)")
        raise typer.Exit(0)


@app.callback()
def _root(version: bool = typer.Option(False, "--version", is_eager=True, callback=_version,
                                       help="Print gtsjax's version and exit.")) -> None:
    """Portable laser ground truth for mobile robots: simulate, train, replay, run live.

    Example, a live ground truth of a simulated robot: gtsjax demo"""


def _metavar(param) -> str:
    """A readable placeholder for an option or argument's value, in place of Typer's Python type
    (``<list[Path]>``, ``<bool>`` on a flag): nothing for a flag, FILE, N, NUMBER or TEXT."""
    if getattr(param, "is_flag", False):
        return ""
    d = param.type_descriptor
    bare = param.bare_type().removeprefix("list[").removesuffix("]")
    name = "FILE" if "Path" in bare else {"int": "N", "float": "NUMBER"}.get(bare, "TEXT")
    return name + ("..." if d.is_list else "")


def command():
    """The Click command of :data:`app`, every parameter given a readable placeholder."""
    cmd = typer.main.get_command(app)
    for sub in getattr(cmd, "commands", {}).values():
        for param in sub.params:
            if param.metavar is None:
                param.metavar = _metavar(param)
    return cmd


def fail(where: object, problem: str) -> "typer.Exit":
    """Print ``gtsjax: <where>: <problem>`` on stderr; return the exit (status 2) to raise."""
    print(f"gtsjax: {InputError(where, problem)}", file=sys.stderr)
    return typer.Exit(2)


MAX_TRACKS_HELP = ("Track slots (and robots given a pose per scan), in place of the model's (default 8): at least as "
                   "many as robots on the field, a few more for look-alikes.")
CONFIRM_HELP = ("Scans of detections before a track is reported (default: the model's, half a second of its training "
                "logs' scans). More keeps short-lived look-alikes of a robot out and delays every robot's first row.")
