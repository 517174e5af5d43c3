"""Facade layouts: windows, doors, shop windows and sign boards painted on building walls.

One parameter row describes a wall (in its own metric coordinates: u along the wall from its left end, v up from
its foot). `shade_facade` evaluates the layout per ray hit (vectorised); `facade_rectangles` lists the same
rectangles for the ground-truth edge list, so both always agree.
"""

from __future__ import annotations

import numpy as np

# Columns of a facade parameter row.
(WIDTH, HEIGHT, GROUND_H, FLOOR_H, WIN_W, WIN_H, SILL, SPACING, U_OFF, N_COLS, N_FLOORS, SHOP, KEY, DOOR_COL,
 FRAME_ALB) = range(15)
N_PARAMS = 15
FRAME_W = 0.08  # window frame width (m)
DOOR_W, DOOR_H = 1.1, 2.2
SHOP_SILL, SIGN_LO, SIGN_HI = 0.4, 0.75, 0.2  # shop window from SHOP_SILL to ground_h - 0.9; sign band below top


def random_facade(
    rng: np.random.Generator, width: float, height: float, like: np.ndarray | None = None
) -> np.ndarray:
    """Draw a layout for a wall `width` x `height` metres (in the style of row `like`) -> (N_PARAMS,) row."""
    p = np.zeros(N_PARAMS)
    if like is not None:
        p[:] = like
        p[WIDTH], p[SHOP] = width, 0.0
        p = _fit_columns(p, rng)
        p[DOOR_COL] = -1  # side walls: no doors, no shops
        return p
    p[WIDTH], p[HEIGHT] = width, height
    p[GROUND_H] = rng.uniform(3.4, 4.2)
    p[FLOOR_H] = rng.uniform(2.9, 3.5)
    p[WIN_W] = rng.uniform(0.9, 1.6)
    p[WIN_H] = rng.uniform(1.3, 1.8)
    p[SILL] = rng.uniform(0.7, min(1.0, p[FLOOR_H] - p[WIN_H] - 0.3))
    p[SPACING] = p[WIN_W] + rng.uniform(1.0, 2.4)
    p[N_FLOORS] = max(int((height - p[GROUND_H] - 0.6) // p[FLOOR_H]), 0)
    p[SHOP] = float(rng.random() < 0.4)
    p[KEY] = rng.integers(0, 2**20)
    p[FRAME_ALB] = rng.choice([0.85, 0.25])
    return _fit_columns(p, rng)


def _fit_columns(p: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    width = p[WIDTH]
    n_cols = max(int((width - 1.0 - p[WIN_W]) // p[SPACING]) + 1, 0) if width > p[WIN_W] + 1.0 else 0
    p[N_COLS] = n_cols
    p[U_OFF] = 0.5 * (width - (n_cols - 1) * p[SPACING] - p[WIN_W]) if n_cols else 0.0
    p[DOOR_COL] = rng.integers(0, n_cols) if n_cols else -1
    return p


def _hash01(*ints: np.ndarray) -> np.ndarray:
    """Integer hash of equally shaped int arrays -> floats in [0, 1)."""
    h = np.zeros(np.broadcast(*ints).shape, np.uint64)
    for k, a in zip((0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D, 0x27D4EB2F), ints):
        h = (h ^ (np.asarray(a).astype(np.int64).astype(np.uint64) * np.uint64(k))) * np.uint64(0x165667B1)
        h ^= h >> np.uint64(15)
    return (h & np.uint64(0xFFFF)).astype(np.float32) / 65536.0


def _in_rect(u: np.ndarray, v: np.ndarray, u0: np.ndarray | float, v0: np.ndarray | float, u1: np.ndarray | float,
             v1: np.ndarray | float) -> np.ndarray:
    return (u >= u0) & (u < u1) & (v >= v0) & (v < v1)


def _framed(u: np.ndarray, v: np.ndarray, u0: np.ndarray | float, v0: np.ndarray | float, u1: np.ndarray | float,
            v1: np.ndarray | float, glass: np.ndarray, frame: np.ndarray | float) -> np.ndarray:
    """Albedo of a framed pane: frame border and a central mullion around the glass."""
    border = (u - u0 < FRAME_W) | (u1 - u < FRAME_W) | (v - v0 < FRAME_W) | (v1 - v < FRAME_W)
    mullion = np.abs(u - 0.5 * (u0 + u1)) < 0.5 * FRAME_W
    return np.where(border | mullion, frame, glass)


def shade_facade(p: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N_PARAMS,N) facade columns, (N,) wall coordinates (m) -> (N,) albedo override, NaN where plain wall."""
    out = np.full(u.shape, np.nan, np.float32)
    col = np.floor((u - p[U_OFF]) / p[SPACING])
    ground = v < p[GROUND_H]
    col_ok = (col >= 0) & (col < p[N_COLS])
    cu = u - p[U_OFF] - col * p[SPACING]
    # Upper floors: a grid of framed windows, each pane with its own reflection. Work on candidates only.
    k = np.flatnonzero(~ground & col_ok & (cu < p[WIN_W]))
    if len(k):
        q = np.take(p, k, axis=1)
        fv_all = v[k] - q[GROUND_H]
        floor = np.floor(fv_all / q[FLOOR_H])
        fv = fv_all - floor * q[FLOOR_H] - q[SILL]
        win = (floor < q[N_FLOORS]) & (fv >= 0) & (fv < q[WIN_H])
        k, q, fv, floor = k[win], q[:, win], fv[win], floor[win]
        glass = 0.08 + 0.22 * _hash01(q[KEY], col[k], floor) + 0.12 * fv / q[WIN_H]
        out[k] = _framed(cu[k], fv, 0.0, 0.0, q[WIN_W], q[WIN_H], glass, q[FRAME_ALB])
    g = np.flatnonzero(ground)
    if len(g):
        out[g] = _shade_ground(np.take(p, g, axis=1), u[g], v[g], col[g], cu[g], col_ok[g])
    return out


def _shade_ground(p: np.ndarray, u: np.ndarray, v: np.ndarray, col: np.ndarray, cu: np.ndarray, col_ok: np.ndarray
                  ) -> np.ndarray:
    """Ground floor: a door, then shop windows under a sign board, or plain windows."""
    out = np.full(u.shape, np.nan, np.float32)
    key = p[KEY]
    glass = 0.08 + 0.22 * _hash01(key, col, col)
    door_c = p[U_OFF] + p[DOOR_COL] * p[SPACING] + 0.5 * p[WIN_W]
    door = (p[DOOR_COL] >= 0) & (np.abs(u - door_c) < 0.5 * DOOR_W) & (v < DOOR_H)
    shop = (p[SHOP] > 0) & ~door
    su0 = p[U_OFF] + col * p[SPACING] - 0.5 * (p[SPACING] - p[WIN_W]) + 0.3
    su1 = su0 + p[SPACING] - 0.6
    top = p[GROUND_H] - 0.9
    shop_win = shop & col_ok & (col != p[DOOR_COL]) & _in_rect(u, v, su0, SHOP_SILL, su1, top)
    out[shop_win] = _framed(u, v, su0, SHOP_SILL, su1, top, 0.1 + 0.1 * glass, 0.3)[shop_win]
    b_u0, b_u1 = p[U_OFF] - 0.3, p[U_OFF] + (p[N_COLS] - 1) * p[SPACING] + p[WIN_W] + 0.3
    board = shop & (p[N_COLS] > 0) & _in_rect(u, v, b_u0, p[GROUND_H] - SIGN_LO, b_u1, p[GROUND_H] - SIGN_HI)
    # Letters: 3x5 glyph cells of 0.1 m, one random bit each, in 0.4 m wide letter slots.
    b = np.flatnonzero(board)
    lu, lv = (u[b] - b_u0[b]) / 0.1, (v[b] - p[GROUND_H][b] + SIGN_LO - 0.05) / 0.09
    slot, gx, gy = np.floor(lu / 4), np.floor(lu % 4), np.floor(lv)
    ink = (gx < 3) & (gy >= 0) & (gy < 5) & (_hash01(key[b], slot * 16 + gx, gy) < 0.55)
    out[b] = np.where(ink, 0.1, 0.9)
    plain = (p[SHOP] == 0) & ~door & col_ok & (col != p[DOOR_COL])
    gv = v - 1.0
    gwin = plain & (cu < p[WIN_W]) & (gv >= 0) & (gv < p[WIN_H])
    out[gwin] = _framed(cu, gv, 0.0, 0.0, p[WIN_W], p[WIN_H], glass, p[FRAME_ALB])[gwin]
    in_frame = door & ((np.abs(u - door_c) > 0.5 * DOOR_W - FRAME_W) | (v > DOOR_H - FRAME_W))
    out[door] = np.where(in_frame, p[FRAME_ALB], 0.12 + 0.05 * glass)[door]
    return out


def facade_rectangles(p: np.ndarray) -> np.ndarray:
    """One wall's (N_PARAMS,) row -> (R,4) rectangles u0, v0, u1, v1 (m) of window, door, shop and board outlines."""
    rects = []
    n_cols, n_floors = int(p[N_COLS]), int(p[N_FLOORS])
    for c in range(n_cols):
        u0 = p[U_OFF] + c * p[SPACING]
        for f in range(n_floors):
            v0 = p[GROUND_H] + f * p[FLOOR_H] + p[SILL]
            rects.append((u0, v0, u0 + p[WIN_W], v0 + p[WIN_H]))
        if c == int(p[DOOR_COL]):
            dc = u0 + 0.5 * p[WIN_W]
            rects.append((dc - 0.5 * DOOR_W, 0.0, dc + 0.5 * DOOR_W, DOOR_H))
        elif p[SHOP] > 0:
            su0 = u0 - 0.5 * (p[SPACING] - p[WIN_W]) + 0.3
            rects.append((su0, SHOP_SILL, su0 + p[SPACING] - 0.6, p[GROUND_H] - 0.9))
        else:
            rects.append((u0, 1.0, u0 + p[WIN_W], 1.0 + p[WIN_H]))
    if p[SHOP] > 0 and n_cols > 0:
        b1 = p[U_OFF] + (n_cols - 1) * p[SPACING] + p[WIN_W] + 0.3
        rects.append((p[U_OFF] - 0.3, p[GROUND_H] - SIGN_LO, b1, p[GROUND_H] - SIGN_HI))
    return np.array(rects, np.float64).reshape(-1, 4)
