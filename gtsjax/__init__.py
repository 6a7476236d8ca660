"""gtsjax: a portable ground-truth system for mobile robots from one 2-D laser scanner, on JAX.

The numeric core follows the paper's Fig. 1, one private module per stage (``_segment``,
``_features``, ``_filters``, ``_classify``, ``_pose``, ``_maptransform``, ``_track``, all composed in
``_pipeline``); the host side (sensor link, files, command line) lives in ``gtsjax.io``,
``gtsjax.sim`` and ``gtsjax.cli``.
"""

from ._frontend import FrontEndConfig as FrontEndConfig
from ._frontend import front_end as front_end
from ._maptransform import Transform as Transform
from ._pipeline import Output as Output
from ._pipeline import PipelineState as PipelineState
from ._pipeline import init_state as init_state
from ._pipeline import step as step
from ._scan import Scan as Scan
from ._track import TrackerParams as TrackerParams
from .drivers.replay import process_log as process_log
from .errors import InputError as InputError
from .model import Model as Model
from .sensors import MODELS as MODELS
from .sensors import SensorModel as SensorModel
from .sensors import get_model as get_model

__version__ = "0.1.0"
