"""The terminal tables show their units: a header like ``x [m]`` is Rich markup unless escaped, and Rich
silently drops ``[m]``, ``[cm]`` and ``[s]`` as unknown styles (the live view read ``x``, ``σx``;
evaluate's ``pos RMSE``). Rendered here as a user's terminal shows them."""

import types

from rich.console import Console

from gtsjax.cli._live import live_view
from gtsjax.cli.evaluate import COLUMNS, DET_COLUMNS, _table
from gtsjax.drivers.live import LiveStats


def _text(renderable) -> str:
    console = Console(record=True, width=400, color_system=None)
    console.print(renderable)
    return console.export_text()


def test_the_live_view_shows_its_units():
    link = types.SimpleNamespace(stats=types.SimpleNamespace(dropped=0, checksum_errors=0, salvaged=0, truncated=0,
                                                             malformed=0, garbage_bytes=0, timeouts=0, reconnects=0))
    stats = LiveStats()
    stats.add_latency(1.0)
    text = _text(live_view(types.SimpleNamespace(classes=("background", "robot")), link, stats, None, 0.0))
    for head in ("x [m]", "y [m]", "θ [°]", "σx [cm]", "σθ [°]"):
        assert head in text, text


def test_evaluate_tables_show_their_units():
    results = {"a": {key: 0.5 for key, _, _ in COLUMNS + DET_COLUMNS}}
    for columns in (COLUMNS, DET_COLUMNS):
        text = _text(_table("t", columns, results))
        for _, head, _ in columns:
            assert head in text, (head, text)
