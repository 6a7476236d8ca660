"""Host-side input and output: scan logs, site files (and, as they land, SCIP, serial, GTD writers)."""

from .logs import ScanLog as ScanLog, from_scans as from_scans, load_log as load_log, save_log as save_log, to_scans as to_scans
from .site import Landmark as Landmark, Site as Site, load_site as load_site, save_site as save_site
