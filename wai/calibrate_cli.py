"""``wai calibrate DIR`` and ``wai render --checkerboards N``: a rig's cameras calibrated from
checkerboard images (their lenses in air, their ports in the water), and such images rendered
through a scene's true lenses and ports."""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path
from typing import Any

from wai_core.errors import WaiInputError

BOARD_FILE = "board.json"
CAMERAS = ("camera_v", "camera_s")
WATER = "_water"
"""A camera's folder of board views through its port in the water: ``camera_v_water/``."""


def board_spec(cols: Any, rows: Any, square_mm: Any, source: str) -> Any:
    """A board spec from its inner corners (integers >= 3) and square size (finite, > 0 mm);
    anything else raises WaiInputError naming ``source`` (the option or the file)."""
    from restoration import BoardSpec

    def corners(v: Any) -> int | None:
        whole = isinstance(v, int | float) and not isinstance(v, bool) and float(v).is_integer()
        return int(v) if whole and v >= 3 else None

    number = isinstance(square_mm, int | float) and not isinstance(square_mm, bool)
    square = float(square_mm) if number else math.nan
    if corners(cols) is None or corners(rows) is None or not math.isfinite(square) or square <= 0:
        raise WaiInputError(f"{source}: a board needs whole numbers of inner corners >= 3 and a "
                            f"finite square size > 0 mm, not cols {cols!r}, rows {rows!r}, "
                            f"square_mm {square_mm!r}")
    return BoardSpec(int(cols), int(rows), float(square))


def parse_board(text: str, square_mm: float) -> Any:
    """``COLSxROWS`` inner corners and the square size as a board spec."""
    m = re.fullmatch(r"(\d+)x(\d+)", text.strip())
    if m is None:
        raise WaiInputError(f"--board must be COLSxROWS inner corners (>= 3 each), not {text!r}")
    return board_spec(int(m[1]), int(m[2]), square_mm, "--board and --square-mm")


def _board(args: argparse.Namespace) -> Any:
    from wai_core.io import read_json

    if args.board is not None:
        return parse_board(args.board, args.square_mm)
    path = args.dir / BOARD_FILE
    if not path.is_file():
        raise WaiInputError(f"{path}: not found; describe the board with --board COLSxROWS "
                            "--square-mm S")
    spec = read_json(path)
    if not isinstance(spec, dict) or not {"cols", "rows", "square_mm"} <= set(spec):
        raise WaiInputError(f"{path}: needs cols, rows and square_mm")
    return board_spec(spec["cols"], spec["rows"], spec["square_mm"], str(path))


def check_rig_output(path: Path) -> None:
    """Refuse, before any work, an output that cannot be written or would replace a file this
    tool did not write (a rig file without ``wai calibrate``'s ``format``)."""
    from restoration import is_written_rig
    from wai_core.outputs import check_output_file

    check_output_file(path, f"--out {path}", is_written_rig,
                      remedy="name a new file: a rig file of one's own is never replaced")


def run_calibrate(args: argparse.Namespace) -> None:
    """Calibrate every camera folder of ``args.dir`` and write the rig file ``args.out``."""
    from tqdm import tqdm

    from restoration import (
        calibrate_device,
        calibrate_port,
        rig_undetermined,
        write_rig,
    )
    from wai_core.images import read_image
    from wai_core.system import load_system

    check_rig_output(args.out)
    figures = _figures_folder(args)
    if not args.dir.is_dir():
        raise WaiInputError(f"calibration folder not found: {args.dir}")
    flat_image = None if args.flat is None else _read_flat(args.flat)
    if args.flat_tilt and args.flat is None:
        raise WaiInputError("--flat-tilt fits the projector port's tilt on --flat: give --flat")
    board = _board(args)
    cfg = load_system(args.config)
    if args.flat_tilt and not cfg.projector.port_thickness_mm > 0:
        raise WaiInputError("--flat-tilt: --config's projector has no port "
                            "([projector].port_thickness_mm is 0)")
    folders = {c: args.dir / c for c in CAMERAS if (args.dir / c).is_dir()}
    if not folders:
        raise WaiInputError(f"{args.dir}: holds no camera_v/ or camera_s/ folder of board images")
    files = {c: _images_in(f) for c, f in folders.items()}
    wet = _port_folders(args.dir, files, cfg)
    fits, views = {}, {}
    for camera, paths in tqdm(files.items(), desc="calibrate", unit="camera",
                              disable=args.quiet):
        dev = getattr(cfg, camera)
        views[camera] = [read_image(p) for p in paths]
        fits[camera] = calibrate_device(views[camera], board, (dev.height_px, dev.width_px))
    ports = {}
    for camera, paths in tqdm(wet.items(), desc="ports", unit="camera", disable=args.quiet):
        dev = getattr(cfg, camera)
        ports[camera] = calibrate_port([read_image(p) for p in paths], board, fits[camera],
                                       dev.port_thickness_mm, dev.port_n, cfg.water.n_water,
                                       (dev.height_px, dev.width_px))
    devices = {c: getattr(cfg, c) for c in fits}
    flat = None
    if args.flat is not None:
        from restoration import refine_on_flat_water, rig_keys
        from wai_core.config import with_keys

        if "camera_s" not in fits:
            raise WaiInputError("--flat refines camera s: DIR needs a camera_s/ folder")
        told = rig_keys(fits, devices)
        for name, port in ports.items():  # the cameras' ports as fitted
            told.update(port.to_config_keys(name))
        flat = refine_on_flat_water(with_keys(cfg, told), flat_image,
                                    held=_camera_s_sigmas(fits["camera_s"], ports),
                                    projector_tilt=args.flat_tilt)
    try:
        write_rig(args.out, fits, devices, board, flat, ports)
    except OSError as exc:
        raise WaiInputError(f"--out {args.out}: {exc.strerror or exc}") from None
    if figures is not None:
        _write_figures(figures, fits, views)
    for camera, fit in fits.items():
        s = fit.sigma
        k1, k2 = fit.distortion[:2]
        print(f"{camera}: fx {fit.fx_px:.2f} +- {s['fx_px']:.2f} px, cx {fit.cx_px:.2f} +- "
              f"{s['cx_px']:.2f}, cy {fit.cy_px:.2f} +- {s['cy_px']:.2f} px, k1 {k1:.4f} +- "
              f"{s['k1']:.4f}, {_k2_text(fit, k2)}; RMS {fit.rms_px:.3f} px over "
              f"{fit.n_used} views ({fit.n_rejected} without the board)")
    for camera, port in ports.items():
        (tx, ty), (sx, sy) = port.tilt_deg, port.sigma_tilt_deg
        print(f"{camera} port: gap {port.gap_mm:.3f} +- {port.sigma_gap_mm:.3f} mm behind "
              f"{port.thickness_mm:g} mm of index {port.port_n:g} (given), tilted "
              f"{tx:.2f} +- {sx:.2f}, {ty:.2f} +- {sy:.2f} deg; RMS "
              f"{port.rms_px:.3f} px over {port.n_used} views in water ({port.n_rejected} "
              f"without the board, {port.n_outliers} set aside); a pinhole's "
              f"{port.pinhole_rms_px:.3f} px")
    if flat is not None:
        f, (cx, cy) = flat.config_keys, flat.config_keys["camera_s.principal_offset_px"]
        print(f"camera_s on flat water: focal {f['camera_s.focal_mm']:.5f} +- "
              f"{flat.sigma['camera_s.focal_mm']:.5f} mm, principal "
              f"offset {cx:.2f}, {cy:.2f} px; residual "
              f"{flat.rms_before_px:.3f} -> {flat.rms_after_px:.3f} px over {flat.n_spots} "
              "spots")
        if flat.fits_projector_port:
            gap = flat.config_keys["projector.port_gap_mm"]
            print(f"projector port on flat water: gap {gap:.3f} +- "
                  f"{flat.sigma['projector.port_gap_mm']:.3f} mm behind "
                  f"{cfg.projector.port_thickness_mm:g} mm of index {cfg.projector.port_n:g} "
                  "(given)")
        if flat.fits_projector_tilt:
            tx, ty = flat.config_keys["projector.port_tilt_deg"]
            print(f"projector port tilt on flat water: {tx:.3f}, {ty:.3f} +- "
                  f"{flat.sigma['projector.port_tilt_deg']:.3f} deg")
    print("not determined: " + "; ".join(rig_undetermined(ports, flat)))
    print(f"rig file: {args.out} (wai restore DIR --rig {args.out})")
    if figures is not None:
        print(f"figures: {figures} (the corners found and reprojected, each view's error; "
              "index.html)")


def _camera_s_sigmas(fit: Any, ports: dict[str, Any]) -> list[dict[str, Any]]:
    """Camera s's lens (k1, k2) and port gap as its checkerboards left them, each one standard
    deviation up: what the flat-water fit holds (see ``refine_on_flat_water``'s ``held``)."""
    held = []
    for k, name in enumerate(("k1", "k2")):
        moved = [float(v) for v in fit.distortion]
        # A term held at zero moves as far as the views would let it move when free.
        moved[k] += float(fit.held_zero.get(name, fit.sigma[name]))
        held.append({"camera_s.distortion": moved})
    if "camera_s" in ports:
        port = ports["camera_s"]
        held.append({"camera_s.port_gap_mm": port.gap_mm + port.sigma_gap_mm})
    return held


def _k2_text(fit: Any, k2: float) -> str:
    """k2 with its deviation, and the terms the views left at zero (not determined)."""
    held = list(fit.held_zero)
    text = "k2 held at 0" if "k2" in held else f"k2 {k2:.4f} +- {fit.sigma['k2']:.4f}"
    if "p1" in held:
        text += ", p1 and p2 held at 0"
    from restoration.rig_calibration import SIGNIFICANT_SIGMAS

    return text + (f" (under {SIGNIFICANT_SIGMAS:g} deviations in the views: not determined)"
                   if held else "")


def _figures_folder(args: argparse.Namespace) -> Path | None:
    """The figures' folder (``--figures``, by default ``<rig file>_figures`` beside it; None
    with ``--no-figures``), checked before any work."""
    from wai_core.outputs import check_output_dir

    if args.no_figures:
        return None
    folder = args.figures or args.out.with_name(args.out.stem + "_figures")
    return check_output_dir(folder, "calibrate", label=f"--figures {folder}",
                            remedy="name another folder with --figures, or --no-figures")


def _write_figures(folder: Path, fits: dict[str, Any], views: dict[str, list]) -> None:
    """Each camera's calibration figure into ``folder`` (written whole, with its index.html)."""
    from restoration.figures import calibration_figure
    from wai_core.outputs import atomic_dir

    with atomic_dir(folder, command="calibrate") as tmp:
        for camera, fit in fits.items():
            calibration_figure(views[camera], fit, camera, tmp / f"{camera}.png")


def _port_folders(root: Path, files: dict[str, list[Path]], cfg: Any) -> dict[str, list[Path]]:
    """Each camera's board images through its port in the water (``root/<camera>_water/``),
    checked before any work: the camera's own folder (its lens in air) and its port's
    thickness in the configuration are needed."""
    wet = {}
    for camera in CAMERAS:
        folder = root / (camera + WATER)
        if not folder.is_dir():
            continue
        if camera not in files:
            raise WaiInputError(f"{folder}: a port is fitted with the lens calibrated in air: "
                                f"{root / camera} is needed too")
        if not getattr(cfg, camera).port_thickness_mm > 0:
            raise WaiInputError(f"{folder}: the port's thickness and index come from --config: "
                                f"set [{camera}].port_thickness_mm and port_n")
        wet[camera] = _images_in(folder)
    return wet


def _images_in(folder: Path) -> list[Path]:
    """The images of a board folder, sorted; a folder without one is refused."""
    from wai_core.images import IMAGE_SUFFIXES

    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not paths:
        raise WaiInputError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    return paths


def _read_flat(path: Path) -> Any:
    """The ``--flat`` image, read before any work."""
    from wai_core.images import read_image

    if not path.is_file():
        raise WaiInputError(f"--flat {path}: not found")
    try:
        return read_image(path)
    except WaiInputError as exc:
        raise WaiInputError(f"--flat {exc}") from None


def run_checkerboards(args: argparse.Namespace, cfg: Any) -> None:
    """Render ``args.checkerboards`` board views per camera of ``cfg`` into
    ``args.out/checkerboards/`` with ``board.json`` and the true intrinsics."""
    from tqdm import tqdm

    from mitsuba_wai import Board, check_render_memory, render_checkerboards
    from wai_core.io import write_json, write_png
    from wai_core.outputs import atomic_dir, check_output_dir

    check_output_dir(args.out, "render", args.overwrite, label=f"--out {args.out}")
    check_render_memory(cfg, str(args.config), views=args.checkerboards)
    board = Board()
    seed = cfg.waves.seed
    with atomic_dir(args.out, command="render", overwrite=args.overwrite) as tmp:
        truth: dict[str, Any] = {}
        for camera in tqdm(CAMERAS, desc="checkerboards", unit="camera", disable=args.quiet):
            folder = tmp / "checkerboards" / camera
            folder.mkdir(parents=True)
            images = render_checkerboards(cfg, camera, args.checkerboards, seed=seed,
                                          board=board)
            for k, img in enumerate(images):
                write_png(folder / f"board_{k:03d}.png", img)
            dev = getattr(cfg, camera)
            truth[camera] = {
                "fx_px": dev.focal_mm * dev.width_px / dev.sensor_width_mm,
                "cx_px": (dev.width_px - 1) / 2.0 + dev.principal_offset_px[0],
                "cy_px": (dev.height_px - 1) / 2.0 + dev.principal_offset_px[1],
                "distortion": list(dev.distortion),
            }
            if dev.port_thickness_mm > 0:  # the port, from the water, other poses
                wet = tmp / "checkerboards" / (camera + WATER)
                wet.mkdir()
                images = render_checkerboards(cfg, camera, args.checkerboards, seed=seed + 7,
                                              board=board, medium="water")
                for k, img in enumerate(images):
                    write_png(wet / f"board_{k:03d}.png", img)
                truth[camera].update(port_gap_mm=dev.port_gap_mm,
                                     port_tilt_deg=list(dev.port_tilt_deg),
                                     port_thickness_mm=dev.port_thickness_mm,
                                     port_n=dev.port_n)
        write_json(tmp / "checkerboards" / BOARD_FILE, board.to_dict())
        write_json(tmp / "scene.json", {"config": cfg.to_dict(), "seed": seed,
                                        "checkerboards": {"views": args.checkerboards,
                                                          "truth": truth}})
    print(f"checkerboards: {args.out / 'checkerboards'} (wai calibrate "
          f"{args.out / 'checkerboards'} --out rig.json)")


def add_calibrate(sub: argparse._SubParsersAction, formatter: type, scene_help: str) -> None:
    """The ``calibrate`` subcommand."""
    p = sub.add_parser(
        "calibrate", help="calibrate the cameras from checkerboard images; write a rig file",
        formatter_class=formatter,
        description="Each camera folder (DIR/camera_v/, DIR/camera_s/) holds images of a "
        "planar checkerboard in 10-20 poses, in air; OpenCV finds its corners and calibrates "
        "the camera (fx = fy, cx, cy, k1, k2, p1, p2). A camera in a housing adds a folder "
        "of the board seen through its port from the water (DIR/camera_v_water/): the gap "
        "behind the port is fitted, its thickness and index taken from --config; with "
        "--flat and a projector port in --config, the projector's gap is fitted on the "
        "flat-water spots. Writes a "
        "rig file for 'wai restore --rig'. See 'wai guide rig'.",
    )
    p.add_argument("dir", type=Path, help="folder of camera folders (and board.json)")
    p.add_argument("--out", type=Path, default=Path("rig.json"), help="rig file to write")
    p.add_argument("--config", default="paper", help=scene_help + " (image sizes and sensors)")
    p.add_argument("--board", help="inner corners COLSxROWS (default: DIR/board.json)")
    p.add_argument("--square-mm", type=float, default=20.0, help="square size with --board, mm")
    p.add_argument(
        "--flat", type=Path, default=None,
        help="the rig's flat-water pattern (pattern_flat): refine camera s's focal length and "
        "principal point on its spots, and the gap behind the projector's port when --config "
        "has one, with --config's poses and diffuser (default: none, the checkerboards' "
        "values)",
    )
    p.add_argument(
        "--flat-tilt", action="store_true",
        help="with --flat and a projector port: fit the port's tilt too, from --config's "
        "(its drawing's) within about a degree; off, the tilt is --config's (a square window: "
        "the gap and the tilt trade against each other, so fit it only for a window off "
        "square)",
    )
    p.add_argument(
        "--figures", type=Path, default=None,
        help="folder for the figures: each camera's views with the corners found and "
        "reprojected, each view's error and the error over the image (default: the rig "
        "file's name with _figures, beside it)",
    )
    p.add_argument("--no-figures", action="store_true", help="write the rig file only")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_calibrate)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    run_calibrate(args)
    return 0
