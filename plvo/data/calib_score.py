"""How well a lidar scan's projection fits its image: the figures and the picture of `plvo calib check`.

Two figures, each cheap and read off one frame:

- **in image**: the share of the scan points in front of the camera (z > 0.5 m) that project inside the image. It
  catches gross errors only (a transform inverted or given in the wrong direction, axes swapped, the wrong camera's
  matrix): then the points in front land mostly outside, or the share is far from what the lidar's and the camera's
  fields of view give (a 360-degree scan and KITTI's 80-degree camera: about a third).
- **edge alignment**: the mean image-edge strength at the scan's depth edges divided by its mean at all the scan's
  visible points. A depth edge is a point with a point at least 0.3 m (and 10 %) farther among its neighbours in
  the same few image rows: the near side of an object's outline (a pole, a car, a trunk). Seen by a correctly
  placed camera, an object's outline is an edge in the image too, so the depth edges land on image edges and the
  ratio is above 1 (1.07-1.67 on the KITTI frames below). With the camera turned by a few degrees (2 degrees are
  25 px at KITTI's focal length, several times the width of an edge) they land beside their edges, on surfaces as
  ordinary as the other points', and the ratio falls towards 1. The denominator takes the scene's texture out: all the
  points, depth edges or not, sample the same busy or plain image. The edge image is the grey image's gradient
  magnitude blurred by 2 px (a calibration good to a pixel or two counts as aligned) and divided by its local mean
  over 41 px, so that a faint outline in a dark region weighs as much as a strong one in a bright one.

How far the ratio rises with a good calibration depends on the scene, so the given calibration is also compared
with itself turned: the depth edges are projected through the transform rotated about each camera axis by up to 3
degrees (36 rotations), and the best of them is reported with its score over the given one's. A good calibration is
its own best or close to it; a turned one is beaten by the rotation that undoes it. The verdict: "looks off" when a
rotation of 1 degree or more scores 1.10x the given one or more, "may be off" from 1.06x, "no more than by chance"
when the ratio is under 1.05.

Measured on every 5th of frames 0-50 (11 frames each) of KITTI 04 (a highway with a few cars, trees and poles) and
raw drive 0009 (a street with shops, trees and parked cars), each with its true calibration and turned by 2 and 3
degrees about each camera axis either way (66 each):
- true: edge alignment 1.07-1.32 (04), 1.24-1.67 (0009); best rotation at most 1.05x (04), 1.09x (0009, by 0.5
  deg); all 22 "looks aligned".
- 2 degrees off: edge alignment 0.84-1.46, median 1.04 (04) and 1.09 (0009); 0009: 64 of 66 "looks off"; 04: 47
  "looks off", 7 "may be off", 4 "by chance", 8 "looks aligned".
- 3 degrees off: 0009: 65 "looks off", 1 "by chance"; 04: 45 "looks off", 6 "may be off", 5 "by chance", 10 "looks
  aligned".
So a street tells a 2-degree error from a single frame; on a plain highway frame about one error in seven passes as
aligned: check frames of different places (consecutive frames of one scene are no help: pooling 5 of them did not
do better).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from plvo.types import Calibration

MIN_DEPTH_M = 0.5
JUMP_M, JUMP_SHARE = 0.3, 0.1  # a depth edge: a neighbour this much farther (both)
NEIGHBOURS_PX = (9, 3)  # width, height of the neighbourhood: one beam's row and its own points mostly
EDGE_BLUR_PX = 2.0
LOCAL_MEAN_PX = 41
SEARCH_STEPS_DEG = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
MIN_EDGES = 50
# A rotation of at least this many degrees that scores this much more than the given calibration says it is off
# (a true one's best rotation of 1 degree or more scored at most 1.05x on KITTI 04 and raw 0009; one turned by 2
# degrees 1.14x (04) and 1.32x (0009) in the median: the module doc)
OFF_GAIN, OFF_DEG = 1.10, 1.0
MAYBE_GAIN = 1.06  # on a plain scene (a highway) a 2-degree error may gain only this much
AXES = "xyz"  # the camera's: x right (a turn about it moves the points up or down), y down, z forward


@dataclass(frozen=True)
class Projection:
    """The scan's visible points (the nearest in each pixel): pixel columns u, rows v, depth (m), depth edge or not."""

    u: np.ndarray
    v: np.ndarray
    depth: np.ndarray
    edge: np.ndarray


@dataclass(frozen=True)
class CalibScore:
    """The figures of one frame (see the module doc)."""

    n_points: int
    n_front: int
    n_image: int
    n_edges: int
    edge_alignment: float  # nan without depth edges
    peak_deg: tuple[float, float, float]  # the best rotation about the camera's x, y, z (zeros: the given one)
    peak_gain: float  # its edge score over the given one's (1: none better)

    @property
    def image_share(self) -> float:
        return self.n_image / self.n_front if self.n_front else 0.0

    @property
    def verdict(self) -> str:
        if self.n_edges < MIN_EDGES:
            return f"too few depth edges to judge ({self.n_edges} < {MIN_EDGES}): try another --frame"
        angle = max(abs(a) for a in self.peak_deg)
        if angle >= OFF_DEG and self.peak_gain >= OFF_GAIN:
            return f"looks off by about {angle:g} deg ({self.peak_text} fits the image better)"
        if self.edge_alignment < 1.05:
            return ("depth edges on image edges no more than by chance: off by more than 3 deg, or a scene with "
                    "too few outlines (try another --frame)")
        if angle >= OFF_DEG and self.peak_gain >= MAYBE_GAIN:
            return f"may be off by about {angle:g} deg ({self.peak_text} fits slightly better: try other frames)"
        return "looks aligned"

    @property
    def peak_text(self) -> str:
        turns = [f"{a:+g} deg about the camera's {axis}" for a, axis in zip(self.peak_deg, AXES) if a]
        return "turning it " + " and ".join(turns) if turns else "the given calibration"

    def line(self) -> str:
        best = ("none better (the given calibration scores highest)" if self.peak_gain <= 1.0
                else f"{self.peak_text}, {self.peak_gain:.2f}x")
        return (f"in image {100 * self.image_share:.0f}% of the {self.n_front} scan points in front of the camera; "
                f"edge alignment {self.edge_alignment:.2f} (1 = chance) at {self.n_edges} depth edges; best rotation "
                f"within 3 deg: {best}; {self.verdict}")


def _camera_points(scan: np.ndarray, T: np.ndarray) -> np.ndarray:
    p = np.asarray(scan[:, :3], dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def _pixels(pc: np.ndarray, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame points -> (u, v, inside: in front and in the image)."""
    z = pc[:, 2]
    front = z > MIN_DEPTH_M
    safe = np.where(front, z, 1.0)
    u = K[0, 0] * pc[:, 0] / safe + K[0, 2]
    v = K[1, 1] * pc[:, 1] / safe + K[1, 2]
    return u, v, front & (u >= 0) & (u < width) & (v >= 0) & (v < height)


def edge_image(gray: np.ndarray) -> np.ndarray:
    """(H,W) grey -> (H,W) float32 edge strength, blurred and divided by its local mean (see the module doc)."""
    g = cv2.GaussianBlur(np.asarray(gray, dtype=np.float32), (0, 0), 1.0)
    E = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    E = cv2.GaussianBlur(E, (0, 0), EDGE_BLUR_PX)
    return E / (cv2.blur(E, (LOCAL_MEAN_PX, LOCAL_MEAN_PX)) + 1.0)


def project_visible(scan: np.ndarray, calib: Calibration) -> tuple[Projection, int, int]:
    """(the visible points with their depth edges, points in front of the camera, points in the image)."""
    W, H = int(calib.width), int(calib.height)
    pc = _camera_points(scan, np.asarray(calib.T_cam_velo, dtype=np.float64))
    u, v, inside = _pixels(pc, np.asarray(calib.K, dtype=np.float64), W, H)
    n_front = int((pc[:, 2] > MIN_DEPTH_M).sum())
    ui, vi = u[inside].astype(np.int64), v[inside].astype(np.int64)
    z = pc[inside, 2].astype(np.float32)
    depth = np.full((H, W), np.inf, np.float32)
    order = np.argsort(-z)  # the nearest written last: it stays
    depth[vi[order], ui[order]] = z[order]
    visible = depth[vi, ui] == z
    ui, vi, z = ui[visible], vi[visible], z[visible]
    farthest = cv2.dilate(np.where(np.isfinite(depth), depth, 0.0).astype(np.float32),
                          cv2.getStructuringElement(cv2.MORPH_RECT, NEIGHBOURS_PX))[vi, ui]
    edge = (farthest - z) > np.maximum(JUMP_M, JUMP_SHARE * z)
    return Projection(ui, vi, z, edge), n_front, int(inside.sum())


def _rotation(axis: int, deg: float) -> np.ndarray:
    R = np.eye(4)
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _sum_at(E: np.ndarray, pc: np.ndarray, K: np.ndarray) -> tuple[float, int]:
    H, W = E.shape
    u, v, inside = _pixels(pc, K, W, H)
    return float(E[v[inside].astype(np.int64), u[inside].astype(np.int64)].sum()), int(inside.sum())


def score_frame(gray: np.ndarray, scan: np.ndarray, calib: Calibration) -> tuple[CalibScore, Projection]:
    """One frame's grey image (H,W), scan (N,3|4) and the calibration to judge -> (its figures, the projection)."""
    score, projections = score_frames([(gray, scan, calib)])
    return score, projections[0]


def score_frames(frames: list[tuple[np.ndarray, np.ndarray, Calibration]]) -> tuple[CalibScore, list[Projection]]:
    """Frames' (grey image, scan, calibration) -> the figures over all their points together, each frame's
    projection. Several frames of a plain scene judge better than one: their outlines add up."""
    projections, sums = [], np.zeros(4)  # scan points, in front, in the image, depth edges
    at_all, at_edges = [0.0, 0], [0.0, 0]
    turned: dict[tuple[int, float], list[float]] = {}
    for gray, scan, calib in frames:
        proj, n_front, n_image = project_visible(scan, calib)
        projections.append(proj)
        sums += (len(scan), n_front, n_image, int(proj.edge.sum()))
        if not proj.edge.any():
            continue
        E = edge_image(gray)
        K = np.asarray(calib.K, dtype=np.float64)
        at_all[0] += float(E[proj.v, proj.u].sum())
        at_all[1] += len(proj.u)
        eu, ev = proj.u[proj.edge], proj.v[proj.edge]
        at_edges[0] += float(E[ev, eu].sum())
        at_edges[1] += len(eu)
        # the depth edges' camera-frame points (found once, under the given calibration), turned with the camera
        dz = proj.depth[proj.edge].astype(np.float64)
        pc = np.stack([(eu + 0.5 - K[0, 2]) * dz / K[0, 0], (ev + 0.5 - K[1, 2]) * dz / K[1, 1], dz], axis=1)
        for axis in range(3):
            for deg in SEARCH_STEPS_DEG:
                for signed in (deg, -deg):
                    total, n = _sum_at(E, pc @ _rotation(axis, signed)[:3, :3].T, K)
                    acc = turned.setdefault((axis, signed), [0.0, 0])
                    acc[0] += total
                    acc[1] += n
    n_points, n_front, n_image, n_edges = (int(x) for x in sums)
    if at_edges[1] == 0 or at_all[0] <= 0:
        return CalibScore(n_points, n_front, n_image, n_edges, float("nan"), (0.0, 0.0, 0.0), 1.0), projections
    given = at_edges[0] / at_edges[1]
    best, peak = given, (0.0, 0.0, 0.0)
    for (axis, signed), (summed, count) in turned.items():
        if count and summed / count > best:
            best, peak = summed / count, (signed if axis == 0 else 0.0, signed if axis == 1 else 0.0,
                                          signed if axis == 2 else 0.0)
    alignment = given / (at_all[0] / at_all[1])
    return CalibScore(n_points, n_front, n_image, n_edges, alignment, peak, best / given), projections


def overlay(image: np.ndarray, proj: Projection, score: CalibScore, title: str) -> np.ndarray:
    """The image (grey or RGB) with the visible scan points coloured by depth (near red, far blue; depth edges
    ringed in white) and the figures written above it -> BGR image."""
    base = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    canvas = (0.6 * cv2.cvtColor(np.ascontiguousarray(base, dtype=np.uint8), cv2.COLOR_RGB2BGR)).astype(np.uint8)
    if len(proj.depth):
        near, far = 2.0, max(float(np.percentile(proj.depth, 95)), 4.0)
        # log depth: the colours spread over near and far alike (linear depth leaves the near scene one colour)
        t = 1.0 - np.log(np.clip(proj.depth, near, far) / near) / np.log(far / near)
        colours = cv2.applyColorMap((255 * t).astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)
        for x, y, c in zip(proj.u.tolist(), proj.v.tolist(), colours.tolist()):
            cv2.circle(canvas, (x, y), 1, c, -1)
        for x, y in zip(proj.u[proj.edge].tolist(), proj.v[proj.edge].tolist()):
            cv2.circle(canvas, (x, y), 3, (255, 255, 255), 1)
        legend = f"colour: depth, red {near:g} m .. blue {far:.0f} m+; white rings: depth edges"
    else:
        legend = "no scan point lands in the image"
    lines = [title, _wrap(score.line(), max(40, canvas.shape[1] // 8)), legend]
    rows = [part for text in lines for part in text.split("\n")]
    band = np.zeros((18 * len(rows) + 8, canvas.shape[1], 3), np.uint8)
    for k, text in enumerate(rows):
        cv2.putText(band, text, (6, 18 * k + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return np.vstack([band, canvas])


def _wrap(text: str, width: int) -> str:
    out, line = [], ""
    for part in text.split("; "):
        if line and len(line) + len(part) + 2 > width:
            out.append(line)
            line = part
        else:
            line = f"{line}; {part}" if line else part
    out.append(line)
    return "\n".join(out)
