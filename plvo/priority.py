"""Thread priorities: work whose result is needed later yields the cores to work the tracker waits for.

In the deployed mode the tracker waits, when it makes a keyframe, for the back end's result of the keyframe before
(plvo.runtime.system): the back end is on the run's critical path. Frames read and their features extracted ahead
(plvo.runtime.prefetch, `System.prepare`, with the line thread they use) and the loop closer (whose results are applied
20 frames later) run at LOOKAHEAD_NICENESS, so that on two cores they take what the back end and the tracker leave.
Measured on KITTI 04 (6 runs each way, alternating, KISS-ICP after each): 0.75 -> 0.82 of KISS-ICP's frames a second
(medians). With the back-end lag of 6 frames (`backend.max_lag_frames`) the tracker rarely waits for the back
end, but for the features of the frames read ahead; the look-ahead at nice 0 was no faster (plvo-viz on 04, 5
alternating runs each: 10.3 against 10.8 frames a second at nice 10). In the deployed mode the features are
extracted in a process of their own (plvo.features.worker), also at LOOKAHEAD_NICENESS: at nice 0 it was no faster
either (`plvo bench`, 9 runs each way: 0.94 of KISS-ICP's rate both).
"""

from __future__ import annotations

import logging
import os
import sys
import threading

log = logging.getLogger(__name__)

LOOKAHEAD_NICENESS = 10


def lower_priority(niceness: int) -> None:
    """Run the calling thread at a nice value of at least `niceness` (Linux, where each thread has its own; other
    systems would lower the whole process, so nothing there). Lowering a priority needs no privilege; threads made
    afterwards by this one inherit it."""
    if niceness <= 0 or not sys.platform.startswith("linux"):
        return
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, max(os.getpriority(os.PRIO_PROCESS, tid), niceness))
    except OSError as exc:  # e.g. a sandbox without the syscall: only the frames a second change
        log.debug("could not lower the priority of thread %d: %s", tid, exc)
