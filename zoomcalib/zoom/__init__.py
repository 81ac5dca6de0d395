"""Zoom models: camera parameters as smooth functions of the zoom value."""

from zoomcalib.zoom.model import ZoomModel

__all__ = ["ZoomModel"]
