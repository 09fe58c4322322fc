"""A video's state between frames: what each frame of a sequence reuses from the previous ones.

A :class:`SequenceState` is a :class:`~restoration.calibration.LevelTrack` (the level search
starts at the previous frame's level) that also carries the last frames' labelled spots, from
which the next frame's labels are tracked (:mod:`restoration.features.track`; full matching
where tracking fails its checks), and the view's :class:`~restoration.reverse_trace.ViewState`
(each frame's warp solve starts at the previous frame's solution). Only a frame whose status
is ``ok`` passes its spots on: after any other the next frame is matched in full. Per
sequence, never per rig, and in order.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from restoration.calibration import LevelTrack
from restoration.features import Matches
from restoration.features.track import TrackedSpots
from restoration.result import RestoreResult
from restoration.reverse_trace import ViewState

__all__ = ["HISTORY", "MAX_WAIT", "TRACK_RESIDUAL", "SequenceState"]

HISTORY = 3
"""Frames of labelled spots kept (the prediction extrapolates up to three positions)."""

MAX_WAIT = 8
"""Most frames matched in full, without trying, between refused attempts to track."""

TRACK_RESIDUAL = 3.0
"""A tracked frame whose surface misses its spots by more than this many times the previous
frame's median miss (:class:`~restoration.consistency.Consistency`) is matched again in
full: labels that passed tracking's checks but are wrong in a part of the pattern give
normals that describe no surface."""


@dataclass
class SequenceState(LevelTrack):
    """A sequence's level, labelled spots and warp between frames.

    Parameters
    ----------
    track : bool
        Reuse the previous frames' spots and warp (default True); False: only the level, as
        a plain :class:`~restoration.calibration.LevelTrack` (every frame matched in full,
        every warp solved cold).

    Attributes
    ----------
    spots : tuple of TrackedSpots
        The labelled spots of the last ``ok`` frames in a row, most recent first (at most
        :data:`HISTORY`).
    view : ViewState
        The warp solve's state.
    tracked, matched : int
        Frames so far labelled by tracking, and matched in full.
    fallbacks : int
        Of the matched frames, those where tracking was tried and refused.
    residual_px : float or None
        The last ``ok`` frame's median miss of its spots, px (what a tracked frame's is
        compared with).
    skipped : int
        Frames matched in full without trying to track them, after refused attempts (see
        :meth:`next_history`).

    Examples
    --------
    >>> state = SequenceState()
    >>> state.next_history(), state.start_mm
    ((), None)
    >>> SequenceState(track=False).view_state is None
    True
    """

    track: bool = True
    spots: tuple[TrackedSpots, ...] = ()
    view: ViewState = field(default_factory=ViewState)
    tracked: int = 0
    matched: int = 0
    fallbacks: int = 0
    residual_px: float | None = None
    skipped: int = 0
    _refused: bool = field(default=False, init=False, repr=False)
    _failures: int = field(default=0, init=False, repr=False)
    _wait: int = field(default=0, init=False, repr=False)

    def next_history(self) -> tuple[TrackedSpots, ...]:
        """What the next frame's tracking starts from: empty when tracking is off, when no
        ``ok`` frame came just before, and while waiting after refused attempts (1, 3, 7
        frames after 1, 2, 3 refusals in a row, then :data:`MAX_WAIT`; where spots move too
        far between frames every attempt would be refused, and each costs a part of a full
        match). Counts down that wait: call it once per frame."""
        if not (self.track and self.spots):
            return ()
        if self._wait > 0:
            self._wait -= 1
            self.skipped += 1
            return ()
        return self.spots

    @property
    def view_state(self) -> ViewState | None:
        """The warp's state for the next frame's view, None when tracking is off."""
        return self.view if self.track else None

    def take(
        self, features: Matches | None, ok: bool, residual_px: float | None = None,
        tried: bool = False,
    ) -> None:
        """Count a frame's labelling and keep its spots, and its median miss of them
        ``residual_px``, when its status is ``ok`` (forget them otherwise, so that the next
        frame is matched in full); ``tried``: tracking was tried on it. A tracked frame that
        is not ``ok``, or whose surface misses its spots by more than :data:`TRACK_RESIDUAL`
        times the last ``ok`` frame did, is refused instead (:meth:`refuses`)."""
        self._refused = False
        if features is not None and features.counts.get("tracked"):
            prior = self.residual_px
            if not ok or (prior is not None and residual_px is not None
                          and not residual_px <= TRACK_RESIDUAL * prior):
                self._refused = True
                self.fallbacks += 1
                self.spots = ()
                self._failed()
                return
            self.tracked += 1
            self._failures = 0
        elif features is not None:
            self.matched += 1
            self.fallbacks += int(features.counts.get("track_fallback", 0))
            if tried:  # the frames before may not lead to this one: start afresh from it
                self._failed()
                self.spots = ()
        if not (ok and features is not None and self.track):
            self.spots = ()
            return
        self.spots = (TrackedSpots.of(features), *self.spots)[:HISTORY]
        self.residual_px = residual_px

    def _failed(self) -> None:
        """One more refused attempt in a row: wait longer before the next."""
        self._failures += 1
        self._wait = min(2**self._failures - 1, MAX_WAIT)

    def refuses(self, result: RestoreResult) -> bool:
        """Whether the frame just restored (``result``) was refused by :meth:`take`: restored
        from tracked labels that its surface does not bear out, it must be matched again in
        full (counted as a fallback; its full match then counts as matched)."""
        refused, self._refused = self._refused, False
        return refused and result.restored
