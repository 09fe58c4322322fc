"""``wai bench render``: wall time per frame of each scene, surface upload included."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from wai.bench.timing import (
    check_runs,
    machine,
    peak_rss_mib,
    reference_workload,
    runtime,
    summarize,
    time_runs,
)

__all__ = ["RENDER_STAGES", "bench_render", "print_render", "render_stages"]

RENDER_STAGES = {"render_s": "pattern", "render_v": "view"}
"""Report stage of each scene of :func:`bench_render` (system S: pattern, system V: view)."""


def _bench_system(cfg: Any, surface: Any, system: str, runs: int) -> dict[str, Any]:
    """Frames of one system through its own renderer: the surface upload, then the render."""
    from mitsuba_wai import FrameRenderer, flat_like, render_seed

    renderer = FrameRenderer(cfg, surface, systems=(system,))
    seed = render_seed(cfg)
    warm, samples = time_runs(
        lambda i: renderer.render(surface, seed + i + 1, which=(system,)), runs
    )
    # The upload alone (alternating surfaces, so every call really changes the mesh).
    flat = flat_like(surface, cfg.water.h0_mm)
    _, upload = time_runs(lambda i: renderer._set_surface(flat if i % 2 else surface), runs)
    cam = cfg.camera_s if system == "pattern" else cfg.camera_v
    spp = cfg.render.spp_pattern if system == "pattern" else cfg.render.spp_view
    return {
        "resolution": [cam.width_px, cam.height_px],
        "spp": spp,
        "warmup_ms": warm * 1e3,
        **summarize(samples),
        "surface_update": summarize(upload),
    }


def _bench_waves(cfg: Any, runs: int) -> dict[str, Any]:
    """The sea's heights on the scene's mesh grid (a new time each run, so every sum is done):
    by the host's matrix product, and on the renders' device (:class:`mitsuba_wai.JitWaveGrid`,
    the surface read back to the host as a dataset's worker takes it)."""
    from mitsuba_wai import JitWaveGrid, sea_surface, wave_grid_axes

    x, y = wave_grid_axes(cfg)
    sea = sea_surface(cfg.waves)
    t0, h0 = cfg.waves.time_s, cfg.water.h0_mm
    grid = JitWaveGrid(x, y)
    _, host = time_runs(lambda i: sea.grid(x, y, t0 + 0.1 * i, mean_level_mm=h0), runs)
    warm, device = time_runs(lambda i: grid.heightfield(sea, t0 + 0.1 * i, h0), runs)
    return {"vertices": int(x.size * y.size), "harmonics": sea.harmonics()[0].size,
            "host": summarize(host), "device": {"warmup_ms": warm * 1e3, **summarize(device)}}


def bench_render(config: str | Path, runs: int, variant: str = "auto") -> dict[str, Any]:
    """Wall time per frame of each scene (pattern: camera s, view: camera v).

    A frame is what a sweep pays for it: the new surface's upload (the mesh buffers, and the
    acceleration structure of each scene a render goes through; the direct tracers ask the
    water's grid, no structure) and the render, read back to a NumPy image.
    ``surface_update`` is the upload alone; ``waves`` the sea's heights on the mesh grid, by
    the host and on the renders' device.

    Parameters
    ----------
    config : str or Path
        The scene: a packaged name or a TOML file.
    runs : int
        Measured runs of each scene, after one warm-up.
    variant : str
        Mitsuba variant: ``auto`` (GPU, else LLVM), ``llvm_ad_rgb`` or ``cuda_ad_rgb``.
    """
    from mitsuba_wai import select_variant, wave_surface
    from wai_core import load_system

    check_runs(runs)
    variant = select_variant(variant)
    cfg = load_system(config)
    surface = wave_surface(cfg)
    reference = reference_workload()
    scenes = {name: _bench_system(cfg, surface, name, runs) for name in ("pattern", "view")}
    pair = scenes["pattern"]["median_ms"] + scenes["view"]["median_ms"]
    return {
        "variant": variant,
        "reference": reference,
        "frame_pair_ms": pair,
        "frame_pair_per_reference": pair / reference["median_ms"],
        "machine": machine(),
        "runtime": runtime(),
        "scenes": scenes,
        "surface_update": {"vertices": int(surface.z.size), **scenes["pattern"]["surface_update"]},
        "waves": _bench_waves(cfg, runs),
        "peak_rss_mib": peak_rss_mib(),
    }


def print_render(res: dict[str, Any]) -> None:
    print(
        f"variant {res['variant']}, {res['machine']['cores']} cores, "
        f"{res['runtime']['drjit_threads']} Dr.Jit threads"
    )
    for name, r in res["scenes"].items():
        w, h = r["resolution"]
        print(
            f"{name:8s} {w}x{h} {r['spp']:4d} spp: median {r['median_ms']:8.1f} ms/frame "
            f"(min {r['min_ms']:.1f}, max {r['max_ms']:.1f}, {r['runs']} runs; "
            f"warm-up {r['warmup_ms']:.0f} ms)"
        )
    ref = res["reference"]
    print(
        f"frame pair (pattern + view): {res['frame_pair_ms']:.0f} ms = "
        f"{res['frame_pair_per_reference']:.1f} x the reference workload ({ref['workload']}, "
        f"median {ref['median_ms']:.1f} ms in the same run)"
    )
    u = res["surface_update"]
    print(f"surface update ({u['vertices']} vertices): median {u['median_ms']:.1f} ms")
    w = res["waves"]
    print(f"waves ({w['vertices']} vertices, {w['harmonics']} harmonics): host (BLAS) median "
          f"{w['host']['median_ms']:.1f} ms, device (Dr.Jit) median "
          f"{w['device']['median_ms']:.1f} ms")
    print(f"peak RSS {res['peak_rss_mib']:.0f} MiB")


def render_stages(render: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """``render_s``/``render_v`` and their uploads from :func:`bench_render`'s scenes, and the
    wave sum by the host and on the device (``waves_host``, ``waves_device``)."""
    stages: dict[str, dict[str, Any]] = {}
    for stage, scene in RENDER_STAGES.items():
        r = render["scenes"][scene]
        summary = {k: v for k, v in r.items() if k.endswith("_ms") and k != "warmup_ms"}
        stages[stage] = {"group": "render", **summary, "runs": r["runs"]}
        stages[f"{stage}.surface_update"] = {"group": "render", **r["surface_update"]}
    # The sea's heights on the mesh grid, by the host and on the renders' device.
    waves = render["waves"]
    stages["waves_host"] = {"group": "render", **waves["host"]}
    stages["waves_device"] = {"group": "render",
                              **{k: v for k, v in waves["device"].items() if k != "warmup_ms"}}
    return stages


