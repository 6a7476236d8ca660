"""gtsjax: a portable ground-truth system for mobile robots from one 2-D laser scanner, on JAX.

The numeric core follows the paper's Fig. 1, one private module per stage (``a_segment``,
``b_features``, ``c_filters``, ``d_classify``, ``e_pose``, ``f_maptransform``, ``g_track``, all composed in
``pipeline``); the host side (sensor link, files, command line) lives in ``gtsjax.io``,
``gtsjax.sim`` and ``gtsjax.cli``.
"""

from .core.f_maptransform import Transform as Transform
from .core.frontend import FrontEndConfig as FrontEndConfig
from .core.frontend import front_end as front_end
from .core.g_track import TrackerParams as TrackerParams
from .core.model import Model as Model
from .core.pipeline import Output as Output
from .core.pipeline import PipelineState as PipelineState
from .core.pipeline import init_state as init_state
from .core.pipeline import step as step
from .core.scan import Scan as Scan
from .drivers.batch import process_log as process_log
from .errors import InputError as InputError
from .errors import InputWarning as InputWarning
from .sensors import MODELS as MODELS
from .sensors import SensorModel as SensorModel
from .sensors import get_model as get_model

__version__ = "0.1.0"
