"""Readers of tracked keypoints and midlines: SLEAP, DeepLabCut, WCON and plain point arrays.

Every reader returns :class:`Keypoints`: points ``(F, K, 2)`` per frame in the file's own units
(pixels, mm, ...) and image axes, with NaN for missing points, optional confidence scores
``(F, K)``, the frame index of each row and, when the file has them, time stamps. Conversion
to a :class:`~torchconn.trajectory.Trajectory` is :mod:`.convert`'s job.

Layouts read (``docs/tracking.md`` has the details and a sample of each):

``sleap`` (``.h5`` / ``.hdf5``)
    SLEAP's analysis HDF5 export: ``tracks`` ``(n_tracks, 2, n_nodes, n_frames)`` (SLEAP's
    "matlab" order; a ``dims`` attribute, as sleap-io writes it, selects any other order),
    ``point_scores`` in the same order without the xy axis, ``node_names``, ``track_names``.
``sleap`` (``.csv``)
    SLEAP's analysis CSV: one row per instance, columns ``track, frame_idx, instance.score,
    <node>.x, <node>.y, <node>.score, ...``.
``dlc`` (``.csv``)
    DeepLabCut: header rows ``scorer``, (``individuals``,) ``bodyparts``, ``coords``
    (``x, y, likelihood``), then one row per frame whose first cell is the frame index or
    image path.
``dlc`` (``.h5``)
    The pandas HDF5 store DeepLabCut writes (key ``df_with_missing``), ``format="table"``
    (``table`` dataset, column names in the ``values_block_0_kind`` attribute) or ``"fixed"``
    (``block0_values`` with ``axis0_level*`` / ``axis0_label*``); read with h5py, no pandas.
``wcon`` (``.wcon`` / ``.json`` / ``.zip``)
    The worm tracker commons JSON: ``units`` and ``data`` records ``{id, t, x, y}`` (``x, y``
    one midline per time), optional ``ox, oy`` / ``cx, cy`` origins and ``head`` (``L``/``R``).
``points`` (``.csv`` / ``.npz``)
    A plain array of midline points per frame. CSV: one row per frame, optional header; an
    optional ``t`` (seconds) or ``frame`` column, then ``x, y`` pairs along the body (named
    ``<name>.x, <name>.y`` / ``<name>_x, <name>_y`` or unnamed). NPZ: ``points (F, K, 2)``,
    optional ``t (F,)``, ``scores (F, K)``, ``names (K,)``.
``movement`` (any file the ``movement`` package loads)
    Read with ``movement.io.load_dataset`` (SLEAP ``.slp``/``.h5``, DeepLabCut, LightningPose,
    Anipose, NWB, ...), then :func:`keypoints_from_movement`, which also takes a ``movement``
    poses dataset already in memory. Detected for files the readers above do not know.

HDF5 needs h5py (``pip install 'torchconn[tracking]'``); the ``movement`` format needs
``movement`` (``pip install 'torchconn[movement]'``).
"""

from __future__ import annotations

import importlib.util
import io
import json
import math
import pickle
import re
import warnings
import zipfile
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path

import numpy as np

from ..._files import check_file, file_kind
from .._table import first_rows, read_table

__all__ = ["Keypoints", "FORMATS", "read_tracking", "detect_format", "TrackingFormatError",
           "MissingDependencyError", "keypoints_from_movement"]

#: the formats :func:`read_tracking` knows (``movement``: through the optional ``movement``
#: package)
FORMATS = ("sleap", "dlc", "wcon", "points", "movement")


class TrackingFormatError(ValueError):
    """A tracking file that cannot be read as asked (the message names file, frame, keypoint)."""


class MissingDependencyError(ImportError, ValueError):
    """An optional dependency a file needs is not installed (a ``ValueError`` too, so that the
    commands report it as bad input with exit code 2)."""


@dataclass(frozen=True, eq=False)
class Keypoints:
    """Tracked points of one animal, as read from one file.

    Attributes:
        points: ``(F, K, 2)`` float64, file units and image axes; NaN where missing.
        names: ``K`` keypoint names, in the file's order.
        frames: ``(F,)`` int64 frame indices (strictly increasing).
        scores: ``(F, K)`` confidence scores, or None when the format has none.
        times: ``(F,)`` time stamps in seconds when the file has them, else None.
        source: the file read.
        format: one of :data:`FORMATS`.
        units: spatial unit of the points (``"px"`` for image trackers).
        head: ``"first"`` | ``"last"`` when the file says which end is the head, else None.
        info: what else the reader learned (track chosen, header, ...), for the sidecar.
    """

    points: np.ndarray
    names: tuple[str, ...]
    frames: np.ndarray
    scores: np.ndarray | None = None
    times: np.ndarray | None = None
    source: str = ""
    format: str = ""
    units: str = "px"
    head: str | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        F, K = self.points.shape[:2]
        if self.points.shape != (F, K, 2):
            raise ValueError(f"{self.source}: points must be (frames, keypoints, 2), got "
                             f"{self.points.shape}")
        if len(self.names) != K:
            raise ValueError(f"{self.source}: {K} keypoints but {len(self.names)} names")
        if self.frames.shape != (F,):
            raise ValueError(f"{self.source}: frames must be ({F},), got {self.frames.shape}")
        if self.scores is not None and self.scores.shape != (F, K):
            raise ValueError(f"{self.source}: scores must be ({F}, {K}), got {self.scores.shape}")
        if self.times is not None and self.times.shape != (F,):
            raise ValueError(f"{self.source}: times must be ({F},), got {self.times.shape}")
        if F and (np.diff(self.frames) <= 0).any():
            i = int(np.argmax(np.diff(self.frames) <= 0)) + 1
            raise TrackingFormatError(f"{self.source}: frame {int(self.frames[i])} comes after "
                                      f"frame {int(self.frames[i - 1])}; frames must increase "
                                      "(one row per frame and animal)")

    @property
    def n_frames(self) -> int:
        return self.points.shape[0]

    @property
    def n_keypoints(self) -> int:
        return self.points.shape[1]


# ============================================================================ dispatch
_SUFFIX_FORMAT = {".wcon": "wcon", ".json": "wcon", ".zip": "wcon", ".npz": "points"}


def detect_format(path: str | PathLike) -> str:
    """The format of a tracking file, from its suffix and first lines; ``"torchconn"`` for a
    trajectory CSV (docs/conventions.md: a ``theta`` or ``r<i>`` column), also under another
    suffix.

    Raises:
        TrackingFormatError: an unknown kind of file, named with what it seems to be (a folder,
            a compressed or binary file).
        FileNotFoundError, OSError: see :func:`torchconn._files.check_file`.
    """
    what = "a trajectory CSV or tracking file"
    path = check_file(path, what)
    suffix = path.suffix.lower()
    if suffix in _SUFFIX_FORMAT:
        return _SUFFIX_FORMAT[suffix]
    if suffix in (".h5", ".hdf5", ".hdf"):
        h5py = _h5py(path)
        with _open_h5(h5py, path) as f:
            if "tracks" in f and "node_names" in f:
                return "sleap"
            if "df_with_missing" in f or any(k in f for k in ("keypoints",)):
                return "dlc"
        if _movement_loads(path):
            return "movement"
        raise TrackingFormatError(
            f"{path}: an HDF5 file that is neither a SLEAP analysis export (datasets 'tracks', "
            "'node_names') nor a DeepLabCut pandas store (key 'df_with_missing')"
            f"{_MOVEMENT_HINT if _movement_missing() else ''}; pass --format to say what it is"
        )
    known = (f"expected a trajectory CSV (.csv) or a tracking file: SLEAP (.h5, .csv), "
             "DeepLabCut (.h5, .csv), WCON (.wcon, .json, .zip), points (.csv, .npz)"
             f"{_MOVEMENT_HINT if _movement_missing() else ''}; pass "
             f"--format {'|'.join(FORMATS)} for another suffix")
    if suffix not in (".csv", ".txt", ".tsv"):
        if _movement_loads(path):
            return "movement"
        with path.open("rb") as fh:
            kind = file_kind(fh.read(4096))
        if kind is not None:
            raise TrackingFormatError(f"{path}: the file is {kind}; {known}")
    try:
        cells = [[c.strip().lower() for c in row] for row in first_rows(path, what, 4)]
    except ValueError:
        if suffix in (".csv", ".txt", ".tsv"):
            raise
        cells = None
    header = cells[0] if cells else []
    if "theta" in header or any(re.fullmatch(r"r\d+", c) for c in header):
        return "torchconn"  # a trajectory CSV (read_csv names any missing column)
    if suffix not in (".csv", ".txt", ".tsv"):
        raise TrackingFormatError(
            f"{path}: unknown tracking file type {suffix or '(no suffix)'!r}; {known}")
    if cells and cells[0] and cells[0][0] == "scorer":
        return "dlc"
    if "frame_idx" in header and any(c.endswith(".x") for c in header):
        return "sleap"
    return "points"


def read_tracking(path: str | PathLike, format: str | None = None, *,
                  track: str | int | None = None) -> Keypoints:
    """Read one tracking file.

    Args:
        path: the file.
        format: one of :data:`FORMATS`, or None to detect it (:func:`detect_format`).
        track: which animal when the file holds several (SLEAP track, DeepLabCut individual,
            WCON id): a name or an index. Default: the only one, else the one with the most
            tracked points (with a warning naming the others).

    Raises:
        TrackingFormatError: naming the file (and line, frame, keypoint) for anything unreadable.
        FileNotFoundError: the file does not exist.
        ImportError: HDF5 without h5py.
    """
    path = check_file(path, "a tracking file")
    if format is None:
        format = detect_format(path)
        if format == "torchconn":
            raise TrackingFormatError(f"{path} is a trajectory CSV (t, x, y, theta, r1, ...), "
                                      "not tracking data: read it with torchconn.read_csv")
    if format not in FORMATS:
        raise TrackingFormatError(f"{path}: unknown format {format!r}; known: "
                                  f"{', '.join(FORMATS)}")
    suffix = path.suffix.lower()
    is_h5 = suffix in (".h5", ".hdf5", ".hdf")
    if format == "sleap":
        return _read_sleap_h5(path, track) if is_h5 else _read_sleap_csv(path, track)
    if format == "dlc":
        return _read_dlc_h5(path, track) if is_h5 else _read_dlc_csv(path, track)
    if format == "wcon":
        return _read_wcon(path, track)
    if format == "movement":
        return _read_movement(path, track)
    if track is not None:
        raise TrackingFormatError(f"{path}: a point-array file holds one animal and no track "
                                  f"names, so track {track!r} (--track) selects nothing; "
                                  "leave it out")
    return _read_points_npz(path) if suffix == ".npz" else _read_points_csv(path)


# ============================================================================ helpers
def _h5py(path: Path):
    try:
        import h5py
    except ImportError:
        raise MissingDependencyError(
            f"{path} is an HDF5 file, and reading HDF5 needs h5py: pip install "
            "'torchconn[tracking]' (or pip install h5py), or export CSV from the tracker"
        ) from None
    return h5py


def _open_h5(h5py, path: Path):
    try:
        return h5py.File(path, "r")
    except OSError as err:
        raise TrackingFormatError(f"{path}: not a readable HDF5 file ({err})") from None


_MOVEMENT_HINT = (", or any file the movement package loads (SLEAP .slp, NWB, Anipose, ...: "
                  "pip install 'torchconn[movement]')")


def _movement_missing() -> bool:
    return importlib.util.find_spec("movement") is None


def _movement_io(path):
    """``movement.io`` (optional: the extra ``torchconn[movement]``)."""
    try:
        import movement.io
        import movement.io.load
    except ImportError:
        raise MissingDependencyError(
            f"{path}: reading it through movement needs the movement package: pip install "
            "'torchconn[movement]' (or pip install movement)"
        ) from None
    return movement.io


def _movement_loads(path: Path) -> bool:
    """Whether the installed ``movement`` (if any) recognises the file."""
    if _movement_missing():
        return False
    try:
        _movement_io(path).load.infer_source_software(path)
    except (OSError, TypeError, ValueError):
        return False
    return True


def _decode(x) -> str:
    return x.decode("utf-8") if isinstance(x, bytes) else str(x)


def _choose_track(path: Path, names: list[str], counts: np.ndarray, track, what: str) -> int:
    """Index of the animal to read among ``names`` (``counts``: tracked points of each)."""
    if track is not None:
        if isinstance(track, str) and track in names:
            return names.index(track)
        if isinstance(track, (int, np.integer)) or (isinstance(track, str) and track.isdigit()):
            k = int(track)
            if 0 <= k < len(names):
                return k
        raise TrackingFormatError(f"{path}: no {what} {track!r}; the file has "
                                  f"{', '.join(repr(n) for n in names)}")
    if len(names) == 1:
        return 0
    k = int(np.argmax(counts))
    warnings.warn(f"{path}: {len(names)} {what}s ({', '.join(repr(n) for n in names)}); using "
                  f"{names[k]!r}, the one with the most tracked points (choose with --track)",
                  stacklevel=3)
    return k


def _nan_rows_dropped(points: np.ndarray, scores, frames: np.ndarray, times=None):
    """Drop frames where no keypoint was tracked (files list empty frames, or not)."""
    keep = np.isfinite(points).all(-1).any(-1)
    return (points[keep], None if scores is None else scores[keep], frames[keep],
            None if times is None else times[keep])


# ============================================================================ SLEAP
def _read_sleap_h5(path: Path, track) -> Keypoints:
    h5py = _h5py(path)
    with _open_h5(h5py, path) as f:
        for key in ("tracks", "node_names"):
            if key not in f:
                raise TrackingFormatError(f"{path}: no dataset {key!r}; a SLEAP analysis HDF5 "
                                          "export has 'tracks' and 'node_names'")
        raw = np.asarray(f["tracks"][()], dtype=np.float64)
        if raw.ndim != 4:
            raise TrackingFormatError(f"{path}: 'tracks' has shape {raw.shape}; expected 4 axes "
                                      "(track, xy, node, frame)")
        dims = f["tracks"].attrs.get("dims")
        if dims is not None:
            order = [str(d) for d in json.loads(_decode(dims))]
        else:  # SLEAP's original export: (track, xy, node, frame), or frame-first when untransposed
            order = (["track", "xy", "node", "frame"] if f.attrs.get("transpose", True)
                     else ["frame", "node", "xy", "track"])
        if sorted(order) != ["frame", "node", "track", "xy"]:
            raise TrackingFormatError(f"{path}: 'tracks' dims {order} are not a permutation "
                                      "of (frame, track, node, xy)")
        tracks = np.transpose(raw, [order.index(a) for a in ("frame", "track", "node", "xy")])
        scores = None
        if "point_scores" in f:
            o3 = [a for a in order if a != "xy"]
            ps = np.asarray(f["point_scores"][()], dtype=np.float64)
            scores = np.transpose(ps, [o3.index(a) for a in ("frame", "track", "node")])
        nodes = [_decode(n) for n in f["node_names"][()]]
        tnames = [_decode(n) for n in f["track_names"][()]] if "track_names" in f else []
        video = _decode(f["video_path"][()]) if "video_path" in f else ""
    F, n_tracks, K, two = tracks.shape
    if two != 2 or K != len(nodes):
        raise TrackingFormatError(f"{path}: 'tracks' has {K} nodes and {two} coordinates; "
                                  f"'node_names' lists {len(nodes)}")
    if not tnames or len(tnames) != n_tracks:
        tnames = [f"track_{i}" for i in range(n_tracks)]
    counts = np.isfinite(tracks).all(-1).sum((0, 2))
    k = _choose_track(path, tnames, counts, track, "track")
    pts, sc = tracks[:, k], (None if scores is None else scores[:, k])
    pts, sc, frames, _ = _nan_rows_dropped(pts, sc, np.arange(F, dtype=np.int64))
    return Keypoints(points=pts, names=tuple(nodes), frames=frames, scores=sc, source=str(path),
                     format="sleap", info={"track": tnames[k], "video": video})


def _read_sleap_csv(path: Path, track) -> Keypoints:
    header, rows, lines = _csv_rows(path)
    col = {c: i for i, c in enumerate(header)}
    if "frame_idx" not in col:
        raise TrackingFormatError(f"{path}: no 'frame_idx' column; a SLEAP analysis CSV has "
                                  "track, frame_idx, instance.score, <node>.x, <node>.y, ...")
    nodes = [c[:-2] for c in header if c.endswith(".x")]
    for n in nodes:
        if f"{n}.y" not in col:
            raise TrackingFormatError(f"{path}: keypoint {n!r} has a column '{n}.x' but no "
                                      f"'{n}.y'")
    if not nodes:
        raise TrackingFormatError(f"{path}: no '<node>.x' / '<node>.y' columns")
    data = _table(rows, [col["frame_idx"]], path, lines, ["frame_idx"])[:, 0]
    tracks = [r[col["track"]].strip() if "track" in col else "" for r in rows]
    tnames = sorted(set(tracks), key=tracks.index)
    xy_names = [f"{n}.{a}" for n in nodes for a in "xy"]
    xy = _table(rows, [col[c] for c in xy_names], path, lines, xy_names).reshape(
        len(rows), len(nodes), 2)
    has_scores = all(f"{n}.score" in col for n in nodes)
    sc_names = [f"{n}.score" for n in nodes]
    sc = _table(rows, [col[c] for c in sc_names], path, lines, sc_names) if has_scores else None
    tr = np.array(tracks)
    counts = np.array([np.isfinite(xy[tr == t]).all(-1).sum() for t in tnames])
    k = _choose_track(path, [t or "(untracked)" for t in tnames], counts, track, "track")
    sel = tr == tnames[k]
    frames = data[sel]
    if np.isnan(frames).any() or (frames != np.round(frames)).any():
        raise TrackingFormatError(f"{path}: 'frame_idx' must hold integer frame numbers")
    frames = frames.astype(np.int64)
    order = np.argsort(frames, kind="stable")
    lines_sel = np.asarray(lines)[sel][order]
    frames = frames[order]
    dup = np.flatnonzero(np.diff(frames) == 0)
    if dup.size:
        raise TrackingFormatError(f"{path}, line {lines_sel[dup[0] + 1]}: frame "
                                  f"{frames[dup[0]]} appears twice for track "
                                  f"{tnames[k] or '(untracked)'!r}")
    pts = xy[sel][order]
    sc = None if sc is None else sc[sel][order]
    return Keypoints(points=pts, names=tuple(nodes), frames=frames, scores=sc, source=str(path),
                     format="sleap", info={"track": tnames[k]})


def _csv_rows(path: Path, header_rows: int | None = 1):
    """Header, rows and line numbers of a tracking CSV (:func:`~torchconn.io._table.read_table`:
    separator, quoting, comments and decimal commas found from the file); ``header_rows=None``:
    one header row when the first row holds a non-number (then ``None`` when there is none)."""
    heads, rows, lines, _ = read_table(path, "a tracking CSV file", header_rows=header_rows,
                                       error=TrackingFormatError)
    if not heads and not rows:
        raise TrackingFormatError(f"{path}: the file is empty")
    if header_rows and len(heads) < header_rows:
        raise TrackingFormatError(f"{path}: the file is empty or its header is incomplete")
    if not rows:
        first = ",".join(heads[0]) if heads else ""
        raise TrackingFormatError(f"{path}: no data rows after the first line "
                                  f"{first[:60]!r}; expected a trajectory CSV (header t, x, y, "
                                  "theta, r1, ..., rd) or a tracking file")
    if header_rows is None:
        return (heads[0] if heads else None), rows, lines
    return (heads[0] if header_rows == 1 else heads), rows, lines


def _table(rows: list[list[str]], cols: list[int], path: Path, lines: list[int],
           names: list[str]) -> np.ndarray:
    """``(len(rows), len(cols))`` floats of the given columns; empty, ``nan``, ``NA`` and
    ``null`` cells are NaN. A bad cell raises an error naming its line and column."""
    if not rows:
        return np.zeros((0, len(cols)))
    raw = np.char.strip(np.asarray([[r[j] for j in cols] for r in rows], dtype=str))
    raw = np.where(np.isin(np.char.lower(raw), ["", "na", "null", "nan"]), "nan", raw)
    try:
        out = raw.astype(np.float64)
    except ValueError:
        out = None
    if out is None or np.isinf(out).any():
        for r, line in zip(rows, lines, strict=True):
            for c, name in zip(cols, names, strict=True):
                _cell(r[c], path, line, name)
        raise TrackingFormatError(f"{path}: unreadable numbers")  # pragma: no cover
    return out


def _cell(text: str, path: Path, line: int, column: str) -> float:
    s = text.strip()
    if s == "" or s.lower() in ("nan", "na", "null"):
        return math.nan
    try:
        v = float(s)
    except ValueError:
        raise TrackingFormatError(f"{path}, line {line}, column {column!r}: non-numeric value "
                                  f"{s!r}") from None
    if not math.isfinite(v):
        raise TrackingFormatError(f"{path}, line {line}, column {column!r}: infinite value {s!r}")
    return v


# ============================================================================ DeepLabCut
def _dlc_table(path: Path, levels: list[str], columns: list[tuple], values: np.ndarray,
               frames: np.ndarray, track) -> Keypoints:
    """Keypoints from DeepLabCut's column MultiIndex (scorer, [individuals,] bodyparts, coords)."""
    if "bodyparts" not in levels or "coords" not in levels:
        raise TrackingFormatError(f"{path}: column levels {levels}; DeepLabCut files have "
                                  "'bodyparts' and 'coords' (x, y, likelihood)")
    ib, ic = levels.index("bodyparts"), levels.index("coords")
    ii = levels.index("individuals") if "individuals" in levels else None
    inds = [] if ii is None else list(dict.fromkeys(c[ii] for c in columns))
    if inds:
        counts = np.array([np.isfinite(values[:, [j for j, c in enumerate(columns)
                                                   if c[ii] == ind]]).sum() for ind in inds])
        k = _choose_track(path, inds, counts, track, "individual")
        keep = [j for j, c in enumerate(columns) if c[ii] == inds[k]]
        columns, values = [columns[j] for j in keep], values[:, keep]
    parts = list(dict.fromkeys(c[ib] for c in columns))
    index = {(c[ib], c[ic]): j for j, c in enumerate(columns)}
    for p in parts:
        for a in ("x", "y"):
            if (p, a) not in index:
                raise TrackingFormatError(f"{path}: keypoint {p!r} has no {a!r} column")
    pts = np.stack([np.stack([values[:, index[(p, a)]] for a in "xy"], -1) for p in parts], 1)
    sc = (np.stack([values[:, index[(p, "likelihood")]] for p in parts], 1)
          if all((p, "likelihood") in index for p in parts) else None)
    info = {"scorer": columns[0][levels.index("scorer")] if "scorer" in levels else ""}
    if inds:
        info["individual"] = inds[k]
    order = np.argsort(frames, kind="stable")
    pts, sc, frames = pts[order], None if sc is None else sc[order], frames[order]
    pts, sc, frames, _ = _nan_rows_dropped(pts, sc, frames)
    return Keypoints(points=pts, names=tuple(parts), frames=frames, scores=sc, source=str(path),
                     format="dlc", info=info)


_FRAME_IN_NAME = re.compile(r"(\d+)(?=\D*$)")


def _frame_numbers(labels: list[str], path: Path, lines: list[int] | None = None) -> np.ndarray:
    """Frame numbers from DeepLabCut's row index: integers, or image paths ``img0042.png``."""
    out = []
    for i, lab in enumerate(labels):
        s = str(lab).strip()
        try:
            out.append(int(float(s)))
            continue
        except ValueError:
            pass
        m = _FRAME_IN_NAME.search(s)
        if m is None:
            where = f", line {lines[i]}" if lines else ""
            raise TrackingFormatError(f"{path}{where}: row label {s!r} is neither a frame number "
                                      "nor an image name with a number")
        out.append(int(m.group(1)))
    return np.asarray(out, dtype=np.int64)


def _read_dlc_csv(path: Path, track) -> Keypoints:
    _, rows, lines = _csv_rows(path, header_rows=0)
    n_head = 0
    for row in rows[:5]:
        if row[0].strip().lower() in ("scorer", "individuals", "bodyparts", "coords"):
            n_head += 1
        else:
            break
    if n_head < 3:
        raise TrackingFormatError(f"{path}: a DeepLabCut CSV starts with header rows 'scorer', "
                                  "('individuals',) 'bodyparts', 'coords'; found "
                                  f"{n_head} of them")
    heads = [[c.strip() for c in row] for row in rows[:n_head]]
    rows, lines = rows[n_head:], lines[n_head:]
    if not rows:
        raise TrackingFormatError(f"{path}: no data rows")
    levels = [h[0].lower() for h in heads]
    # a labelled-data CSV has up to three index columns (labeled-data, video, image)
    n_idx = next(j for j in range(len(heads[-1])) if heads[-1][j].lower() in ("x", "y",
                                                                             "likelihood"))
    columns = [tuple(h[j] for h in heads) for j in range(n_idx, len(heads[0]))]
    coords_level = levels.index("coords")
    columns = [tuple(c if i != coords_level else c.lower() for i, c in enumerate(col))
               for col in columns]
    values = _table(rows, list(range(n_idx, n_idx + len(columns))), path, lines,
                    ["/".join(c) for c in columns])
    frames = _frame_numbers([r[n_idx - 1] for r in rows], path, lines)
    return _dlc_table(path, levels, columns, values, frames, track)


class _NoGlobals(pickle.Unpickler):
    """Unpickle plain lists/tuples/strings only (pandas' column metadata), never code."""

    def find_class(self, module, name):
        raise TrackingFormatError(f"refusing to load {module}.{name} from an HDF5 attribute")


def _unpickle(blob) -> object:
    return _NoGlobals(io.BytesIO(bytes(blob))).load()


def _read_dlc_h5(path: Path, track) -> Keypoints:
    h5py = _h5py(path)
    with _open_h5(h5py, path) as f:
        keys = [k for k in ("df_with_missing", "keypoints") if k in f] or list(f.keys())
        if not keys:
            raise TrackingFormatError(f"{path}: an empty HDF5 file")
        g = f[keys[0]]
        if "table" in g:  # pandas format="table" (what DeepLabCut's analyze_videos writes)
            table = g["table"][()]
            names = table.dtype.names
            blocks = [n for n in names if n.startswith("values_block_")]
            if len(blocks) != 1:
                raise TrackingFormatError(f"{path}: expected one float block in the pandas table, "
                                          f"found {blocks}")
            values = np.asarray(table[blocks[0]], dtype=np.float64)
            columns = [tuple(_decode(x) for x in c)
                       for c in _unpickle(g["table"].attrs[f"{blocks[0]}_kind"])]
            info = _unpickle(g.attrs["info"]) if "info" in g.attrs else {}
            levels = [str(n) for n in info.get(1, {}).get("names", [])]
            index = table["index"]
            labels = [_decode(x) for x in index] if index.dtype.kind in "SOU" else list(index)
        elif "block0_values" in g:  # pandas format="fixed"
            n_levels = int(g.attrs.get("axis0_nlevels", 1))
            level_vals = [[_decode(x) for x in g[f"axis0_level{i}"][()]] for i in range(n_levels)]
            codes = [g[f"axis0_label{i}"][()] for i in range(n_levels)]
            columns = [tuple(level_vals[i][codes[i][j]] for i in range(n_levels))
                       for j in range(len(codes[0]))]
            levels = [_decode(g[f"axis0_level{i}"].attrs.get("name", b"")) for i in range(n_levels)]
            item_levels = [[_decode(x) for x in g[f"block0_items_level{i}"][()]]
                           for i in range(n_levels)]
            item_codes = [g[f"block0_items_label{i}"][()] for i in range(n_levels)]
            items = [tuple(item_levels[i][item_codes[i][j]] for i in range(n_levels))
                     for j in range(len(item_codes[0]))]
            block = np.asarray(g["block0_values"][()], dtype=np.float64)
            where = {c: j for j, c in enumerate(items)}
            values = block[:, [where[c] for c in columns]]
            axis1 = g["axis1"][()]
            labels = [_decode(x) for x in axis1] if axis1.dtype.kind in "SOU" else list(axis1)
        else:
            raise TrackingFormatError(f"{path}: group {keys[0]!r} is not a pandas DataFrame store "
                                      "(no 'table' or 'block0_values')")
    frames = _frame_numbers([str(x) for x in labels], path)
    return _dlc_table(path, [lv.lower() for lv in levels], columns, values, frames, track)


# ============================================================================ WCON
_TIME_UNITS = {"s": 1.0, "sec": 1.0, "second": 1.0, "seconds": 1.0, "ms": 1e-3,
               "millisecond": 1e-3, "milliseconds": 1e-3, "min": 60.0, "minute": 60.0,
               "minutes": 60.0, "h": 3600.0, "hour": 3600.0, "hours": 3600.0}


def _read_wcon(path: Path, track) -> Keypoints:
    try:
        if path.suffix.lower() == ".zip":
            with zipfile.ZipFile(path) as z:
                names = [n for n in z.namelist() if not n.endswith("/")]
                if not names:
                    raise TrackingFormatError(f"{path}: the zip archive is empty")
                doc = json.loads(z.read(names[0]).decode("utf-8"))
        else:
            doc = json.loads(path.read_text(encoding="utf-8-sig"))
    except json.JSONDecodeError as err:
        raise TrackingFormatError(f"{path}: not valid JSON (line {err.lineno}, column "
                                  f"{err.colno}: {err.msg}); WCON is JSON") from None
    except zipfile.BadZipFile as err:
        raise TrackingFormatError(f"{path}: not a readable zip archive ({err})") from None
    if not isinstance(doc, dict) or "units" not in doc or "data" not in doc:
        raise TrackingFormatError(f"{path}: a WCON file is a JSON object with 'units' and 'data'")
    units = doc["units"]
    for k in ("t", "x", "y"):
        if k not in units:
            raise TrackingFormatError(f"{path}: 'units' has no entry for {k!r}")
    t_unit = str(units["t"]).strip()
    if t_unit not in _TIME_UNITS:
        raise TrackingFormatError(f"{path}: time unit {t_unit!r} not understood; use one of "
                                  f"{', '.join(sorted(_TIME_UNITS))}")
    records = doc["data"] if isinstance(doc["data"], list) else [doc["data"]]
    by_id: dict[str, list] = {}
    for i, rec in enumerate(records):
        for k in ("id", "t", "x", "y"):
            if k not in rec:
                raise TrackingFormatError(f"{path}: data record {i} has no {k!r}")
        by_id.setdefault(str(rec["id"]), []).append(rec)
    ids = list(by_id)
    counts = np.array([sum(np.size(r["t"]) for r in by_id[i]) for i in ids])
    wid = ids[_choose_track(path, ids, counts, track, "worm id")]
    ts, xs, ys, heads = [], [], [], []
    for j, rec in enumerate(by_id[wid]):
        arrayed = isinstance(rec["t"], list)
        t = rec["t"] if arrayed else [rec["t"]]
        x = rec["x"] if arrayed else [rec["x"]]
        y = rec["y"] if arrayed else [rec["y"]]
        if len(x) != len(t) or len(y) != len(t):
            raise TrackingFormatError(f"{path}: worm {wid!r}, record {j}: {len(t)} times but "
                                      f"{len(x)} x and {len(y)} y midlines")
        n = len(t)

        def per_time(key, default, rec=rec, n=n, arrayed=arrayed):
            v = rec.get(key, default)
            return list(v) if (arrayed and isinstance(v, list)) else [v] * n

        ox, oy = per_time("ox", None), per_time("oy", None)
        cx, cy = per_time("cx", None), per_time("cy", None)
        # the origin: ox/oy, else the centroid cx/cy (WCON), else 0; JSON null -> NaN
        orig_x = np.array([a if a is not None else (b if b is not None else 0.0)
                           for a, b in zip(ox, cx, strict=True)], dtype=np.float64)
        orig_y = np.array([a if a is not None else (b if b is not None else 0.0)
                           for a, b in zip(oy, cy, strict=True)], dtype=np.float64)
        heads += per_time("head", None)
        ts.append(np.array([math.nan if v is None else v for v in t], dtype=np.float64))
        try:  # one midline length for every time: one array
            xa, ya = np.array(x, dtype=np.float64), np.array(y, dtype=np.float64)
            if xa.ndim == 1:
                xa, ya = xa[:, None], ya[:, None]
            if xa.shape != ya.shape or xa.ndim != 2:
                raise ValueError
            xs += list(xa + orig_x[:, None])
            ys += list(ya + orig_y[:, None])
        except ValueError:  # ragged: one array per time
            for k in range(n):
                xk = np.atleast_1d(np.asarray(x[k], dtype=np.float64))
                yk = np.atleast_1d(np.asarray(y[k], dtype=np.float64))
                if xk.shape != yk.shape:
                    raise TrackingFormatError(f"{path}: worm {wid!r} at t={t[k]}: {xk.size} x "
                                              f"but {yk.size} y points") from None
                xs.append(xk + orig_x[k])
                ys.append(yk + orig_y[k])
    sizes = {a.size for a in xs}
    if len(sizes) != 1:
        # midlines of varying length: resample each to the longest at equal arc length
        K = max(sizes)
        xs, ys = zip(*(_resample_polyline(a, b, K) for a, b in zip(xs, ys, strict=True)),
                     strict=True)
    K = xs[0].size
    pts = np.stack([np.stack([np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)],
                             -1) for a, b in zip(xs, ys, strict=True)])
    t = np.concatenate(ts) * _TIME_UNITS[t_unit]
    order = np.argsort(t, kind="stable")
    pts, t = pts[order], t[order]
    if np.isnan(t).any():
        raise TrackingFormatError(f"{path}: worm {wid!r} has a null time stamp")
    if (np.diff(t) <= 0).any():
        i = int(np.argmax(np.diff(t) <= 0))
        raise TrackingFormatError(f"{path}: worm {wid!r} has time {t[i + 1]:g} s twice")
    given = {h for h in heads if h in ("L", "R")}
    head = None
    if len(given) == 1:
        head = "first" if given == {"L"} else "last"
    elif len(given) > 1:
        warnings.warn(f"{path}: worm {wid!r}: 'head' switches between L and R; the converter "
                      "orders head and tail by continuity instead", stacklevel=2)
    frames = np.arange(len(t), dtype=np.int64)  # placeholder; times decide the grid
    return Keypoints(points=pts, names=tuple(f"p{i}" for i in range(K)), frames=frames,
                     times=t, source=str(path), format="wcon", units=str(units["x"]), head=head,
                     info={"id": wid, "time_unit": t_unit})


def _resample_polyline(x: np.ndarray, y: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray]:
    """``K`` points at equal arc length along the polyline ``(x, y)`` (NaN when any is NaN)."""
    if x.size < 2 or not (np.isfinite(x).all() and np.isfinite(y).all()):
        return np.full(K, np.nan), np.full(K, np.nan)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    u = np.linspace(0.0, s[-1], K)
    return np.interp(u, s, x), np.interp(u, s, y)


# ============================================================================ plain points
def _read_points_npz(path: Path) -> Keypoints:
    with path.open("rb") as fh:
        start = fh.read(8)
    if not start.startswith(b"PK"):  # an NPZ is a ZIP archive of .npy arrays
        kind = file_kind(start) or "not a ZIP archive of .npy arrays"
        raise TrackingFormatError(f"{path}: not an NPZ file ({kind}); write one with "
                                  "numpy.savez(path, points=..., t=...)")
    try:
        z = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise TrackingFormatError(f"{path}: not a readable NPZ file ({err})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise TrackingFormatError(f"{path}: a single .npy array, not an NPZ archive")
    with z:
        if "points" not in z.files:
            raise TrackingFormatError(f"{path}: no array 'points'; expected points (frames, "
                                      f"keypoints, 2)[, t (frames,)][, scores][, names]; "
                                      f"found {', '.join(z.files)}")
        pts = np.asarray(z["points"], dtype=np.float64)
        if pts.ndim != 3 or pts.shape[-1] != 2:
            raise TrackingFormatError(f"{path}: 'points' has shape {pts.shape}; expected "
                                      "(frames, keypoints, 2)")
        F, K = pts.shape[:2]
        t = np.asarray(z["t"], dtype=np.float64) if "t" in z.files else None
        sc = np.asarray(z["scores"], dtype=np.float64) if "scores" in z.files else None
        names = tuple(str(n) for n in z["names"]) if "names" in z.files else tuple(
            f"p{i}" for i in range(K))
    if t is not None and t.shape != (F,):
        raise TrackingFormatError(f"{path}: 't' has shape {t.shape}; expected ({F},)")
    if sc is not None and sc.shape != (F, K):
        raise TrackingFormatError(f"{path}: 'scores' has shape {sc.shape}; expected ({F}, {K})")
    if len(names) != K:
        raise TrackingFormatError(f"{path}: 'names' lists {len(names)} keypoints, 'points' has {K}")
    if np.isinf(pts).any():
        f_, k_ = np.argwhere(np.isinf(pts))[0][:2]
        raise TrackingFormatError(f"{path}: frame {f_}, keypoint {names[k_]!r}: infinite value")
    return Keypoints(points=pts, names=names, frames=np.arange(F, dtype=np.int64), scores=sc,
                     times=t, source=str(path), format="points", units="")


_PAIR = re.compile(r"^(.*?)[._ ]?([xy])$", re.IGNORECASE)


def _read_points_csv(path: Path) -> Keypoints:
    header, rows, lines = _csv_rows(path, header_rows=None)
    width = len(rows[0])
    tcol = fcol = None
    names: list[str] = []
    coord_cols: list[int] = []
    if header is not None:
        low = [h.lower() for h in header]
        tcol = next((i for i, h in enumerate(low) if h in ("t", "time", "time_s")), None)
        fcol = next((i for i, h in enumerate(low) if h in ("frame", "frame_idx")), None)
        rest = [i for i in range(width) if i not in (tcol, fcol)]
        if len(rest) % 2 or not rest:
            raise TrackingFormatError(f"{path}: {len(rest)} coordinate columns (header "
                                      f"{', '.join(header)}); expected x, y pairs (one pair per "
                                      "point along the body), or a trajectory CSV 't, x, y, "
                                      "theta, r1, ..., rd'")
        for a, b in zip(rest[::2], rest[1::2], strict=True):
            ma, mb = _PAIR.match(header[a]), _PAIR.match(header[b])
            if (ma and mb and ma.group(2).lower() == "x" and mb.group(2).lower() == "y"
                    and ma.group(1) == mb.group(1)):
                names.append(ma.group(1) or f"p{len(names)}")
            elif ma and mb and ma.group(2).lower() == "x" and mb.group(2).lower() == "y":
                names.append(ma.group(1) or f"p{len(names)}")
            else:
                raise TrackingFormatError(f"{path}: columns {header[a]!r}, {header[b]!r} are not "
                                          "an x, y pair; expected '<name>.x, <name>.y' (or "
                                          "'_x', '_y', or 'x1, y1, ...')")
        coord_cols = rest
    else:
        if width % 2:
            raise TrackingFormatError(f"{path}: {width} columns without a header; expected x, y "
                                      "pairs (add a header to mark a t or frame column)")
        coord_cols = list(range(width))
        names = [f"p{i}" for i in range(width // 2)]
    colname = (lambda j: header[j]) if header else (lambda j: f"column {j + 1}")
    vals = _table(rows, coord_cols, path, lines, [colname(j) for j in coord_cols])
    pts = vals.reshape(len(rows), len(names), 2)
    t = None
    frames = np.arange(len(rows), dtype=np.int64)
    if tcol is not None:
        t = _table(rows, [tcol], path, lines, [header[tcol]])[:, 0]
        if np.isnan(t).any():
            i = int(np.argmax(np.isnan(t)))
            raise TrackingFormatError(f"{path}, line {lines[i]}: empty time {header[tcol]!r}")
    elif fcol is not None:
        fr = _table(rows, [fcol], path, lines, [header[fcol]])[:, 0]
        if np.isnan(fr).any() or (fr != np.round(fr)).any():
            raise TrackingFormatError(f"{path}: column {header[fcol]!r} must hold integer frame "
                                      "numbers")
        frames = fr.astype(np.int64)
    return Keypoints(points=pts, names=tuple(names), frames=frames, times=t, source=str(path),
                     format="points", units="")


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return s.lower() in ("nan", "")


# ============================================================================ movement
#: ``movement``'s ``source_software`` -> the native format whose defaults apply (y flip, score
#: threshold); any other source converts with the plain-points defaults
_MOVEMENT_FORMAT = {"SLEAP": "sleap", "DeepLabCut": "dlc", "LightningPose": "dlc",
                    "DeepLabCut/LightningPose": "dlc"}


def _read_movement(path: Path, track) -> Keypoints:
    load = _movement_io(path).load
    try:
        ds = load.load_dataset(path)
    except (OSError, TypeError, ValueError, KeyError) as err:
        raise TrackingFormatError(f"{path}: movement could not load it ({err})") from None
    return keypoints_from_movement(ds, track, source=str(path))


def _dim(dims: tuple[str, ...], names: tuple[str, ...], source: str) -> str:
    """The one of ``names`` (a dimension's singular and plural spelling) among ``dims``."""
    for n in names:
        if n in dims:
            return n
    raise TrackingFormatError(f"{source}: 'position' has dimensions {dims}; a movement poses "
                              f"dataset has {names[0]!r} (time, space, keypoint, individual)")


def keypoints_from_movement(ds, track: str | int | None = None, *,
                            source: str | None = None) -> Keypoints:
    """The keypoints of one animal in a ``movement`` poses dataset.

    Args:
        ds: an ``xarray.Dataset`` as ``movement`` loads it: ``position`` with dimensions
            ``(time, space, keypoint, individual)`` (or the plural ``keypoints``,
            ``individuals`` of movement < 0.14), ``space`` holding ``x`` and ``y``; optional
            ``confidence (time, keypoint, individual)`` (all NaN: no scores). The ``time``
            coordinate is in frames, or in seconds when the ``fps`` attribute is set (then
            frames are ``round(time · fps)`` and the time stamps are kept).
        track: which individual (name or index); default: the only one, else the one with the
            most tracked points (with a warning naming the others).
        source: the name used in messages and reports (default: the ``source_file``
            attribute).

    Returns:
        :class:`Keypoints` with ``format`` ``"sleap"`` or ``"dlc"`` for data from SLEAP,
        DeepLabCut or LightningPose (their defaults apply in :func:`convert`), else
        ``"movement"``. Frames where no keypoint was tracked are dropped, as the native readers
        do.

    Raises:
        TypeError: ``ds`` is not an xarray Dataset with a ``position`` variable.
        TrackingFormatError: bounding boxes, 3-D poses, missing dimensions, an unknown
            individual.
    """
    if not hasattr(ds, "data_vars") or "position" not in ds.data_vars:
        raise TypeError(f"expected a movement poses dataset (an xarray.Dataset with a "
                        f"'position' variable), got {type(ds).__name__}")
    attrs = dict(ds.attrs)
    src = source or str(attrs.get("source_file") or "movement dataset")
    if attrs.get("ds_type") == "bboxes":
        raise TrackingFormatError(f"{src}: a movement dataset of bounding boxes; torchconn needs "
                                  "keypoints along the body (a poses dataset)")
    pos = ds["position"]
    dims = tuple(pos.dims)
    kdim = _dim(dims, ("keypoint", "keypoints"), src)
    idim = _dim(dims, ("individual", "individuals"), src)
    for d in ("time", "space"):
        _dim(dims, (d,), src)
    space = [str(c) for c in pos["space"].values]
    if sorted(space) != ["x", "y"]:
        raise TrackingFormatError(
            f"{src}: space coordinates {space}; torchconn needs planar poses (x, y). Select "
            "a plane first, e.g. ds.sel(space=['x', 'y'])")
    inds = [str(n) for n in pos[idim].values]
    xy = pos.sel(space=["x", "y"]).transpose(idim, "time", kdim, "space").values
    xy = np.asarray(xy, dtype=np.float64)  # (I, F, K, 2)
    counts = np.isfinite(xy).all(-1).sum((1, 2))
    k = _choose_track(src, inds, counts, track, "individual")
    points = xy[k]
    scores = None
    if "confidence" in ds.data_vars:
        conf = ds["confidence"].transpose(idim, "time", kdim).values[k]
        conf = np.asarray(conf, dtype=np.float64)
        scores = conf if np.isfinite(conf).any() else None
    t = np.asarray(ds["time"].values, dtype=np.float64)
    fps = attrs.get("fps")
    times = None
    if fps is not None and math.isfinite(float(fps)) and float(fps) > 0:
        times = t
        frames = np.rint(t * float(fps)).astype(np.int64)
    elif attrs.get("time_unit") == "seconds":
        times, frames = t, np.arange(t.size, dtype=np.int64)
    else:
        if (t != np.round(t)).any():
            raise TrackingFormatError(f"{src}: the time coordinate is in frames but holds "
                                      "non-integer values; set the dataset's fps attribute")
        frames = t.astype(np.int64)
    points, scores, frames, times = _nan_rows_dropped(points, scores, frames, times)
    software = str(attrs.get("source_software") or "")
    fmt = _MOVEMENT_FORMAT.get(software, "movement")
    return Keypoints(points=points, names=tuple(str(n) for n in pos[kdim].values),
                     frames=frames, scores=scores, times=times, source=src, format=fmt,
                     units="px" if fmt != "movement" else "",
                     info={"individual": inds[k], "movement_source_software": software})
