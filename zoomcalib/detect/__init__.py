"""Detection stage: images in, target points out (OpenCV pixel convention: the centre of the
top-left pixel is (0, 0), x right, y down). Re-exports the public API of
:mod:`zoomcalib.detect.opencv`."""

from zoomcalib.detect import opencv as _opencv
from zoomcalib.detect.opencv import *  # noqa: F403 (the list is opencv.__all__)

__all__ = list(_opencv.__all__)
