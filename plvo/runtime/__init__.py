"""The runtime: what runs the algorithm over a sequence, beside it, not part of it.

`system` (the System: one step a frame, the map's one owner), `run` (the loop shared by the library and plvo-viz),
`workers` (a stage inline, in a thread or in a worker process) and `worker_stages` (the back end's and loop
closer's jobs and results), `scheduler` (the frames at which results are applied), `prefetch` and `lookahead`
(frames read and their features extracted ahead), `frame_poses` (every frame's pose from its keyframe's current
one), `timing`. It imports the algorithm's packages (tracking, backend, loop, lidar, depth, features, data) and
nothing imports it from there.
"""
