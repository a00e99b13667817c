"""Tracked video in: keypoints and midlines from SLEAP, DeepLabCut, WCON, plain arrays or any
file (or dataset) of the ``movement`` package, converted to an N-link swimmer's trajectory.

:func:`read_tracking` reads a file into :class:`Keypoints`; :func:`convert` (or
:func:`convert_file`) turns them into a :class:`~torchconn.trajectory.Trajectory` with a
:class:`ConversionReport` of everything assumed; :func:`convert_movement` (or
:meth:`Trajectory.from_movement <torchconn.trajectory.Trajectory.from_movement>`) does the
same for a ``movement`` poses dataset. ``python -m torchconn.convert`` is the command.
"""

from .convert import (
    Conversion,
    ConversionReport,
    ConversionSettings,
    convert,
    convert_file,
    convert_movement,
    midline_to_pose,
    resample_midline,
)
from .readers import (
    FORMATS,
    Keypoints,
    TrackingFormatError,
    detect_format,
    keypoints_from_movement,
    read_tracking,
)

__all__ = [
    "FORMATS", "Keypoints", "TrackingFormatError", "detect_format", "read_tracking",
    "keypoints_from_movement",
    "ConversionSettings", "ConversionReport", "Conversion", "convert", "convert_file",
    "convert_movement",
    "midline_to_pose", "resample_midline",
]
