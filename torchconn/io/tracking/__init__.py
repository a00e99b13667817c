"""Tracked video in: keypoints and midlines from SLEAP, DeepLabCut, WCON or plain arrays,
converted to an N-link swimmer's trajectory.

:func:`read_tracking` reads a file into :class:`Keypoints`; :func:`convert` (or
:func:`convert_file`) turns them into a :class:`~torchconn.trajectory.Trajectory` with a
:class:`ConversionReport` of everything assumed. ``python -m torchconn.convert`` is the command.
"""

from .convert import (
    Conversion,
    ConversionReport,
    ConversionSettings,
    convert,
    convert_file,
    midline_to_pose,
    resample_midline,
)
from .readers import FORMATS, Keypoints, TrackingFormatError, detect_format, read_tracking

__all__ = [
    "FORMATS", "Keypoints", "TrackingFormatError", "detect_format", "read_tracking",
    "ConversionSettings", "ConversionReport", "Conversion", "convert", "convert_file",
    "midline_to_pose", "resample_midline",
]
