"""Absolute trajectory error after SE(2) Umeyama alignment (Umeyama 1991, without scale), and
relative pose error over fixed travelled distances (as in evo's RPE with ``--delta_unit m``)."""
from __future__ import annotations

import numpy as np

from slam2d.geometry import between, wrap


def umeyama_se2(est_xy: np.ndarray, ref_xy: np.ndarray):
    """Rotation angle and translation that map est onto ref in the least-squares sense."""
    mu_e, mu_r = est_xy.mean(axis=0), ref_xy.mean(axis=0)
    h = (est_xy - mu_e).T @ (ref_xy - mu_r)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, d]) @ u.T
    t = mu_r - r @ mu_e
    return float(np.arctan2(r[1, 0], r[0, 0])), t


def align(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    ang, t = umeyama_se2(est[:, :2], ref[:, :2])
    c, s = np.cos(ang), np.sin(ang)
    xy = est[:, :2] @ np.array([[c, s], [-s, c]]) + t
    return np.column_stack([xy, wrap(est[:, 2] + ang)])


def _stats(v: np.ndarray) -> dict:
    return {"rmse": float(np.sqrt(np.mean(v ** 2))), "mean": float(v.mean()), "median": float(np.median(v)),
            "max": float(v.max()), "std": float(v.std())}


def ate(est: np.ndarray, ref: np.ndarray) -> dict:
    aligned = align(est, ref)
    e = np.hypot(*(aligned[:, :2] - ref[:, :2]).T)
    rot = np.degrees(np.abs(wrap(aligned[:, 2] - ref[:, 2])))
    return {"trans_m": _stats(e), "rot_deg": _stats(rot), "pairs": int(len(e))}


def rpe(est: np.ndarray, ref: np.ndarray, distances=(1.0, 5.0, 10.0)) -> dict:
    """Relative error between pose pairs that the reference travelled ``d`` metres apart."""
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref[:, :2], axis=0).T))])
    out = {}
    for d in distances:
        j = np.searchsorted(travelled, travelled + d)
        ok = j < len(ref)
        i, j = np.flatnonzero(ok), j[ok]
        if len(i) == 0:
            continue
        err = between(between(ref[i], ref[j]), between(est[i], est[j]))
        out[f"{d:g}m"] = {"trans_m": _stats(np.hypot(err[:, 0], err[:, 1])),
                          "rot_deg": _stats(np.degrees(np.abs(err[:, 2]))), "pairs": int(len(i))}
    return out
