"""Write the small tracking sample files the reader tests parse (run once; outputs committed).

Every file holds the same 5 frames of 3 keypoints (snout, mid, tail) in its tool's documented
layout: point k of frame f is (10 + f + 3k, 20 + 2f − k) pixels, score 0.9, except frame 2's
tail, which is missing (SLEAP: NaN; DeepLabCut: likelihood 0.1). The DeepLabCut HDF5 files are
written by pandas itself (``DataFrame.to_hdf``, as DeepLabCut does), so this script needs
pandas and PyTables; the SLEAP HDF5 file is written with h5py in SLEAP's analysis layout.
"""

import csv
import json

import h5py
import numpy as np
import pandas as pd

F, K = 5, 3
NAMES = ["snout", "mid", "tail"]
f = np.arange(F)[:, None]
k = np.arange(K)[None, :]
PTS = np.stack([10.0 + f + 3 * k, 20.0 + 2 * f - k], -1)  # (F, K, 2)
SC = np.full((F, K), 0.9)
PTS_MISSING = PTS.copy()
PTS_MISSING[2, 2] = np.nan

# SLEAP analysis HDF5: tracks (n_tracks, 2, n_nodes, n_frames), point_scores (n_tracks, n_nodes, n_frames)
with h5py.File("sleap.analysis.h5", "w") as h:
    h["tracks"] = PTS_MISSING.transpose(2, 1, 0)[None]
    ps = SC.copy()
    ps[2, 2] = np.nan
    h["point_scores"] = ps.T[None]
    h["node_names"] = np.array([n.encode() for n in NAMES])
    h["track_names"] = np.array([b"track_0"])
    h["track_occupancy"] = np.ones((F, 1), dtype=np.uint8)
    h["instance_scores"] = np.full((1, F), 0.95)
    h["video_path"] = "fish.mp4"

# SLEAP analysis CSV: track, frame_idx, instance.score, <node>.x, <node>.y, <node>.score
with open("sleap.analysis.csv", "w", newline="") as fh:
    w = csv.writer(fh)
    w.writerow(["track", "frame_idx", "instance.score"]
               + [f"{n}.{a}" for n in NAMES for a in ("x", "y", "score")])
    for i in range(F):
        row = ["track_0", i, 0.95]
        for j in range(K):
            x, y = PTS_MISSING[i, j]
            row += ["" if np.isnan(x) else x, "" if np.isnan(y) else y,
                    "" if np.isnan(x) else SC[i, j]]
        w.writerow(row)

# DeepLabCut: columns (scorer, bodyparts, coords); a lost point keeps a position, low likelihood
lik = SC.copy()
lik[2, 2] = 0.1
cols = pd.MultiIndex.from_product([["DLC_resnet50_fishJan1shuffle1_1000"], NAMES,
                                   ["x", "y", "likelihood"]],
                                  names=["scorer", "bodyparts", "coords"])
vals = np.concatenate([PTS, lik[..., None]], -1).reshape(F, K * 3)
df = pd.DataFrame(vals, columns=cols)
df.to_csv("dlc.csv")
df.to_hdf("dlc_table.h5", key="df_with_missing", format="table", mode="w")
df.to_hdf("dlc_fixed.h5", key="df_with_missing", mode="w")
# multi-animal: (scorer, individuals, bodyparts, coords); fish2 is a shifted copy
cols4 = pd.MultiIndex.from_product([["DLC_dlcrnetms5"], ["fish1", "fish2"], NAMES,
                                    ["x", "y", "likelihood"]],
                                   names=["scorer", "individuals", "bodyparts", "coords"])
vals2 = np.concatenate([PTS + 100, lik[..., None]], -1).reshape(F, K * 3)
pd.DataFrame(np.concatenate([vals, vals2], 1), columns=cols4).to_csv("dlc_multi.csv")

# WCON: units, data records {id, t, x, y}; head first ("L"); an origin offset ox, oy
doc = {"units": {"t": "s", "x": "mm", "y": "mm", "ox": "mm", "oy": "mm"},
       "metadata": {"software": {"name": "torchconn test sample"}},
       "data": [{"id": "1", "t": [i / 25 for i in range(F)], "head": "L", "ox": 1.0, "oy": -1.0,
                 "x": [[None if np.isnan(v) else v - 1.0 for v in PTS_MISSING[i, :, 0]]
                       for i in range(F)],
                 "y": [[None if np.isnan(v) else v + 1.0 for v in PTS_MISSING[i, :, 1]]
                       for i in range(F)]}]}
with open("worm.wcon", "w") as fh:
    json.dump(doc, fh, indent=1)

# plain points: CSV with a frame column and named pairs; NPZ with points, scores, names
with open("points.csv", "w", newline="") as fh:
    w = csv.writer(fh)
    w.writerow(["frame"] + [f"{n}_{a}" for n in NAMES for a in "xy"])
    for i in range(F):
        w.writerow([i] + ["nan" if np.isnan(v) else v for v in PTS_MISSING[i].reshape(-1)])
np.savez("points.npz", points=PTS_MISSING, scores=SC, names=np.array(NAMES),
         t=np.arange(F) / 25)
