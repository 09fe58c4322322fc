"""The store's records: a frame's arrays and parameters appended to ``dataset.h5`` and its
manifest, and read back.

The store is one HDF5 file, ``DIR/dataset.h5``, one chunk per frame and image; the attribute
``frames`` (the frames complete) is written after each frame's arrays, so an interrupted run
leaves a readable file that a rerun continues (:func:`open_store`, :func:`trim`).

A frame's arrays are compressed where the frame is made (:class:`FramePacker`, in the worker
that rendered it) and written into the store as they are (HDF5's direct chunk writes): the
writing process only moves bytes, so it does not bound how many workers a store can take.

The compression is Blosc's LZ4 after a byte shuffle (:func:`filters`), a filter HDF5 reads
through ``hdf5plugin``: a reader of the store imports it before reading the arrays
(``import hdf5plugin``), as :func:`read_frame` does.
"""

from __future__ import annotations

import csv
import io
import json
import platform
import subprocess
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wai.dataset import store
from wai.dataset.spec import DatasetSpec, FrameParams
from wai.dataset.store import DATASET_FILE, FORMAT, FORMAT_FAMILY
from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError

__all__ = ["ARRAYS", "FramePacker", "FrameRecord", "PackedFrame", "append",
           "filters", "h5_file", "open_store", "read_frame", "read_manifest", "read_runs",
           "rewrite_manifest", "trim"]


# Attributes that must match for a rerun to append to an existing store.
_IDENTITY = ("format", "seed", "config", "config_json", "ranges", "spp", "size_px", "degrade")


@dataclass(frozen=True)
class FrameRecord:
    """One frame of the dataset, as stored (:mod:`wai.dataset` gives each array's meaning).

    Attributes
    ----------
    params : FrameParams
    view, view_truth : (H, W, 3) ndarray of float16
    pattern, pattern_flat : (Hs, Ws) ndarray of float16
    height_mm : (ny, nx) ndarray of float32
    normals : (ny, nx, 3) ndarray of float32
    warp_px : (H, W, 2) ndarray of float32
    """

    params: FrameParams
    view: NDArray[np.float16]
    view_truth: NDArray[np.float16]
    pattern: NDArray[np.float16]
    pattern_flat: NDArray[np.float16]
    height_mm: NDArray[np.float32]
    normals: NDArray[np.float32]
    warp_px: NDArray[np.float32]


ARRAYS = ("view", "view_truth", "pattern", "pattern_flat", "height_mm", "normals", "warp_px")
"""The per-frame datasets of the store, in :class:`FrameRecord`'s order."""


def filters() -> dict[str, Any]:
    """The HDF5 filter of every per-frame array (``h5py.create_dataset``'s keywords): Blosc's
    LZ4 at level 5 after a byte shuffle, which puts the floats' exponents and high bytes
    together. On a frame of the paper's size it makes the arrays as small as LZF after the
    same shuffle did (5.96 against 5.84 MB) in a seventh of the time (12 against 80 ms on
    one core); the filter is ``hdf5plugin``'s, registered by importing it."""
    import hdf5plugin

    return dict(**hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE))


def h5_file(path: str | Path, mode: str = "r") -> Any:
    """``h5py.File(path, mode)`` with the store's compression filter registered."""
    import h5py
    import hdf5plugin  # noqa: F401  (registers the filter)

    return h5py.File(path, mode)

_SHARED = ("pattern_flat", "view_truth")
# The arrays frames may share (the flat-water renders, without the sensor's noise): their
# chunk is compressed once while they stay the same.


@dataclass(frozen=True)
class PackedFrame:
    """A frame's arrays as the store's compressed chunks (:class:`FramePacker`).

    Attributes
    ----------
    params : FrameParams
    chunks : dict
        Per array of :data:`ARRAYS`: its shape, dtype (``numpy`` string), HDF5 filter mask and
        compressed bytes (:func:`filters`).
    """

    params: FrameParams
    chunks: dict[str, tuple[tuple[int, ...], str, int, bytes]]

    @property
    def nbytes(self) -> int:
        """The compressed bytes of the frame's arrays."""
        return sum(len(chunk[3]) for chunk in self.chunks.values())


class FramePacker:
    """Compresses frames into the store's chunks (:func:`filters`), by HDF5 itself in a file
    held in memory, so the bytes are the ones the store's own filters would write.

    Examples
    --------
    >>> import numpy as np
    >>> from wai.dataset.spec import FrameParams
    >>> z16, z32 = np.zeros((6, 8, 3), np.float16), np.zeros((5, 4), np.float32)
    >>> rec = FrameRecord(FrameParams(0, 1.0, 0.0, 0.0, 1), z16, z16, z16[..., 0], z16[..., 0],
    ...                   z32, np.zeros((5, 4, 3), np.float32), np.zeros((6, 8, 2), np.float32))
    >>> packed = FramePacker().pack(rec)
    >>> packed.chunks["height_mm"][:2], packed.nbytes < 8 * 6 * 8 * 3
    (((5, 4), '<f4'), True)
    """

    def __init__(self) -> None:
        self._file: Any = None
        self._last: dict[str, tuple[NDArray, tuple[tuple[int, ...], str, int, bytes]]] = {}

    def pack(self, rec: FrameRecord) -> PackedFrame:
        """``rec``'s arrays compressed."""
        chunks = {}
        for name in ARRAYS:
            a = np.ascontiguousarray(getattr(rec, name))
            last = self._last.get(name)  # only the arrays frames may share are kept
            if last is not None and last[0].dtype == a.dtype and np.array_equal(last[0], a):
                chunks[name] = last[1]
                continue
            chunks[name] = self._compress(name, a)
            if name in _SHARED:
                self._last[name] = (a.copy(), chunks[name])
        return PackedFrame(rec.params, chunks)

    def _compress(self, name: str, a: NDArray) -> tuple[tuple[int, ...], str, int, bytes]:
        if self._file is None:
            self._file = h5_file(io.BytesIO(), "w")
        key = f"{name}/{a.dtype.str}/{'x'.join(map(str, a.shape))}"
        if key not in self._file:
            self._file.create_dataset(key, shape=(1, *a.shape), dtype=a.dtype,
                                      chunks=(1, *a.shape), **filters())
        ds = self._file[key]
        ds[0] = a
        mask, data = ds.id.read_direct_chunk((0,) * ds.ndim)
        return a.shape, a.dtype.str, int(mask), bytes(data)

def _versions() -> dict[str, str]:
    """The software the store was written with (``git`` commit of a checkout)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version(), "numpy": np.__version__}
    for pkg in ("mitsuba", "drjit", "h5py", "hdf5plugin", "wavy-water-testbed"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "unknown"
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent,
                                capture_output=True, text=True, timeout=10, check=False)
        out["git_commit"] = commit.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        out["git_commit"] = "unknown"
    return out


_PARAM_DTYPE = np.dtype([(f.name, np.int64 if f.type in ("int", int) else np.float64)
                         for f in fields(FrameParams)])


def open_store(path: Path, spec: DatasetSpec, cfg: SystemConfig) -> Any:
    """The store at ``path``, opened to append: created, or an existing one of ``spec``
    (refusing a file this module did not write or one of another dataset)."""
    import h5py

    want = spec.attrs(cfg)
    if not path.exists():
        versions = json.dumps(_versions(), sort_keys=True)
        return store.create_store(path, {**want, "versions": versions, "frames": 0})
    # Checked read-only: a file that is refused is not touched.
    try:
        with h5py.File(path, "r") as f:
            attrs = {k: _plain(f.attrs.get(k)) for k in _IDENTITY}
    except OSError:
        raise WaiInputError(f"--out {path.parent}: {path.name} exists and is not an HDF5 "
                            "file of wai dataset") from None
    if str(attrs["format"]).startswith(FORMAT_FAMILY) and attrs["format"] != FORMAT:
        raise WaiInputError(f"--out {path.parent}: holds a dataset of format {attrs['format']}; "
                            f"this version writes {FORMAT} and continues only those: choose "
                            "another --out")
    if attrs["format"] != FORMAT:
        raise WaiInputError(f"--out {path.parent}: {path.name} exists and is not a store of "
                            "wai dataset")
    differ = [k for k in _IDENTITY if attrs[k] != _plain(want[k])]
    if differ:
        raise WaiInputError(f"--out {path.parent}: holds a dataset of other "
                            f"{', '.join(differ)}; choose another --out to make this one")
    return h5py.File(path, "a")


def _plain(value: Any) -> Any:
    return value.item() if isinstance(value, np.generic) else value


def append(f: Any, rec: PackedFrame, x_mm: NDArray, y_mm: NDArray) -> None:
    """Write ``rec`` as frame ``attrs['frames']``, then count it."""
    k = int(f.attrs["frames"])
    if "x_mm" not in f:
        f.create_dataset("x_mm", data=x_mm)
        f.create_dataset("y_mm", data=y_mm)
    for name in ARRAYS:
        shape, dtype, mask, data = rec.chunks[name]
        if name not in f:
            f.create_dataset(name, shape=(0, *shape), maxshape=(None, *shape),
                             dtype=np.dtype(dtype), chunks=(1, *shape), **filters())
        ds = f[name]
        if ds.shape[1:] != tuple(shape) or ds.dtype != np.dtype(dtype):
            raise ValueError(f"{name}: a frame of {shape} {dtype} in a store of "
                             f"{ds.shape[1:]} {ds.dtype}")
        ds.resize(k + 1, axis=0)
        ds.id.write_direct_chunk((k,) + (0,) * len(shape), data, mask)
    if "params" not in f:
        f.create_dataset("params", shape=(0,), maxshape=(None,), dtype=_PARAM_DTYPE,
                         chunks=(256,))
    f["params"].resize(k + 1, axis=0)
    f["params"][k] = tuple(getattr(rec.params, n) for n in _PARAM_DTYPE.names)
    f.flush()
    f.attrs["frames"] = k + 1  # last: a frame counts once all of it is written
    f.flush()


def trim(f: Any) -> int:
    """Drop rows past ``attrs['frames']`` (a frame interrupted half written); the frames
    complete."""
    k = int(f.attrs["frames"])
    for name in (*ARRAYS, "params"):
        if name in f and f[name].shape[0] > k:
            f[name].resize(k, axis=0)
    return k


def rewrite_manifest(f: Any, path: Path) -> None:
    """Write the manifest at ``path`` anew from the frames the open store ``f`` holds."""
    names = _PARAM_DTYPE.names
    rows = f["params"][: int(f.attrs["frames"])] if "params" in f else []
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(names)
    for row in rows:
        w.writerow([repr(v.item()) for v in row])
    store.write_manifest(path, buf.getvalue())


def read_runs(out_dir: str | Path) -> list[dict[str, Any]]:
    """The runs that wrote a dataset folder's frames, oldest first (keys: docs/dataset.md).

    >>> read_runs("datasets/d1")[-1]["frames_per_s"]   # doctest: +SKIP
    0.146
    """
    import h5py

    with h5py.File(Path(out_dir) / DATASET_FILE, "r") as f:
        return list(json.loads(f.attrs.get("runs", "[]")))


def read_manifest(out_dir: str | Path) -> list[FrameParams]:
    """The frames' parameters of a dataset folder, from its store."""
    import h5py

    with h5py.File(Path(out_dir) / DATASET_FILE, "r") as f:
        k = int(f.attrs["frames"])
        rows = f["params"][:k] if "params" in f else []
        return [FrameParams(**{n: r[n].item() for n in _PARAM_DTYPE.names}) for r in rows]


def read_frame(out_dir: str | Path, index: int) -> FrameRecord:
    """Frame ``index`` of a dataset folder.

    Examples
    --------
    >>> rec = read_frame("datasets/d1", 0)          # doctest: +SKIP
    >>> rec.warp_px.shape                           # doctest: +SKIP
    (60, 80, 2)
    """
    with h5_file(Path(out_dir) / DATASET_FILE) as f:
        k = int(f.attrs["frames"])
        if not 0 <= index < k:
            raise WaiInputError(f"frame {index}: the dataset holds frames 0 .. {k - 1}")
        row = f["params"][index]
        params = FrameParams(**{n: row[n].item() for n in _PARAM_DTYPE.names})
        return FrameRecord(params, *(f[name][index] for name in ARRAYS))
