"""The measurement scripts' argument parser: a bad value is one line on stderr and exit status 2,
before any work (as ``gtsjax``'s own commands answer), not argparse's usage block."""

import argparse
import sys


class Parser(argparse.ArgumentParser):
    def error(self, message: str):  # noqa: D102 (argparse's hook)
        print(f"{self.prog}: {message}", file=sys.stderr)
        raise SystemExit(2)


def parser(doc: str) -> Parser:
    """A parser described by the first line of a script's docstring ``doc``."""
    return Parser(description=doc.splitlines()[0])
