"""zoomcalib: calibrate zoom cameras and measure which error source limits the calibration."""

__version__ = "0.1.0"
