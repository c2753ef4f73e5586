"""Deterministic 2D world and robot for tests and the bundled dataset.

A floor of 30 m × 20 m: a corridor ring around a block of rooms with doorways, some
clutter; the robot drives the ring twice with detours into two rooms (three loop
closures), a 360° LiDAR with range noise, dropouts (NaN) and no-returns beyond its range
(+inf, as ROS drivers report them), and wheel odometry whose scale and heading errors
make it drift. Everything comes from one seeded ``numpy.random.Generator``, so the same
seed writes the same bytes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam2d.geometry import between, compose, wrap
from slam2d.io.ros2_msgs import stamp_text
from slam2d.types import Scan


def _box(x0, y0, x1, y1):
    return [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]


def _wall_with_gaps(x0, y0, x1, y1, gaps):
    """A straight wall from (x0, y0) to (x1, y1) with gaps given as (start, end) distances along it."""
    length = math.hypot(x1 - x0, y1 - y0)
    ux, uy = (x1 - x0) / length, (y1 - y0) / length
    segs, s = [], 0.0
    for g0, g1 in sorted(gaps) + [(length, length)]:
        if g0 > s:
            segs.append((x0 + ux * s, y0 + uy * s, x0 + ux * g0, y0 + uy * g0))
        s = g1
    return segs


def floor_plan() -> np.ndarray:
    """Wall segments (S, 4) as x0, y0, x1, y1."""
    segs = _box(0, 0, 30, 20)
    segs += _wall_with_gaps(2.5, 2.5, 27.5, 2.5, [(3.5, 4.5), (13.5, 14.5)])     # block bottom, doors
    segs += _wall_with_gaps(2.5, 17.5, 27.5, 17.5, [(10.5, 11.5), (20.5, 21.5)])  # block top
    segs += _wall_with_gaps(2.5, 2.5, 2.5, 17.5, [(6.5, 7.5)])                     # block left
    segs += [(27.5, 2.5, 27.5, 17.5)]                                              # block right
    segs += _wall_with_gaps(10, 2.5, 10, 17.5, [(9.5, 10.5)])                      # room dividers
    segs += _wall_with_gaps(20, 2.5, 20, 17.5, [(3.5, 4.5)])
    segs += _wall_with_gaps(2.5, 10, 10, 10, [(2.5, 3.5)])
    segs += _wall_with_gaps(20, 11, 27.5, 11, [(4.0, 5.0)])
    for cx, cy, w in [(8, 0.35, 0.5), (15, 19.6, 0.6), (29.6, 9, 0.5), (0.4, 14, 0.5), (22, 0.4, 0.6),
                      (5, 7, 0.8), (14, 12, 1.0), (24, 6, 0.7), (17, 15, 0.6), (12.5, 5, 0.4), (25.5, 14.5, 0.9)]:
        segs += _box(cx - w / 2, cy - w / 2, cx + w / 2, cy + w / 2)
    return np.array(segs, dtype=float)


WAYPOINTS = [
    (1.25, 1.25), (28.75, 1.25), (28.75, 18.75), (1.25, 18.75), (1.25, 1.25),   # ring 1
    (6.5, 1.25), (6.5, 6.0), (4.5, 6.0), (6.5, 6.0), (6.5, 1.25),               # room A and back
    (28.75, 1.25), (28.75, 18.75), (13.5, 18.75), (13.5, 14.0), (13.5, 18.75),  # ring 2, room B
    (1.25, 18.75), (1.25, 1.25), (12.0, 1.25),                                  # close the ring again
]


@dataclass
class SimConfig:
    seed: int = 0
    rate_hz: float = 5.0
    speed: float = 0.8
    turn_rate: float = 1.0
    beams: int = 360
    fov_deg: float = 360.0  # below 360: the beams span this field of view, centred ahead, both ends included
    max_range: float = 12.0
    range_sigma: float = 0.015
    dropout_prob: float = 0.01
    odom_scale_error: float = 0.02
    odom_rot_scale_error: float = 0.03
    odom_trans_sigma: float = 0.01
    odom_rot_sigma: float = 0.005
    start_time: int = 1_700_000_000


def ground_truth_path(cfg: SimConfig) -> np.ndarray:
    """(N, 3) poses at the scan rate: drive each leg at constant speed, turn in place at corners."""
    dt = 1.0 / cfg.rate_hz
    poses = []
    x, y = WAYPOINTS[0]
    th = math.atan2(WAYPOINTS[1][1] - y, WAYPOINTS[1][0] - x)
    poses.append((x, y, th))
    for (x0, y0), (x1, y1) in zip(WAYPOINTS[:-1], WAYPOINTS[1:]):
        target = math.atan2(y1 - y0, x1 - x0)
        while abs(wrap(target - th)) > 1e-9:
            step = float(np.clip(wrap(target - th), -cfg.turn_rate * dt, cfg.turn_rate * dt))
            th = float(wrap(th + step))
            poses.append((x, y, th))
        length = math.hypot(x1 - x0, y1 - y0)
        n = max(1, int(round(length / (cfg.speed * dt))))
        for k in range(1, n + 1):
            a = k / n
            poses.append((x0 + a * (x1 - x0), y0 + a * (y1 - y0), th))
        x, y = x1, y1
    return np.array(poses)


def raycast(segs: np.ndarray, origin, angles: np.ndarray, max_range: float) -> np.ndarray:
    """Distance from origin along each angle to the nearest segment (inf beyond max_range)."""
    dx, dy = np.cos(angles)[:, None], np.sin(angles)[:, None]
    ax, ay = segs[:, 0][None, :] - origin[0], segs[:, 1][None, :] - origin[1]
    ex, ey = (segs[:, 2] - segs[:, 0])[None, :], (segs[:, 3] - segs[:, 1])[None, :]
    den = dx * ey - dy * ex
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ax * ey - ay * ex) / den
        u = (ax * dy - ay * dx) / den
    hit = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    t = np.where(hit, t, np.inf)
    d = t.min(axis=1)
    d[d > max_range] = np.inf
    return d


def simulate(cfg: SimConfig):
    """Yield `Scan` records with odometry and ground truth."""
    rng = np.random.default_rng(cfg.seed)
    segs = floor_plan()
    gt = ground_truth_path(cfg)
    if cfg.fov_deg >= 360.0:
        inc = 2 * math.pi / cfg.beams
        angles_rel = -math.pi + inc * np.arange(cfg.beams)
    else:
        fov = math.radians(cfg.fov_deg)
        inc = fov / (cfg.beams - 1)
        angles_rel = -0.5 * fov + inc * np.arange(cfg.beams)
    odom = gt[0].copy()
    for i, pose in enumerate(gt):
        if i > 0:
            d = between(gt[i - 1], pose)
            dist = math.hypot(d[0], d[1])
            noisy = np.array([
                d[0] * (1 + cfg.odom_scale_error) + rng.normal(0, cfg.odom_trans_sigma) * dist,
                d[1] + rng.normal(0, cfg.odom_trans_sigma) * dist,
                d[2] * (1 + cfg.odom_rot_scale_error) + rng.normal(0, cfg.odom_rot_sigma) * (dist + abs(d[2])),
            ])
            odom = compose(odom, noisy)
        r = raycast(segs, pose[:2], angles_rel + pose[2], cfg.max_range)
        finite = np.isfinite(r)
        r[finite] += rng.normal(0, cfg.range_sigma, size=int(finite.sum()))
        r = np.maximum(r, 0.05)
        r[r > cfg.max_range] = np.inf  # noise never pushes a reading past the sensor's range
        r[rng.random(cfg.beams) < cfg.dropout_prob] = np.nan
        ns = i * round(1e9 / cfg.rate_hz)
        sec, nsec = cfg.start_time + ns // 1_000_000_000, ns % 1_000_000_000
        r32 = r.astype(np.float32)
        yield Scan(
            timestamp=sec + nsec * 1e-9, timestamp_text=stamp_text(sec, nsec), ranges=r32,
            angle_min=float(angles_rel[0]), angle_increment=inc, range_min=0.05, range_max=cfg.max_range,
            valid=np.isfinite(r32), no_return=np.isposinf(r32), index=i, odom_pose=odom.copy(),
            ground_truth=pose.copy(),
        )


def write_simulation(path, cfg: SimConfig) -> int:
    """Write the simulated log as MCAP; returns the number of scans."""
    from slam2d.io.mcap import McapWriter

    n = 0
    with open(path, "wb") as f:
        w = McapWriter(f)
        for scan in simulate(cfg):
            w.write_scan(scan)
            n += 1
        w.finish()
    return n
