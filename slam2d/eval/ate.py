"""Absolute trajectory error after SE(2) Umeyama alignment (Umeyama 1991), and
relative pose error over fixed travelled distances (as in evo's RPE with ``--delta_unit m``).

The ATE also reports the scale of the best similarity alignment (Umeyama's Sim(2) solution, as
evo's ``--correct_scale`` finds it) and the error left after it: a map shrunk or stretched as a
whole (scan matching that falls short of every step along a corridor, a wheel radius taken
wrong) shows as a scale away from 1, and the second figure says how much of the ATE that
explains. The SE(2) figure stays the one reported: a SLAM map has a scale of its own to get right."""
from __future__ import annotations

import numpy as np

from slam2d.geometry import between, wrap


def umeyama(est_xy: np.ndarray, ref_xy: np.ndarray, with_scale: bool = False):
    """(rotation angle, translation, scale) that map est onto ref (``ref ≈ scale · R est + t``) in
    the least-squares sense (Umeyama 1991); the scale is 1 unless ``with_scale``."""
    mu_e, mu_r = est_xy.mean(axis=0), ref_xy.mean(axis=0)
    e = est_xy - mu_e
    h = e.T @ (ref_xy - mu_r)
    u, sv, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, d]) @ u.T
    spread = float((e ** 2).sum())
    scale = float((sv[0] + d * sv[1]) / spread) if with_scale and spread > 0.0 else 1.0
    t = mu_r - scale * r @ mu_e
    return float(np.arctan2(r[1, 0], r[0, 0])), t, scale


def align(est: np.ndarray, ref: np.ndarray, with_scale: bool = False) -> np.ndarray:
    """``est`` moved (and, ``with_scale``, scaled) onto ``ref`` by ``umeyama``."""
    return _moved(est, *umeyama(est[:, :2], ref[:, :2], with_scale))


def _moved(est: np.ndarray, ang: float, t: np.ndarray, scale: float) -> np.ndarray:
    c, s = np.cos(ang), np.sin(ang)
    xy = scale * est[:, :2] @ np.array([[c, s], [-s, c]]) + t
    return np.column_stack([xy, wrap(est[:, 2] + ang)])


def _stats(v: np.ndarray) -> dict:
    return {"rmse": float(np.sqrt(np.mean(v ** 2))), "mean": float(v.mean()), "median": float(np.median(v)),
            "max": float(v.max()), "std": float(v.std())}


def ate(est: np.ndarray, ref: np.ndarray) -> dict:
    """Translation and rotation error after SE(2) alignment; ``scale``: the factor the similarity
    alignment multiplies ``est`` by (above 1: ``est`` is too small), ``sim2_trans_m``: the
    translation error left after that alignment (module docstring)."""
    aligned = align(est, ref)
    e = np.hypot(*(aligned[:, :2] - ref[:, :2]).T)
    rot = np.degrees(np.abs(wrap(aligned[:, 2] - ref[:, 2])))
    sim = umeyama(est[:, :2], ref[:, :2], with_scale=True)
    scale = sim[2]
    e_sim = np.hypot(*(_moved(est, *sim)[:, :2] - ref[:, :2]).T)
    return {"trans_m": _stats(e), "rot_deg": _stats(rot), "pairs": int(len(e)), "scale": scale,
            "sim2_trans_m": _stats(e_sim)}


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
