"""Scene simulator: vertical prisms cut by a (possibly tilted) scan plane, sensor noise per model, and
scenarios that write labelled logs with their site files (``gtsjax simulate``). The pty emulator of a
live sensor lives in :mod:`gtsjax.sim.emulator`."""

from .scenarios import SCENARIOS as _SCENARIOS
from .scenarios import STYLES as STYLES
from .scenarios import check_scene as check_scene
from .scenarios import plan_scenario as plan_scenario
from .scenarios import recording as recording
from .scenarios import simulate as simulate
from .scene import Effects as Effects
from .scene import Scene as Scene
from .scene import render as render

SCENARIOS: dict[str, str] = {name: desc for name, (desc, _) in _SCENARIOS.items()}
