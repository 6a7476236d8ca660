"""The Typer application every command module registers on, and the guard that turns a user's
mistake into one line on stderr and exit status 2."""

import functools
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


#: Options whose path is a folder to write: shown as DIR, not FILE.
FOLDER_OPTIONS = ("--out-dir", "--out-bag", "--out-beliefs")


def _metavar(param) -> str:
    """A readable placeholder for an option or argument's value, in place of Typer's Python type
    (``<list[Path]>``, ``<bool>`` on a flag): nothing for a flag, FILE or DIR, N, NUMBER or TEXT."""
    if getattr(param, "is_flag", False):
        return ""
    d = param.type_descriptor
    bare = param.bare_type().removeprefix("list[").removesuffix("]")
    path = "DIR" if any(o in FOLDER_OPTIONS for o in getattr(param, "opts", ())) else "FILE"
    name = path if "Path" in bare else {"int": "N", "float": "NUMBER"}.get(bare, "TEXT")
    return name + ("..." if d.is_list else "")


QUIET_HELP = "No progress bar or live view; the results, warnings and errors still print."
_quiet = [False]  # set by any command's --quiet; reset by each call of ``gtsjax.cli.main``


def quiet() -> bool:
    """Whether this command was given ``--quiet``: progress bars (``Progress(disable=quiet())``) and
    live views stay off."""
    return _quiet[0]


def set_quiet(value: bool) -> None:
    _quiet[0] = bool(value)


# An example per command, shown at the end of its --help (and checked to parse, tests/test_cli.py).
EXAMPLES = {
    "demo": ["gtsjax demo --seconds 20 --view web"],
    "simulate": ["gtsjax simulate --list", "gtsjax simulate spl-train --seed 1 --out train.npz --site site.json"],
    "train": ["gtsjax train train.npz --site site.json --out model.npz"],
    "replay": ["gtsjax replay log.npz --site site.json --model demo --out gtd.csv",
               "gtsjax replay --log north=north.npz --log south=south.npz --site site.json --model match.npz "
               "--out gtd.csv"],
    "run": ["gtsjax run --port /dev/ttyACM0 --site site.json --model model.npz --out gtd.csv --record raw.npz"],
    "emulate": ["gtsjax emulate spl-eval --seed 2"],
    "recover": ["gtsjax recover raw.npz.journal"],
    "evaluate": ["gtsjax evaluate --model demo --scenario spl-eval:1000",
                 "gtsjax evaluate truth.npz --site site.json --model model.npz --out-dir eval-out"],
    "convert": ["gtsjax convert robot.bag --topic /scan --out robot.npz"],
    "info": ["gtsjax info demo", "gtsjax info log.npz"],
    "sensors": ["gtsjax sensors"],
    "plot": ["gtsjax plot gtd.csv --site site.json --truth truth.npz --out gtd.png",
             "gtsjax plot --coverage site.json"],
    "export-tum": ["gtsjax export-tum gtd.csv --out-dir tum"],
    "grade": ["gtsjax grade gtd.csv --robot nao3=nao3.tum --robot nao5=nao5.csv --site site.json",
              "gtsjax grade gtd.csv --robot nao3=match.mcap:/nao3/pose --frame nao3=mirrored --site site.json"],
    "tags": ["gtsjax tags --robots 10 --perimeter 0.8 --range 9 --names nao1,nao2,nao3,nao4,nao5,nao6,nao7,nao8,nao9,"
             "nao10 --out-dir tags"],
    "enrol": ["gtsjax enrol --site site.json --model utm.npz --robot nao3 --log nao3.npz --codes tags/tags.json",
              "gtsjax enrol --site site.json --model utm.npz --robot nao3 --port /dev/ttyACM0 --seconds 20"],
}


def command():
    """The Click command of :data:`app`, every parameter given a readable placeholder, an example at
    the end of its help (:data:`EXAMPLES`), and every command a ``--quiet`` (those with a live view
    have their own, which turns the view off too)."""
    cmd = typer.main.get_command(app)
    for sub in getattr(cmd, "commands", {}).values():
        for param in sub.params:
            if param.metavar is None:
                param.metavar = _metavar(param)
            if isinstance(param, typer.core.TyperArgument):  # its placeholder is its name: no Python type beside it
                param.display_type_rich = lambda ctx: None
            info = getattr(getattr(param, "type_descriptor", None), "parameter_info", None)
            if getattr(info, "readable", False):  # a Path: the loaders say in one line what cannot be read
                info.readable = False
        help_option = sub.get_help_option(sub.make_context(sub.name, [], resilient_parsing=True))
        if help_option is not None:
            help_option.metavar = ""
        if sub.name in EXAMPLES:
            sub.help = (sub.help or "").rstrip() + "\n\n\b\nExample" + ("s" if len(EXAMPLES[sub.name]) > 1 else "") \
                + ":\n" + "\n".join(f"  {e}" for e in EXAMPLES[sub.name])
        if not any(p.name == "quiet" for p in sub.params):
            sub.params.append(_quiet_option())
    return cmd


@functools.cache
def _quiet_option():
    """The ``--quiet`` flag as Typer makes it (taken from a one-option command of its own), setting
    :func:`quiet` instead of being passed to the command."""
    one = typer.Typer()

    @one.command()
    def _flag(q: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP, expose_value=False,
                                     callback=set_quiet)) -> None:
        pass

    param = next(p for p in typer.main.get_command(one).params if p.name == "q")
    param.metavar = ""
    return param


def fail(where: object, problem: str) -> "typer.Exit":
    """Print ``gtsjax: <where>: <problem>`` on stderr; return the exit (status 2) to raise."""
    print(f"gtsjax: {InputError(where, problem)}", file=sys.stderr)
    return typer.Exit(2)


MAX_TRACKS_HELP = ("Track slots (and robots given a pose per scan), 1–64, in place of the model's (default 8): at least as "
                   "many as robots on the field, a few more for look-alikes.")
CONFIRM_HELP = ("Scans of detections before a track is reported (default: the model's, half a second of its training "
                "logs' scans). More keeps short-lived look-alikes of a robot out and delays every robot's first row.")


from . import enrol as _enrol  # noqa: E402,F401  (registers ``gtsjax enrol`` on :data:`app`)
