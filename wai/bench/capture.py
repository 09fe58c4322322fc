"""``wai bench capture``: the image-only baselines on a real capture of a planar checkerboard.

No truth exists for a real capture; a planar board seen by a fixed camera gives one anyway:
its undistorted corners lie on a homography of a regular grid
(:func:`restoration.video.checkerboard_score`). The raw frames, their temporal mean and each
baseline's fused image are scored so. The water distorts the raw frames beyond what the
corner detector accepts, so their corners are followed from the best fused image's
(:func:`restoration.video.track_corners`); the mean, too blurred for the full board, is scored
on the corners of the largest board the detector finds in it, and each fused image on the
same corners.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from wai.bench import parse_pair
from wai.bench.timing import machine, reference_workload
from wai_core.errors import WaiInputError

SAME_CORNER_PX = 8.0
"""A fused image's corner and the mean's are the same corner within this distance, px."""


def parse_board(text: str) -> tuple[int, int]:
    """``"8x6"``: inner corners (columns, rows); one-line error naming ``--board``."""
    return parse_pair(text, "--board", "COLSxROWS inner corners", 2, "inner corners")


def _on_mean_corners(score: Any, mean: Any, board: tuple[int, int]) -> float | None:
    """``score``'s (a full ``board``'s) grid residual on the corners it shares with the
    mean's partial board."""
    from restoration import video

    if not (score.found and mean.found):
        return None
    d = np.linalg.norm(score.corners[:, None] - mean.corners[None], axis=2)
    same = d.min(axis=1) < SAME_CORNER_PX
    if same.sum() != len(mean.corners):
        return None
    return float(video.grid_residual_px(score.corners, board, same))


def _mean_partial(image: np.ndarray, board: tuple[int, int]) -> tuple[Any, tuple[int, int]]:
    """The largest board, one row or column short at a time, the detector finds in the
    blurred mean."""
    from restoration import video

    cols, rows = board
    for size in ((cols, rows), (cols, rows - 1), (cols - 1, rows), (cols - 1, rows - 1)):
        s = video.checkerboard_score(image, size)
        if s.found:
            return s, size
    return s, board


def bench_capture(video: str | Path, board: tuple[int, int]) -> dict[str, Any]:
    """Score the raw frames, the temporal mean and each baseline on ``video``."""
    import restoration as rs

    video = Path(video)
    if not video.exists():
        raise WaiInputError(f"--video {video}: no such file or folder")
    frames = rs.video.read_frames(video)
    reference = reference_workload()
    fused = {"mean": rs.video.temporal_mean(frames),
             "registration": rs.video.register_frames(frames),
             "lucky": rs.video.lucky_fusion(frames)}
    scores = {k: rs.video.checkerboard_score(v.image, board) for k, v in fused.items()}
    mean_part, part_board = _mean_partial(fused["mean"].image, board)
    rows = []
    for name, res in fused.items():
        s = scores[name]
        on_mean = (float(mean_part.rms_px) if name == "mean" and mean_part.found
                   else _on_mean_corners(s, mean_part, board))
        rows.append({"input": name, "board_found": bool(s.found),
                     "rms_px": float(s.rms_px) if s.found else None,
                     "rms_on_mean_corners_px": on_mean, "ms_per_frame": res.ms_per_frame,
                     "valid_fraction": float(res.valid.mean())})
    raw_found = sum(rs.video.checkerboard_score(f, board).found for f in frames)
    best = min((k for k in scores if scores[k].found), key=lambda k: scores[k].rms_px,
               default=None)
    raw = {"input": "raw frames", "board_found_frames": int(raw_found), "frames": len(frames)}
    if best is not None:
        tracked = rs.video.track_corners(frames, scores[best].corners, board)
        kept = np.isfinite(tracked[..., 0])
        raw.update(tracked_from=best, corners_kept=float(kept.mean()),
                   rms_px=float(np.nanmedian([rs.video.grid_residual_px(c, board)
                                              for c in tracked])),
                   stability_px=float(rs.video.stability_px(list(tracked))))
    return {"video": str(video), "frames": len(frames), "shape": list(frames.shape[1:3]),
            "board": list(board), "mean_partial_board": list(part_board),
            "machine": machine(), "reference": reference, "raw": raw, "rows": rows}


def print_capture(res: dict[str, Any]) -> None:
    """The table of :func:`bench_capture`."""
    def f(v: Any, spec: str = ".3f") -> str:
        return "-" if v is None else format(v, spec)

    raw = res["raw"]
    print(f"{res['video']}: {res['frames']} frames {res['shape'][1]}x{res['shape'][0]}, board "
          f"{res['board'][0]}x{res['board'][1]} inner corners; reference workload "
          f"{res['reference']['median_ms']:.1f} ms")
    print(f"raw frames: full board found in {raw['board_found_frames']}/{raw['frames']}; "
          f"corners followed from the {raw.get('tracked_from')} image: kept "
          f"{f(raw.get('corners_kept'), '.0%')}, median grid residual "
          f"{f(raw.get('rms_px'))} px, frame-to-frame motion {f(raw.get('stability_px'))} px")
    pb = res["mean_partial_board"]
    print(f"{'input':14s} {'board':>6s} {'grid rms px':>12s} {f'on the mean {pb[0]}x{pb[1]}':>16s}"
          f" {'ms/frame':>9s} {'valid':>6s}")
    for r in res["rows"]:
        print(f"{r['input']:14s} {str(r['board_found']):>6s} {f(r['rms_px']):>12s} "
              f"{f(r['rms_on_mean_corners_px']):>16s} {r['ms_per_frame']:9.1f} "
              f"{r['valid_fraction']:6.1%}")
