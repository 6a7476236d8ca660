"""Host-side input and output: scan logs, site files (and, as they land, SCIP, serial, GTD writers)."""

from .logs import ScanLog as ScanLog
from .logs import from_scans as from_scans
from .logs import load_log as load_log
from .logs import save_log as save_log
from .logs import to_scans as to_scans
from .site import Landmark as Landmark
from .site import Site as Site
from .site import load_site as load_site
from .site import save_site as save_site
