"""Recordings that ship with torchconn, to try the pipeline on real tracked animals.

:func:`prickleback` is a SLEAP-tracked rock prickleback (*Xiphister mucosus*) from the R
package fishmechr (github.com/tytell/fishmechr, CC BY 4.0; :func:`attribution` has the
authors, source and licence). Each recording comes with the conversion settings it needs::

    rec = torchconn.datasets.prickleback()
    conversion = rec.convert()           # Conversion: trajectory and report
    # at the shell: torchconn-convert PATH --links 5 --fps 60 --keypoints ... --out DIR,
    # with the flags of rec.convert_args()
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from ..io.tracking import Conversion, ConversionSettings, convert_file

__all__ = ["TrackedRecording", "prickleback", "attribution"]

_ATTRIBUTION = "ATTRIBUTION.md"


@dataclass(frozen=True)
class TrackedRecording:
    """A tracking file that ships with torchconn and how to convert it.

    Attributes:
        name: short name (the function's).
        path: the file (inside the installed package; read it, do not write it).
        settings: the conversion settings it needs (links, frame rate, keypoints head to tail).
        description: what was recorded.
    """

    name: str
    path: Path
    settings: ConversionSettings
    description: str

    def convert(self) -> Conversion:
        """The recording converted with :attr:`settings`
        (:func:`~torchconn.io.tracking.convert_file`)."""
        return convert_file(self.path, self.settings)

    def convert_args(self) -> list[str]:
        """The ``torchconn-convert`` flags for :attr:`settings` (without ``--out``)."""
        s = self.settings
        args = [str(self.path), "--links", str(s.n_links)]
        if s.fps is not None:
            args += ["--fps", f"{s.fps:g}"]
        if s.keypoints is not None:
            args += ["--keypoints", ",".join(s.keypoints)]
        return args


def _file(name: str) -> Path:
    return Path(str(resources.files(__name__).joinpath(name)))


def prickleback() -> TrackedRecording:
    """A rock prickleback (*Xiphister mucosus*) swimming freely, tracked with SLEAP.

    ``XMUC02_Trial1_sleap-1.csv``: SLEAP's analysis CSV, 711 frames at 60 frames per second, 8
    keypoints head to tail (``Snout``, ``BP1`` ... ``BP6``, ``Tail``) in image pixels. Converted
    as a 5-link swimmer. From fishmechr (Tytell and Hawkins), CC BY 4.0: see
    :func:`attribution`.
    """
    keypoints = ("Snout", "BP1", "BP2", "BP3", "BP4", "BP5", "BP6", "Tail")
    return TrackedRecording(
        name="prickleback", path=_file("XMUC02_Trial1_sleap-1.csv"),
        settings=ConversionSettings(n_links=5, fps=60.0, keypoints=keypoints),
        description="rock prickleback (Xiphister mucosus), free swimming, SLEAP, 711 frames "
                    "at 60 fps, 8 keypoints",
    )


def attribution() -> str:
    """Authors, source, licence and changes of every shipped recording (Markdown)."""
    return _file(_ATTRIBUTION).read_text(encoding="utf-8")
