"""``wai restore PATH --method registration|lucky|mean``: a still scene restored from video
alone (:mod:`restoration.video`), from a video file, a folder of frames or a sequence folder,
with no ``scene.json``; writes ``restored.png``/``.exr``, its mask and ``metrics.json``."""

from __future__ import annotations

import argparse
import platform
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from wai_core.errors import WaiInputError

VIDEO_METHODS = ("registration", "lucky", "mean")
"""The image-only methods ``wai restore --method`` takes besides the per-frame ones."""


def out_folder(path: Path, method: str) -> Path:
    """Where a video's restoration by ``method`` goes by default: ``DIR/restore_METHOD`` for a
    folder, ``renders/NAME_restore_METHOD`` for a video file (never beside it: a capture's
    folder may be shared or read-only). One folder per method: restoring by another method
    never replaces a previous one's results, nor a per-frame restoration's ``DIR/restore``."""
    name = f"restore_{method}"
    return path / name if path.is_dir() else Path("renders") / f"{path.stem}_{name}"


def _views(path: Path) -> tuple[Iterator[Any], tuple[int, int, int, int], int]:
    """The frames of a sequence folder (its views, on the object's radiance scale), of a
    folder of images or of a video file, one at a time; their count, height, width and
    channels; and the bytes per frame a sequence's loader holds beside them."""
    from restoration import video
    from wai_core.sequence import is_sequence

    if path.is_dir() and is_sequence(path):
        from restoration import sequence_frames
        from wai_core.sequence import read_sequence

        cal, images = sequence_frames(path)
        (h, w), (hs, ws) = cal.image_size("view"), cal.image_size("pattern")
        views = (np.clip(cal.radiance(im["view"]), 0, 1) for im in images)
        # A sequence's frames are loaded whole: each frame's view and pattern (float32 RGB).
        return views, (len(read_sequence(path).frames), h, w, 3), 12 * (h * w + hs * ws)
    return video.iter_frames(path), video.frames_shape(path), 0


def _check_memory(path: Path, method: str, shape: tuple[int, int, int, int],
                  loader_bytes: int) -> None:
    """Refuse a registration or lucky fusion whose frames, loaded whole, would need more
    memory than is available (:func:`restoration.video.fusion_bytes`)."""
    from restoration import video
    from wai_core.memory import check_memory

    n, h, w, _ = shape
    check_memory(video.fusion_bytes(*shape) + n * loader_bytes,
                 f"{path} ({n} frames of {w} x {h} px)",
                 f"--method {method} (every frame in memory; --method mean streams them)")


def run_restore_video(args: argparse.Namespace) -> None:
    """Restore ``args.dir`` by ``args.method``; print what a person reads first."""
    import cv2

    from restoration import video
    from wai_core.io import write_exr, write_json, write_png
    from wai_core.outputs import atomic_dir, check_output_dir

    path = Path(args.dir)
    if not path.exists():
        raise WaiInputError(f"restore: no such file or folder: {path}")
    board = None
    if args.board:
        from wai.bench.capture import parse_board

        board = parse_board(args.board)
    target = Path(args.out) if args.out is not None else out_folder(path, args.method)
    check_output_dir(target, "restore", remedy="choose another --out")
    frames, shape, loader_bytes = _views(path)
    first: list[Any] = []  # the first frame as captured, for the before/after figure

    def keeping_first(it: Any) -> Any:
        for k, frame in enumerate(it):
            if k == 0:
                first.append(np.array(frame, copy=True))
            yield frame

    if args.method == "mean":
        res = video.streamed_mean(keeping_first(frames))
    else:
        _check_memory(path, args.method, shape, loader_bytes)
        run = {"registration": video.register_frames, "lucky": video.lucky_fusion}
        res = run[args.method](np.stack(list(keeping_first(frames))))
    metrics: dict[str, Any] = {
        "method": res.method, "source": str(path), "frames": int(res.frames_used),
        "ms_per_frame": float(res.ms_per_frame), "valid_fraction": float(res.valid.mean()),
        "versions": {"python": platform.python_version(), "numpy": np.__version__,
                     "opencv": cv2.__version__},
    }
    if board is not None:
        s = video.checkerboard_score(res.image, board)
        metrics["checkerboard"] = {"board": list(board), "found": bool(s.found),
                                   "rms_px": float(s.rms_px) if s.found else None}
    image = res.image if res.image.ndim == 3 else np.repeat(res.image[..., None], 3, axis=2)
    with atomic_dir(target, command="restore", remedy="choose another --out") as tmp:
        write_exr(tmp / "restored.exr", image.astype(np.float32))
        write_png(tmp / "restored.png", image, exposure=1.0)
        write_png(tmp / "restored_mask.png", (res.valid * np.uint8(255)).astype(np.uint8))
        write_json(tmp / "metrics.json", metrics)
        if first:
            from restoration.figures import side_by_side

            side_by_side([first[0], image], ["the first frame, as captured",
                                             f"restored: {res.method}, {res.frames_used} frames"],
                         tmp / "before_after.png", [None, None])
    print(f"{res.method}: {res.frames_used} frames fused in {res.ms_per_frame:.1f} ms per frame; "
          f"{metrics['valid_fraction']:.0%} of the pixels valid; wrote {target}")
    if "checkerboard" in metrics:
        c = metrics["checkerboard"]
        print("checkerboard: " + (f"corners {c['rms_px']:.3f} px (RMS) from a grid's homography"
                                  if c["found"] else "the full board is not found"))
