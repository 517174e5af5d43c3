"""LBD descriptors (opencv-contrib line_descriptor) of given segments, here the repaired LSD segments.

cv2.line_descriptor.BinaryDescriptor.compute takes KeyLine objects; built by hand they need (checked against the
opencv-contrib 5.0 sources and by experiment): class_id unique in 0..M-1 (it indexes the result), octave 0,
start/end points in the image and "in octave" (the same at octave 0), angle = atan2(ey - sy, ex - sx) in radians
(the band's orientation, so a segment's direction changes its descriptor), numOfPixels = the support region's
length in samples. The support region is numOfPixels x 63 px (9 bands of 7 px) centred on the midpoint.
BinaryDescriptor keeps per-image state (its Sobel images), so one instance per thread.
"""

from __future__ import annotations

import threading

import cv2
import numpy as np

from plvo.errors import PlvoError

_local = threading.local()


def _descriptor() -> cv2.line_descriptor.BinaryDescriptor:
    bd = getattr(_local, "bd", None)
    if bd is None:
        bd = cv2.line_descriptor.BinaryDescriptor.createBinaryDescriptor()
        _local.bd = bd
    return bd


def make_keylines(segments: np.ndarray, image_size: tuple[int, int]) -> list:
    """KeyLine objects of (M,4) segments in level-0 pixels; image_size (width, height) sets their response."""
    out = []
    scale = float(max(image_size))
    for i, (x1, y1, x2, y2) in enumerate(np.asarray(segments, dtype=np.float64).tolist()):
        kl = cv2.line_descriptor.KeyLine()
        kl.startPointX, kl.startPointY, kl.endPointX, kl.endPointY = x1, y1, x2, y2
        kl.sPointInOctaveX, kl.sPointInOctaveY, kl.ePointInOctaveX, kl.ePointInOctaveY = x1, y1, x2, y2
        length = float(np.hypot(x2 - x1, y2 - y1))
        kl.lineLength = length
        kl.angle = float(np.arctan2(y2 - y1, x2 - x1))
        kl.numOfPixels = max(int(round(length)), 1)
        kl.octave = 0
        kl.class_id = i
        kl.pt = ((x1 + x2) / 2.0, (y1 + y2) / 2.0)
        kl.response = length / scale
        kl.size = (x2 - x1) * (y2 - y1)
        out.append(kl)
    return out


def compute_lbd(image: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(M,32) uint8 binary LBD descriptors of (M,4) segments in a (H,W) uint8 image, row i for segment i."""
    if image.ndim != 2 or image.dtype != np.uint8:
        raise PlvoError(f"LBD: image must be (H,W) uint8, got shape {image.shape} dtype {image.dtype}")
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    if len(segments) == 0:
        return np.zeros((0, 32), np.uint8)
    keylines = make_keylines(segments, (image.shape[1], image.shape[0]))
    kls, desc = _descriptor().compute(image, keylines)
    if desc is None or len(kls) != len(segments):
        raise PlvoError(f"LBD: {len(segments)} segments in, {0 if desc is None else len(desc)} descriptors out")
    # rows follow the returned keylines; put them back in segment order
    ids = np.fromiter((k.class_id for k in kls), dtype=np.intp, count=len(kls))
    out = np.empty((len(segments), 32), np.uint8)
    out[ids] = desc
    return out
