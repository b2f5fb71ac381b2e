"""Writes the OME-Zarr stores other programs make, for isowall-volume's tests.

Run once (the stores are committed; written with zarr 3.1.6 and ome-zarr 0.18.0):
python3 write_foreign.py, with zarr >= 3 and ome-zarr
(pip install "zarr>=3" ome-zarr numpy). Writes, beside this script:

- foreign_v04.ome.zarr: NGFF 0.4 on Zarr v2, through ome-zarr-py with Blosc (lz4, byte
  shuffle), v2's classic compressor, and a leading `c` axis of size 1;
- foreign_v05.ome.zarr: NGFF 0.5 on Zarr v3, through ome-zarr-py, with sharded arrays
  (written by zarr-python, zstd inside the shards).

Level 0 holds int16 samples v(x, y, z) = x + 3y + 7z - 50 on 13 x 17 x 20 (x, y, z); level 1
is level 0's every other sample. Scale (z, y, x) = (2.0, 0.75, 0.5), translation (10, -4, 3).
"""
import os
import shutil

import numcodecs
import numpy as np
import zarr
from ome_zarr.format import FormatV04, FormatV05
from ome_zarr.io import parse_url
from ome_zarr.writer import write_multiscale

HERE = os.path.dirname(os.path.abspath(__file__))
NX, NY, NZ = 13, 17, 20
z, y, x = np.meshgrid(np.arange(NZ), np.arange(NY), np.arange(NX), indexing="ij")
LEVEL0 = (x + 3 * y + 7 * z - 50).astype(np.int16)
LEVELS = [LEVEL0, LEVEL0[::2, ::2, ::2]]
SCALE = [2.0, 0.75, 0.5]
TRANSLATION = [10.0, -4.0, 3.0]


def transforms(extra_axes):
    out = []
    for level in range(len(LEVELS)):
        scale = [1.0] * extra_axes + [s * 2**level for s in SCALE]
        out.append(
            [
                {"type": "scale", "scale": scale},
                {"type": "translation", "translation": [0.0] * extra_axes + TRANSLATION},
            ]
        )
    return out


def fresh(name):
    path = os.path.join(HERE, name)
    shutil.rmtree(path, ignore_errors=True)
    return path


# NGFF 0.4, Zarr v2, a `c` axis of one channel, ome-zarr's default compressor (Blosc).
path = fresh("foreign_v04.ome.zarr")
store = parse_url(path, mode="w", fmt=FormatV04()).store
root = zarr.open_group(store, mode="w", zarr_format=2)
write_multiscale(
    [lv[np.newaxis] for lv in LEVELS],
    group=root,
    axes=["c", "z", "y", "x"],
    fmt=FormatV04(),
    coordinate_transformations=transforms(1),
    storage_options={"chunks": (1, 8, 8, 8), "compressor": numcodecs.Blosc(cname="lz4", shuffle=1)},
)

# NGFF 0.5, Zarr v3, sharded: shards of 16^3 holding chunks of 8^3.
path = fresh("foreign_v05.ome.zarr")
store = parse_url(path, mode="w", fmt=FormatV05()).store
root = zarr.open_group(store, mode="w", zarr_format=3)
write_multiscale(
    LEVELS,
    group=root,
    axes=["z", "y", "x"],
    fmt=FormatV05(),
    coordinate_transformations=transforms(0),
    storage_options={"chunks": (8, 8, 8), "shards": (16, 16, 16)},
)
print("wrote", HERE)
