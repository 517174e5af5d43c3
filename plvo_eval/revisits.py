"""Ground-truth revisits of a keyframe trajectory: what loop detection should find, and how well it did.

A revisit: a keyframe within REVISIT_M metres and REVISIT_DEG degrees (ground truth) of a keyframe more than `gap`
keyframes back. Precision: accepted loops joining a true revisit / accepted loops. Recall: revisit passages (runs of
consecutive revisiting keyframes) with at least one accepted true loop / passages; and revisiting keyframes within
the closer's cooldown after an accepted true loop / revisiting keyframes.

`loop_edge_errors` judges each accepted loop by what it asserts rather than by where its keyframes are: the
relative pose the loop edge gives against the ground truth's. A loop seen from the other direction (a street driven
back) joins keyframes facing apart, which the revisit test above, built for the bags of words' same-direction
views, does not count; its edge is right or wrong all the same. A loop is true when its edge is within
TRUE_LOOP_M and TRUE_LOOP_DEG of the truth: a revisit misjudged by more than that would pull the map apart.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

REVISIT_M, REVISIT_DEG = 5.0, 30.0
TRUE_LOOP_M, TRUE_LOOP_DEG = 1.0, 2.0


def revisits(gt: np.ndarray, kf_frame: dict[int, int], gap: int, max_m: float = REVISIT_M,
             max_deg: float = REVISIT_DEG) -> dict[int, set[int]]:
    """(N,4,4) ground-truth poses by frame, keyframe id -> frame -> {keyframe id: ids of keyframes more than `gap`
    back that it revisits}: within max_m metres and max_deg degrees of it."""
    ids = np.array(sorted(kf_frame), np.int64)
    if len(ids) == 0:
        return {}
    T = np.asarray(gt, float)[[kf_frame[int(k)] for k in ids]]
    pos, R = T[:, :3, 3], T[:, :3, :3]
    cos_max = np.cos(np.radians(max_deg))
    out: dict[int, set[int]] = {}
    for n, q in enumerate(ids):
        older = np.flatnonzero(ids < q - gap)
        if not len(older):
            continue
        near = older[np.linalg.norm(pos[older] - pos[n], axis=1) < max_m]
        if not len(near):
            continue
        # rotation angle of R_m^T R_q from its trace: cos = (tr - 1) / 2
        tr = np.einsum("kij,ij->k", R[near], R[n])
        near = near[(tr - 1.0) / 2.0 > cos_max]
        if len(near):
            out[int(q)] = set(ids[near].tolist())
    return out


def detection_stats(gt: np.ndarray, kf_frame: dict[int, int], accepted: list[tuple[int, int]], gap: int,
                    cooldown: int, edges: list[np.ndarray | None] | None = None) -> dict[str, int]:
    """Ground truth (N,4,4) by frame, keyframe id -> frame, accepted loops (query, match) -> counts for precision
    and recall (see the module doc). edges: the accepted loops' T_match_query (4,4) in the same order, where known;
    then a loop that joins no revisit (a street driven back the other way) still counts in n_true when its edge is
    true (`loop_edge_errors`); recall stays that of the revisits."""
    truth = revisits(gt, kf_frame, gap)
    true = [(q, m) for q, m in accepted if m in truth.get(q, set())]
    n_true = len(true)
    if edges is not None:
        n_true = sum(1 for (q, m), T in zip(accepted, edges, strict=True) if m in truth.get(q, set()) or (
            T is not None and any(e["true"] for e in loop_edge_errors(gt, kf_frame, [(m, q, T)]))))
    qs = sorted(truth)
    passages: list[list[int]] = [[q] for q in qs[:1]]
    for q in qs[1:]:
        (passages[-1].append(q) if q == passages[-1][-1] + 1 else passages.append([q]))
    found = {q for q, _ in true}
    covered = [q for q in qs if any(0 <= q - a <= cooldown for a in found)]
    return {"n_accepted": len(accepted), "n_true": n_true, "n_revisit_keyframes": len(qs),
            "n_passages": len(passages), "n_passages_found": sum(1 for p in passages if found & set(p)),
            "n_revisit_keyframes_covered": len(covered)}


def loop_edge_errors(gt: np.ndarray, kf_frame: dict[int, int], edges: Iterable[tuple[int, int, np.ndarray]]
                     ) -> list[dict[str, float | int | bool]]:
    """Ground-truth poses (N,4,4) of the tracked camera by row, keyframe id -> row, loop edges (match id, query id,
    T_match_query (4,4)) -> per edge: the keyframes, their true distance apart and heading difference, the edge's
    error against the truth (m, deg) and whether it is true (see the module doc)."""
    out: list[dict[str, float | int | bool]] = []
    for m, q, T in edges:
        if int(m) not in kf_frame or int(q) not in kf_frame:
            continue
        Gm, Gq = np.asarray(gt[kf_frame[int(m)]], float), np.asarray(gt[kf_frame[int(q)]], float)
        truth = np.linalg.inv(Gm) @ Gq
        E = np.linalg.inv(truth) @ np.asarray(T, float)
        t_err = float(np.linalg.norm(E[:3, 3]))
        r_err = float(np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))
        apart = float(np.degrees(np.arccos(np.clip((np.trace(truth[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))
        out.append({"match_keyframe": int(m), "query_keyframe": int(q), "true_distance_m": round(
            float(np.linalg.norm(truth[:3, 3])), 3), "heading_apart_deg": round(apart, 2),
            "edge_error_m": round(t_err, 4), "edge_error_deg": round(r_err, 4),
            "true": bool(t_err <= TRUE_LOOP_M and r_err <= TRUE_LOOP_DEG)})
    return out
