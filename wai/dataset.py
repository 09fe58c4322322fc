"""Datasets for learned methods: frames of random sea states rendered with their truth.

Frame ``i`` of a dataset of seed ``s`` draws its sea state from ``default_rng([s, i])``, so a
frame's parameters depend on neither the number of frames nor the workers that render them
(:func:`sample_params`). Each frame is rendered by :mod:`mitsuba_wai` on one mesh grid shared by
the whole dataset (the finest the wind range needs), and stored with:

``view``, ``view_truth``
    Camera v through the wavy and the flat water, (H, W, 3), radiance divided by the views'
    gain ``n^2`` (the object's radiance), float16.
``pattern``, ``pattern_flat``
    Camera s through the wavy and the flat water, grey (mean over channels), (Hs, Ws), float16.
``height_mm``, ``normals``
    The true surface ``z`` (ny, nx) mm and its unit normals (ny, nx, 3) on the grid ``x_mm``
    (nx,), ``y_mm`` (ny,) of the ``lab`` frame, float32.
``warp_px``
    For each camera-v pixel (col, row) of ``view``, the (col, row) of ``view_truth`` that sees
    the same object point, (H, W, 2) float32; NaN where the ray is totally reflected or misses
    (:func:`true_view_warp`). ``cv2.remap(view_truth, warp_px[..., 0], warp_px[..., 1], ...)``
    is the distorted view.
``params``
    Each frame's parameters (a compound dataset, also written to ``manifest.csv``).

The store is one HDF5 file, ``DIR/dataset.h5``, one chunk per frame and image; the attribute
``frames`` (the frames complete) is written after each frame's arrays, so an interrupted run
leaves a readable file and a rerun continues from there (:func:`write_dataset`).
"""

from __future__ import annotations

import csv
import functools
import io
import itertools
import json
import multiprocessing
import os
import platform
import subprocess
import time
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wai import dataset_store as store
from wai.dataset_store import DATASET_FILE, FORMAT, MANIFEST_FILE
from wai.threads import limit_native_threads
from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield
from wai_core.light_paths import flat_pixel_of

__all__ = [
    "ARRAYS",
    "DATASET_FILE",
    "MANIFEST_FILE",
    "DatasetSpec",
    "FrameMaker",
    "FrameParams",
    "FrameRecord",
    "Ranges",
    "frame_config",
    "read_frame",
    "read_manifest",
    "read_runs",
    "sample_params",
    "true_view_warp",
    "write_dataset",
]


# Attributes that must match for a rerun to append to an existing store.
_IDENTITY = ("format", "seed", "config", "config_json", "ranges", "spp", "size_px", "degrade")


@dataclass(frozen=True)
class Ranges:
    """The ranges frame parameters are drawn from, uniformly.

    Attributes
    ----------
    wind_speed_m_s : (float, float)
        Wind speed U at 19.5 m, m/s.
    wind_direction_deg : (float, float)
        Mean wave direction, deg from lab +x towards +y.
    time_s : (float, float)
        Time of the sea state, s.
    wave_seed : (int, int)
        The wave phases' seed, integers in ``[lo, hi)``.
    signal_level : (float, float)
        With degradations: the sensor's exposure (fraction of the full well).
    read_noise_e : (float, float)
        With degradations: the sensor's read noise, e- rms.
    """

    wind_speed_m_s: tuple[float, float] = (0.5, 2.0)
    wind_direction_deg: tuple[float, float] = (0.0, 360.0)
    time_s: tuple[float, float] = (0.0, 100.0)
    wave_seed: tuple[int, int] = (0, 2**31 - 1)
    signal_level: tuple[float, float] = (0.2, 0.8)
    read_noise_e: tuple[float, float] = (2.0, 10.0)

    def __post_init__(self) -> None:
        for f in fields(self):
            lo, hi = getattr(self, f.name)
            if not lo < hi:
                raise ValueError(f"Ranges.{f.name}: needs lo < hi, not {lo}, {hi}")
        if self.wind_speed_m_s[0] <= 0:
            raise ValueError("Ranges.wind_speed_m_s: the wind must be > 0")

    def to_json(self) -> str:
        """The ranges as the JSON the store records."""
        return json.dumps(asdict(self), sort_keys=True)


@dataclass(frozen=True)
class FrameParams:
    """The parameters of one frame (one row of the manifest).

    ``signal_level`` and ``read_noise_e`` are 0 where degradations are off.
    """

    frame: int
    wind_speed_m_s: float
    wind_direction_deg: float
    time_s: float
    wave_seed: int
    signal_level: float = 0.0
    read_noise_e: float = 0.0


def sample_params(
    seed: int, index: int, ranges: Ranges = Ranges(), degrade: bool = False
) -> FrameParams:
    """Frame ``index``'s parameters, drawn from ``default_rng([seed, index])``.

    Examples
    --------
    >>> p = sample_params(0, 3)
    >>> 0.5 <= p.wind_speed_m_s <= 2.0 and 0.0 <= p.time_s < 100.0
    True
    >>> p == sample_params(0, 3)
    True
    """
    if seed < 0:
        raise WaiInputError(f"--seed must be >= 0, not {seed}")
    if index < 0:
        raise ValueError(f"frame index must be >= 0, not {index}")
    rng = np.random.default_rng([int(seed), int(index)])
    r = ranges
    # Draw every value in a fixed order, degradations included, so turning them on does not
    # change a frame's sea state.
    wind = float(rng.uniform(*r.wind_speed_m_s))
    direction = float(rng.uniform(*r.wind_direction_deg))
    t = float(rng.uniform(*r.time_s))
    wave_seed = int(rng.integers(*r.wave_seed))
    level = float(rng.uniform(*r.signal_level))
    noise = float(rng.uniform(*r.read_noise_e))
    return FrameParams(int(index), wind, direction, t, wave_seed,
                       level if degrade else 0.0, noise if degrade else 0.0)


@dataclass(frozen=True)
class DatasetSpec:
    """What a dataset is made of (what a rerun must match to continue it).

    Attributes
    ----------
    config : str
        A packaged scene's name or a scene TOML file (:func:`wai_core.load_rig`).
    seed : int
        The dataset's seed (:func:`sample_params`).
    ranges : Ranges
    spp : int or None
        Samples per pixel of every render (None: the scene's).
    size_px : (int, int) or None
        Both cameras' (width, height), px, at the scene's field of view (None: the scene's).
    degrade : bool
        Sensor noise on, with exposure and read noise drawn per frame (:class:`Ranges`).
    """

    config: str = "paper"
    seed: int = 0
    ranges: Ranges = field(default_factory=Ranges)
    spp: int | None = None
    size_px: tuple[int, int] | None = None
    degrade: bool = False

    def base_config(self) -> SystemConfig:
        """The scene, with ``size_px`` applied to both cameras."""
        from mitsuba_wai.lens import lens_keys
        from wai_core.system import load_rig

        cfg = load_rig(self.config)
        if self.size_px is not None:
            w, h = self.size_px
            for cam in ("camera_s", "camera_v"):
                cfg = cfg.replace(cam, width_px=int(w), height_px=int(h))
        if lens_keys(cfg.camera_v):
            raise WaiInputError(f"--config {self.config}: camera v has a lens or port "
                                f"({', '.join(lens_keys(cfg.camera_v))}); the dataset's warp "
                                "is a pinhole camera's")
        return cfg

    def attrs(self, cfg: SystemConfig) -> dict[str, Any]:
        """The identity attributes of the store (``_IDENTITY``)."""
        return {
            "format": FORMAT, "seed": int(self.seed), "config": str(self.config),
            "config_json": json.dumps(cfg.to_dict(), sort_keys=True, default=str),
            "ranges": self.ranges.to_json(), "spp": int(self.spp or 0),
            "size_px": json.dumps(list(self.size_px) if self.size_px else None),
            "degrade": bool(self.degrade),
        }


def frame_config(base: SystemConfig, p: FrameParams) -> SystemConfig:
    """``base`` with frame ``p``'s sea state (and sensor, when degraded).

    Examples
    --------
    >>> from wai_core import load_system
    >>> cfg = frame_config(load_system("paper"), FrameParams(0, 1.5, 90.0, 12.0, 3))
    >>> cfg.waves.wind_speed_m_s, cfg.waves.seed, cfg.sensor.enabled
    (1.5, 3, False)
    """
    cfg = base.replace("waves", wind_speed_m_s=p.wind_speed_m_s,
                       wind_direction_deg=p.wind_direction_deg, time_s=p.time_s,
                       seed=p.wave_seed)
    if p.signal_level > 0:
        cfg = cfg.replace("sensor", enabled=True, signal_level=p.signal_level,
                          read_noise_e=p.read_noise_e)
    return cfg


def true_view_warp(cfg: SystemConfig, surface: Heightfield) -> NDArray[np.float32]:
    """Where each pixel of camera v's view through ``surface`` appears in the flat-water view.

    Each pixel's ray is traced through the true surface to the object plane (as
    :func:`wai_core.optics.trace_to_object`), and the object point is taken back to the pixel
    that sees it through flat water (:func:`wai_core.light_paths.flat_pixel_of`).

    Parameters
    ----------
    cfg : SystemConfig
    surface : Heightfield
        The true surface, absolute heights, mm.

    Returns
    -------
    (H, W, 2) ndarray of float32
        The flat-water view's (col, row) of each pixel, NaN where the ray is totally reflected
        or misses the surface or the object plane.

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core import load_system
    >>> from wai_core.heightfield import Heightfield
    >>> cfg = load_system("paper").replace("camera_v", width_px=40, height_px=30)
    >>> x = y = np.linspace(-600.0, 600.0, 9)
    >>> flat = Heightfield(x, y, np.full((9, 9), cfg.water.h0_mm))
    >>> warp = true_view_warp(cfg, flat)
    >>> cols, rows = np.meshgrid(np.arange(40.0), np.arange(30.0))
    >>> ok = np.isfinite(warp[..., 0])
    >>> bool(np.allclose(warp[ok], np.stack([cols, rows], axis=-1)[ok], atol=1e-3))
    True
    """
    fc, fr = flat_pixel_of(cfg.rig, _object_points(cfg, surface))
    return np.stack([fc, fr], axis=-1).astype(np.float32)


# Newton steps of the rays' surface hits: from the mean level, four reach the steps' rounding
# on sea waves (the default eight cost twice the time for nothing).
NEWTON_STEPS = 4


def _object_points(cfg: SystemConfig, surface: Heightfield) -> NDArray:
    """Camera v's pixels traced through ``surface`` to the object plane, (H, W, 3) mm, NaN where
    totally reflected or missed: :func:`wai_core.optics.trace_to_object` with
    :data:`NEWTON_STEPS` steps to the surface."""
    from wai_core.geometry import intersect_plane_z, refract

    cam = cfg.rig.camera_v
    origin, dirs = cam.pixel_rays(*cam.pixel_grid())
    hit, hit_ok = surface.intersect(origin, dirs, n_iter=NEWTON_STEPS)
    normals = surface.normal(hit[..., 0], hit[..., 1])
    air, tir = refract(dirs, normals, cfg.water.n_water)  # water to air (eq. 20)
    points, _ = intersect_plane_z(hit, air, cfg.object_z_mm)
    points[~hit_ok | tir | ~np.all(np.isfinite(points), axis=-1)] = np.nan
    return points


@dataclass(frozen=True)
class FrameRecord:
    """One frame of the dataset, as stored (the module notes give each array's meaning).

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


def _grid_axes(spec: DatasetSpec, base: SystemConfig) -> tuple[NDArray, NDArray]:
    """The dataset's storage grid: the wave model's mesh grid at the lowest wind of the range,
    whose waves are the shortest (as fine as any frame's mesh)."""
    from mitsuba_wai.surface_sampling import wave_surface

    grid = wave_surface(base.replace("waves", wind_speed_m_s=spec.ranges.wind_speed_m_s[0]))
    return grid.x, grid.y


def _coarser(axis: NDArray, level: int) -> NDArray:
    """``axis`` over the same span with its spacing times ``2**level`` (>= 5 samples)."""
    n = max(int(np.ceil((axis.size - 1) / 2**level)) + 1, 5)
    return np.linspace(axis[0], axis[-1], n)


class FrameMaker:
    """Renders frames of a dataset, with its scenes loaded once per mesh level.

    A frame's mesh is the storage grid (:func:`_grid_axes`) with its spacing doubled as often
    as the frame's shortest wave allows (at most its own ``mesh_points_per_wavelength``
    spacing): a few mesh levels cover the wind range, each with its renderer loaded on first
    use, so calm and windy frames both render on meshes their own size.

    Parameters
    ----------
    spec : DatasetSpec

    Examples
    --------
    >>> maker = FrameMaker(DatasetSpec(size_px=(80, 60), spp=1))     # doctest: +SKIP
    >>> maker.make(0).view.shape                                        # doctest: +SKIP
    (60, 80, 3)
    """

    def __init__(self, spec: DatasetSpec) -> None:
        self.spec = spec
        self.base = spec.base_config()
        self.x_mm, self.y_mm = _grid_axes(spec, self.base)
        self._renderers: dict[int, Any] = {}

    def surface(
        self, cfg: SystemConfig, time_s: float | None = None, level: int = 0
    ) -> Heightfield:
        """The sea state of ``cfg`` at ``time_s`` (default its own) on the storage grid, or
        on mesh ``level`` (spacing times ``2**level``)."""
        from mitsuba_wai.waves import sea_surface

        t = cfg.waves.time_s if time_s is None else time_s
        x, y = _coarser(self.x_mm, level), _coarser(self.y_mm, level)
        return sea_surface(cfg.waves).grid(x, y, t, mean_level_mm=cfg.water.h0_mm)

    def level(self, cfg: SystemConfig) -> int:
        """The coarsest mesh level whose spacing resolves ``cfg``'s shortest wave."""
        from mitsuba_wai.waves import mesh_spacing_mm, sea_surface

        span = float(max(self.x_mm[-1] - self.x_mm[0], self.y_mm[-1] - self.y_mm[0]))
        own = mesh_spacing_mm(sea_surface(cfg.waves), cfg.waves.mesh_points_per_wavelength, span)
        fine = float(max(np.diff(self.x_mm).max(), np.diff(self.y_mm).max()))
        level = 0
        while (2 ** (level + 1) * fine <= own and _coarser(self.x_mm, level + 1).size > 5
               and _coarser(self.y_mm, level + 1).size > 5):
            level += 1
        return level

    def _renderer(self, level: int, surface: Heightfield) -> Any:
        from mitsuba_wai.render import FrameRenderer

        if level not in self._renderers:
            self._renderers[level] = FrameRenderer(self.base, surface)
        return self._renderers[level]

    def render(self, index: int) -> tuple[SystemConfig, Heightfield, dict[str, NDArray], float]:
        """Frame ``index``'s configuration, true surface (on the storage grid), images and the
        views' gain: the renders of :func:`mitsuba_wai.render_frame` on the frame's mesh."""
        from mitsuba_wai.frame_images import render_frame_images
        from mitsuba_wai.render import render_seed
        from wai_core.optics import radiance_gain

        p = sample_params(self.spec.seed, index, self.spec.ranges, self.spec.degrade)
        cfg = frame_config(self.base, p)
        level = self.level(cfg)
        mesh = self.surface(cfg, level=level)

        def surface_at(t: float) -> Heightfield:
            return self.surface(cfg, t, level)

        cfg, images = render_frame_images(
            self._renderer(level, mesh), cfg, mesh, render_seed(cfg), spp=self.spec.spp,
            surface_at=surface_at if cfg.motion.exposure_s > 0 else None,
        )
        # With the sensor on, the views are its reading, already scaled by the exposure.
        gain = 1.0 if cfg.sensor.enabled else radiance_gain(cfg.water.n_water)
        # Level 0's mesh is the storage grid: the same heights, not synthesised twice.
        return cfg, mesh if level == 0 else self.surface(cfg), images, gain

    def make(self, index: int) -> FrameRecord:
        """Frame ``index``, rendered and reduced to what the store holds, with BLAS on one
        thread: idle ones would spin beside Dr.Jit's, and the sums are the same in any process."""
        from threadpoolctl import threadpool_limits

        p = sample_params(self.spec.seed, index, self.spec.ranges, self.spec.degrade)
        with threadpool_limits(1, user_api="blas"):
            cfg, surf, images, gain = self.render(index)
            return FrameRecord(
                params=p,
                view=(images["view"] / gain).astype(np.float16),
                view_truth=(images["view_truth"] / gain).astype(np.float16),
                pattern=images["pattern"].mean(axis=-1).astype(np.float16),
                pattern_flat=images["pattern_flat"].mean(axis=-1).astype(np.float16),
                height_mm=surf.z.astype(np.float32),
                normals=surf.grid_normals().astype(np.float32),
                warp_px=true_view_warp(cfg, surf),
            )


# A worker process's FrameMaker of each spec (its scenes stay loaded between frames).
_MAKERS: dict[DatasetSpec, FrameMaker] = {}


def _make_cached(spec: DatasetSpec, index: int, host_threads: dict[str, int] | None = None
                 ) -> FrameRecord:
    """Frame ``index`` of ``spec``, by this process's FrameMaker of it; on a Dask worker, with
    the native pools sized to the cores over the cluster's threads on its host."""
    if host_threads is not None:
        from distributed import get_worker
        from distributed.comm import get_address_host

        host = get_address_host(get_worker().address)
        limit_native_threads(max(1, (os.cpu_count() or 1) // host_threads.get(host, 1)))
    maker = _MAKERS[spec] if spec in _MAKERS else _MAKERS.setdefault(spec, FrameMaker(spec))
    return maker.make(index)


def _frames_on_dask(client: Any, spec: DatasetSpec, indices: Sequence[int]
                    ) -> Iterator[FrameRecord]:
    """The frames ``indices`` in order, rendered by the workers of ``client``'s cluster; a
    window of twice the workers' threads is in flight (the rest waits, not the memory)."""
    with client:
        info = [(w["host"], w["nthreads"]) for w in client.scheduler_info()["workers"].values()]
        hosts = {h: sum(n for k, n in info if k == h) for h, _ in info}
        window, todo = max(2, 2 * sum(hosts.values())), iter(indices)
        pending = deque(client.submit(_make_cached, spec, i, hosts, pure=False)
                        for i in itertools.islice(todo, window))
        while pending:
            rec = pending.popleft().result()
            for i in itertools.islice(todo, 1):
                pending.append(client.submit(_make_cached, spec, i, hosts, pure=False))
            yield rec


def _dask_client(scheduler: str) -> Any:
    try:
        from distributed import Client
        return Client(scheduler, timeout=30)
    except ModuleNotFoundError as exc:
        raise WaiInputError(f"--scheduler needs Dask's distributed ({exc})") from None
    except (OSError, TimeoutError, ValueError) as exc:
        raise WaiInputError(f"--scheduler {scheduler}: no Dask scheduler there ({exc})") from None


def _frames_in_pool(spec: DatasetSpec, indices: Sequence[int], n: int) -> Iterator[FrameRecord]:
    threads = max(1, (os.cpu_count() or 1) // n)
    with multiprocessing.get_context("spawn").Pool(n, limit_native_threads, (threads,)) as pool:
        yield from pool.imap(functools.partial(_make_cached, spec), indices)


def _frames(spec: DatasetSpec, indices: Sequence[int], workers: int, scheduler: str | None,
            maker: FrameMaker | None) -> tuple[Iterator[FrameRecord], str]:
    """The frames ``indices`` in order, rendered here (``workers`` <= 1, by ``maker``), in
    ``workers`` spawned processes or on the Dask cluster at ``scheduler``; who, in words."""
    if scheduler is not None:
        threads = (client := _dask_client(scheduler)).nthreads()
        return (_frames_on_dask(client, spec, indices),
                f"Dask {scheduler}: {len(threads)} workers, {sum(threads.values())} threads")
    if workers <= 1:
        return map((maker or FrameMaker(spec)).make, indices), "this process"
    return _frames_in_pool(spec, indices, workers), f"{workers} worker processes"


def _versions() -> dict[str, str]:
    """The software the store was written with (``git`` commit of a checkout)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version(), "numpy": np.__version__}
    for pkg in ("mitsuba", "drjit", "h5py", "wavy-water-testbed"):
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


def _open_store(path: Path, spec: DatasetSpec, cfg: SystemConfig) -> Any:
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


def _append(f: Any, rec: FrameRecord, x_mm: NDArray, y_mm: NDArray) -> None:
    """Write ``rec`` as frame ``attrs['frames']``, then count it."""
    k = int(f.attrs["frames"])
    if "x_mm" not in f:
        f.create_dataset("x_mm", data=x_mm)
        f.create_dataset("y_mm", data=y_mm)
    for name in ARRAYS:
        a = getattr(rec, name)
        if name not in f:
            f.create_dataset(name, shape=(0, *a.shape), maxshape=(None, *a.shape),
                             dtype=a.dtype, chunks=(1, *a.shape), compression="lzf")
        ds = f[name]
        ds.resize(k + 1, axis=0)
        ds[k] = a
    if "params" not in f:
        f.create_dataset("params", shape=(0,), maxshape=(None,), dtype=_PARAM_DTYPE,
                         chunks=(256,))
    f["params"].resize(k + 1, axis=0)
    f["params"][k] = tuple(getattr(rec.params, n) for n in _PARAM_DTYPE.names)
    f.flush()
    f.attrs["frames"] = k + 1  # last: a frame counts once all of it is written
    f.flush()


def _trim(f: Any) -> int:
    """Drop rows past ``attrs['frames']`` (a frame interrupted half written); the frames
    complete."""
    k = int(f.attrs["frames"])
    for name in (*ARRAYS, "params"):
        if name in f and f[name].shape[0] > k:
            f[name].resize(k, axis=0)
    return k


def _write_manifest(f: Any, path: Path) -> None:
    names = _PARAM_DTYPE.names
    rows = f["params"][: int(f.attrs["frames"])] if "params" in f else []
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(names)
    for row in rows:
        w.writerow([repr(v.item()) for v in row])
    store.write_manifest(path, buf.getvalue())


def write_dataset(
    out_dir: str | Path,
    frames: int,
    spec: DatasetSpec = DatasetSpec(),
    *,
    workers: int = 0,
    scheduler: str | None = None,
    progress: bool = True,
) -> Path:
    """Render frames ``0 .. frames - 1`` of ``spec`` into ``out_dir/dataset.h5`` and its
    ``manifest.csv``, continuing an existing store of the same spec from its frame count.

    Parameters
    ----------
    out_dir : path
        The dataset folder (created if missing).
    frames : int
        The frames the store holds when done (>= 1); fewer than it holds adds none.
    spec : DatasetSpec
    workers : int
        Processes rendering frames (spawned; 0 or 1: in this process). The store is written
        here, in frame order.
    scheduler : str, optional
        A running Dask scheduler's address (``tcp://host:8786``) whose workers render the
        frames instead (they need this package, not the store's file system).
    progress : bool
        Show a progress bar.

    Returns
    -------
    Path
        The store, ``out_dir/dataset.h5``.

    Raises
    ------
    WaiInputError
        ``out_dir`` may not be written, holds another spec, or lacks memory or disk (dataset_store).

    Examples
    --------
    >>> write_dataset("datasets/d1", 2, DatasetSpec(size_px=(80, 60), spp=1))  # doctest: +SKIP
    PosixPath('datasets/d1/dataset.h5')
    """
    from tqdm import tqdm

    if frames < 1:
        raise WaiInputError(f"--frames must be >= 1, not {frames}")
    if workers < 0:
        raise WaiInputError(f"--workers must be >= 0, not {workers}")
    if scheduler is not None and workers > 0:
        raise WaiInputError("--workers and --scheduler exclude each other: the scheduler's "
                            "workers render")
    out = Path(out_dir)
    store.check_dataset_folder(out)
    cfg = spec.base_config()
    if scheduler is None:  # a cluster's workers have their own memory
        store.check_dataset_memory(spec, cfg, max(workers, 1))
    store.mark_dataset_folder(out)
    path = out / DATASET_FILE
    f = _open_store(path, spec, cfg)
    try:
        done = _trim(f)
        todo = list(range(done, frames))
        t0 = time.perf_counter()  # the run's time: its processes' start and scene loads too
        maker = FrameMaker(spec) if todo and scheduler is None and workers <= 1 else None
        with tqdm(total=frames, initial=min(done, frames), desc="dataset", unit="frame",
                  disable=not progress) as bar:
            if todo:
                x_mm, y_mm = (maker.x_mm, maker.y_mm) if maker else _grid_axes(spec, cfg)
                made, renderers = _frames(spec, todo, workers, scheduler, maker)
                for rec in made:
                    store.reserve_space(f, sum(getattr(rec, a).nbytes for a in ARRAYS),
                                        int(f.attrs["frames"]))
                    _append(f, rec, x_mm, y_mm)
                    _write_manifest(f, out / MANIFEST_FILE)
                    bar.update(1)
                store.reserve_space(f, 0, int(f.attrs["frames"]))
                _record_run(f, done, len(todo), time.perf_counter() - t0, renderers)
        _write_manifest(f, out / MANIFEST_FILE)
    finally:
        store.close_store(f)
    return path


def _record_run(f: Any, first: int, frames: int, seconds: float, renderers: str) -> None:
    """Append a run's throughput and the reference workload's time now to ``attrs['runs']``."""
    from wai.bench.timing import reference_workload

    ref = reference_workload()
    f.attrs["runs"] = json.dumps([*json.loads(f.attrs.get("runs", "[]")), {
        "first_frame": first, "frames": frames, "seconds": round(seconds, 3),
        "frames_per_s": frames / seconds, "renderers": renderers, "cores": os.cpu_count(),
        "reference": ref["workload"], "reference_ms": ref["median_ms"]}])


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
    import h5py

    with h5py.File(Path(out_dir) / DATASET_FILE, "r") as f:
        k = int(f.attrs["frames"])
        if not 0 <= index < k:
            raise WaiInputError(f"frame {index}: the dataset holds frames 0 .. {k - 1}")
        row = f["params"][index]
        params = FrameParams(**{n: row[n].item() for n in _PARAM_DTYPE.names})
        return FrameRecord(params, *(f[name][index] for name in ARRAYS))
