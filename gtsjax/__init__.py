"""gtsjax: a portable ground-truth system for mobile robots from one 2-D laser scanner, on JAX.

The numeric core follows the paper's Fig. 1, one private module per stage; the host side (sensor
link, files, command line) lives in ``gtsjax.io``, ``gtsjax.sim`` and ``gtsjax.cli``.
"""

from ._scan import Scan as Scan
from .errors import InputError as InputError
from .sensors import MODELS as MODELS
from .sensors import SensorModel as SensorModel
from .sensors import get_model as get_model

__version__ = "0.1.0"
