"""Ground-truth revisits of a keyframe trajectory: what loop detection should find (issue 9's precision/recall)."""

from __future__ import annotations

import numpy as np

from plvo.geometry import se3

REVISIT_M, REVISIT_DEG = 5.0, 30.0


def revisits(gt: np.ndarray, kf_frame: dict[int, int], gap: int, max_m: float = REVISIT_M,
             max_deg: float = REVISIT_DEG) -> dict[int, set[int]]:
    """(N,4,4) ground-truth poses by frame, keyframe id -> frame -> {keyframe id: ids of keyframes more than `gap`
    back that it revisits}: within max_m metres and max_deg degrees of it."""
    out: dict[int, set[int]] = {}
    for q, fq in kf_frame.items():
        for m, fm in kf_frame.items():
            if m < q - gap:
                dT = se3.inv(gt[fm]) @ gt[fq]
                if np.linalg.norm(dT[:3, 3]) < max_m and np.degrees(se3.rotation_angle(dT)) < max_deg:
                    out.setdefault(q, set()).add(m)
    return out
