"""
A dataset for learned methods, and a loader for training
========================================================

``wai dataset`` writes frames with their exact truth (camera v's warp to the flat-water view,
the surface's heights and normals) into one HDF5 store, with ``manifest.csv``, ``preview.png``
and ``index.html`` beside it. Here a store of four small frames, and a loader that yields
batches of (distorted view, warp) pairs as NumPy arrays: what a PyTorch or JAX ``Dataset``
wraps.
"""

import tempfile
from pathlib import Path

import h5py
import hdf5plugin  # noqa: F401  (the store's compression filter, Blosc)
import matplotlib.pyplot as plt
import numpy as np

from wai.dataset import DatasetSpec, read_manifest, write_dataset

folder = Path(tempfile.mkdtemp()) / "d1"
write_dataset(folder, 4, DatasetSpec(size_px=(160, 120), spp=1, seed=7), progress=False)
print([p.name for p in sorted(folder.iterdir()) if not p.name.startswith(".")])
print(read_manifest(folder)[0])


def batches(store, batch_size, seed=0):
    """Shuffled batches of (view (B, H, W, 3) float32, warp (B, H, W, 2) float32)."""
    with h5py.File(store, "r") as f:
        n = int(f.attrs["frames"])
        order = np.random.default_rng(seed).permutation(n)
        for start in range(0, n, batch_size):
            idx = np.sort(order[start:start + batch_size])  # h5py reads sorted indices
            yield f["view"][idx].astype(np.float32), f["warp_px"][idx]


for views, warps in batches(folder / "dataset.h5", batch_size=2):
    print("batch", views.shape, warps.shape)

# %%
# The store's own preview: each frame's view, truth, pattern, heights and warp.
img = plt.imread(folder / "preview.png")
fig, ax = plt.subplots(figsize=(12, 9))
ax.imshow(img)
ax.set_axis_off()

plt.show()
