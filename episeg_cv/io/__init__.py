"""File formats: two-view calibrations (JSON, OpenCV YAML/XML) and the matches file."""

from .calibration import Calibration, load_calibration, save_calibration
from .matches import FORMAT, FORMAT_VERSION, read_matches, write_matches

__all__ = ["Calibration", "load_calibration", "save_calibration", "write_matches", "read_matches", "FORMAT",
           "FORMAT_VERSION"]
