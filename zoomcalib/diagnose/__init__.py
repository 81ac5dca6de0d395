"""Model discrepancy: what the simulation's principal-point model gets wrong on measured data.

``diagnose_table`` fits the paper's model and each physical extension to a per-zoom table and
names the cause (or ``none``); ``diagnose_input`` is the ``zoomcalib diagnose`` job.
"""

from .discrepancy import CAUSES, Diagnosis, diagnose_table
from .model import FocalRangeError, LensResponse
from .run import diagnose_input, load_zoom_table
from .synthetic import synthetic_zoom_table
from .table import ZoomTable

__all__ = ["CAUSES", "Diagnosis", "diagnose_table", "FocalRangeError", "LensResponse",
           "diagnose_input", "load_zoom_table", "synthetic_zoom_table", "ZoomTable"]
