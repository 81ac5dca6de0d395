"""Detection stage: images in, target points out (OpenCV pixel convention: the centre of the
top-left pixel is (0, 0), x right, y down)."""

from zoomcalib.detect.opencv import (
    DEFAULT_METHODS,
    IMAGE_EXTENSIONS,
    METHODS,
    Detection,
    default_method,
    detect_folder,
    detect_image,
    image_files,
    read_detections,
    write_detections,
)

__all__ = [
    "DEFAULT_METHODS",
    "Detection",
    "IMAGE_EXTENSIONS",
    "METHODS",
    "default_method",
    "detect_folder",
    "detect_image",
    "image_files",
    "read_detections",
    "write_detections",
]
