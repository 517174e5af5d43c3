"""Recording levels: which frames of a run get full detail in the .rrd (plvo_app.level_sizes measures their bytes).

Every level keeps the whole-run picture at full length (camera pose, keyframes, graph with zeta, loops, timings and
counts, the decision log, the map at keyframes, thinned) and, on every keyframe, its scan and camera image thinned
to a few kB (so that a replay shows the road everywhere, not only where the detail is), and the list of the frames
that got detail and why (written on close: what a viewer offers to jump to). Detail (the image with every overlay,
raw and merged segments, the projected scan and patches, planes, fitted lines, full map snapshots) is kept:

- summary: only in the windows the user names (`--detail A:B`);
- default: also on every `keyframe_stride`-th keyframe and in windows around events: tracking lost or
  re-initialised, a loop accepted or rejected after geometric verification, a discarded optimisation (a warning
  of the pipeline), a large correction of a keyframe by the back end, a slow frame (at most `max_event_windows`
  windows, `max_windows_per_kind` of each kind: the detail of a long run is bounded, the summary grows with it);
- full: on every frame (as before levels existed), with the keyframes' scans as 3D points too (the other levels
  have the thin ones only).

An event is known only once it happened, so the detail of the last `before` frames is held back in memory and
written when an event wants it (else dropped): a window reaches `before` frames back and `after` frames forward.
"""

from __future__ import annotations

import logging
import statistics
from collections import deque
from dataclasses import dataclass
from typing import Any

from plvo.errors import RecordingError

log = logging.getLogger(__name__)

LEVELS = ("summary", "default", "full")
LATE_FRAMES = 16  # the back end and loop closer hand a keyframe's results back within this many frames


@dataclass(frozen=True)
class DetailOptions:
    level: str = "default"
    windows: tuple[tuple[int, int], ...] = ()  # the user's --detail A:B windows (B exclusive), frame numbers
    keyframe_stride: int = 100  # default level: full detail on keyframes 0, 100, 200...
    before: int = 3  # frames of detail before an event
    after: int = 3  # and after it
    max_event_windows: int = 10  # events past this many windows are still in the log, without detail...
    max_windows_per_kind: int = 3  # ...and past this many of one kind, so near-miss loops leave room for a loss
    loop_min_inliers: int = 10  # a rejected loop candidate is an event once it got this far in verification
    slow_factor: float = 4.0  # a frame slower than this x the running mean is an event...
    slow_min_frames: int = 30  # ...once this many frames give the mean
    large_correction_m: float = 2.0  # a back-end step moving a keyframe further than this is an event

    def __post_init__(self) -> None:
        if self.level not in LEVELS:
            raise RecordingError(f"recording level {self.level!r}: choose one of {', '.join(LEVELS)}")


def parse_window(text: str) -> tuple[int, int]:
    """'A:B' -> (A, B), B exclusive; a PlvoError naming the text otherwise."""
    parts = text.strip().split(":")
    try:
        a, b = (int(p) for p in parts)
    except ValueError:
        raise RecordingError(f"window {text!r}: expected A:B with frame numbers A < B, e.g. 1200:1300") from None
    if a < 0 or b <= a:
        raise RecordingError(f"window {text!r}: expected A:B with frame numbers 0 <= A < B")
    return a, b


class DetailPolicy:
    """Decides, frame by frame, whether detail is written; holds back the detail of the last frames.

    The recorder calls `want(frame)` before writing a detail entity: True writes it now, False hands it to
    `defer(frame, item)`. `keyframe`, `event` and `slow` open windows; `end_frame` drops what no event can still
    want. `take(frames)` returns the held-back items of frames that became detail (the recorder writes them).
    """

    def __init__(self, opt: DetailOptions):
        self.opt = opt
        self._open: list[tuple[int, int]] = list(opt.windows)  # [a, b) windows of detail
        # every window opened, with why: what the recording's list of detail frames names (see detail_runs)
        self.windows: list[tuple[int, int, str]] = [(a, b, f"--detail {a}:{b}") for a, b in opt.windows]
        self._held: dict[int, list[Any]] = {}
        self._order: deque[int] = deque()
        self._n_keyframes = 0
        self._intervals: deque[float] = deque(maxlen=200)  # seconds between step ends (timing)
        self.n_event_windows = 0
        self._per_kind: dict[str, int] = {}
        self.events: list[tuple[int, str]] = []  # (frame, why) of every event, whether it got detail or not

    @property
    def everything(self) -> bool:
        return self.opt.level == "full"

    def want(self, frame: int) -> bool:
        return self.everything or any(a <= frame < b for a, b in self._open)

    def defer(self, frame: int, item: Any) -> None:
        if frame not in self._held:
            self._held[frame] = []
            self._order.append(frame)
        self._held[frame].append(item)

    def keyframe(self, frame: int) -> list[int]:
        """A keyframe was made at `frame`; the frames that became detail (to flush)."""
        n, self._n_keyframes = self._n_keyframes, self._n_keyframes + 1
        if self.opt.level == "default" and self.opt.keyframe_stride > 0 and n % self.opt.keyframe_stride == 0:
            return self._open_window(frame, frame + 1, f"keyframe {n} (1 in {self.opt.keyframe_stride})")
        return []

    def event(self, frame: int, why: str) -> list[int]:
        """Something a bug report is about happened at `frame`; the frames that became detail (to flush)."""
        self.events.append((frame, why))
        if self.opt.level != "default" or self.want(frame):
            return []
        if self.n_event_windows >= self.opt.max_event_windows or \
                self._per_kind.get(why, 0) >= self.opt.max_windows_per_kind:
            return []
        self.n_event_windows += 1
        self._per_kind[why] = self._per_kind.get(why, 0) + 1
        return self._open_window(frame - self.opt.before, frame + self.opt.after + 1, f"{why} at frame {frame}")

    def timing(self, frame: int, seconds: float) -> bool:
        """`frame` took `seconds` to arrive (since the last step's end): True when that makes it a slow frame."""
        # Against the mean, not the median: with features extracted ahead, frames between keyframes arrive in a
        # fraction of a keyframe's time (which waits for the back end), and 4x the median flagged ordinary keyframes
        slow = (len(self._intervals) >= self.opt.slow_min_frames
                and seconds > self.opt.slow_factor * statistics.fmean(self._intervals))
        self._intervals.append(seconds)
        return slow

    def take(self, frames: list[int]) -> list[tuple[int, Any]]:
        out = []
        for f in frames:
            out += [(f, item) for item in self._held.pop(f, [])]
        return out

    def end_frame(self, frame: int) -> None:
        """`frame` is done: forget held-back detail older than `before` frames."""
        while self._order and self._order[0] <= frame - self.opt.before:
            self._held.pop(self._order.popleft(), None)
        # a window stays known a while after it ends: the back end's results for its frames arrive late
        self._open = [(a, b) for a, b in self._open if b > frame - LATE_FRAMES]

    def _open_window(self, a: int, b: int, why: str) -> list[int]:
        self._open.append((a, b))
        self.windows.append((a, b, why))
        return sorted(f for f in self._held if a <= f < b)

    def detail_runs(self, written: set[int] | list[int]) -> list[tuple[int, int, str]]:
        """The frames that got detail (`written`: the recorder knows, the windows do not: a loop verified ten frames
        late opens a window whose frames were already dropped) as [a, b) runs of consecutive frames, each with the
        reasons of the windows that cover it."""
        frames = sorted(written)
        if self.everything:
            return [(frames[0], frames[-1] + 1, "every frame (--record full)")] if frames else []
        runs: list[tuple[int, int, str]] = []
        i = 0
        while i < len(frames):
            j = i
            while j + 1 < len(frames) and frames[j + 1] == frames[j] + 1:
                j += 1
            a, b = frames[i], frames[j] + 1
            why = list(dict.fromkeys(w for wa, wb, w in self.windows if wa < b and a < wb))
            runs.append((a, b, "; ".join(why) or "detail"))
            i = j + 1
        return runs


class Lazy:
    """Detail held back that is costly to make (the JPEG, Rerun's archetypes): made only if its frame is written."""

    def __init__(self, fn, *args, **kwargs):
        self.fn, self.args, self.kwargs = fn, args, kwargs

    def __call__(self):
        return self.fn(*self.args, **self.kwargs)


class WarningCapture(logging.Handler):
    """Collects the pipeline's warnings (from any thread); the recorder drains them from the tracking thread."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: deque[logging.LogRecord] = deque()

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)
