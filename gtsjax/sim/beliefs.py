"""Simulated self-localisation: what each robot of a scenario *believed*, to grade (``gtsjax simulate
... --beliefs DIR``, ``gtsjax grade``).

A team's self-localisation is wrong in ways a grade must see through, and each is put in here with a
known size, so that a test can ask ``grade`` for it back:

* **a bias in the robot's own frame** (2–4 cm; a camera's mounting off by a little shows as the robot
  placing itself a little ahead or aside of where it stands, turning with it), a heading bias of 1–3°;
* **correlated noise** (an AR(1) process of 1.5–3 cm and 1–2°, 0.5–1.5 s correlation: a filter's
  estimate wanders, it does not jump every frame) and a little white noise (5 mm, 0.3°);
* **kidnaps**: about once a minute (a Poisson draw) the robot "falls" and relocalises 1 m off in a
  random direction, staying there for 2–6 s before it finds itself again (the truth does not fall:
  the scenario's path goes on, which is all the grade sees of a fall);
* **its own clock**: stamps on the robot's clock, ``offset`` (0.1–2 s, either sign) ahead of the
  laptop's, and 30 poses a second (:data:`RATE_HZ`) whatever the laser's rate;
* **the other team's frame** for one robot of two or more (``mirrored``): the field turned half a turn
  about its centre.

What was put in is written beside the poses (``put-in.json``: per robot the truth's index in the
log, the offset, the frame, the biases, the kidnaps), and :func:`put_in_error` gives the error at any
laptop time, the figure the grade's must agree with.
"""

import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..core.geometry import wrap
from ..grade.series import interpolate, invert, mirror_frame, transform

RATE_HZ = 30.0
KIDNAP_M = 1.0
KIDNAPS_PER_S = 1.0 / 60.0
# Truth samples further apart than this are a robot off the field (absent rows), not one to interpolate.
TRUTH_GAP_S = 0.5


@dataclass(frozen=True)
class Kidnap:
    start: float  # laptop clock, s
    duration: float  # s
    dx: float  # m, in the field
    dy: float


@dataclass(frozen=True)
class PutIn:
    """What the simulation put into one robot's beliefs."""

    name: str
    truth_index: int  # the robot's column in the log's truth_poses
    offset: float  # robot clock − laptop clock, s
    frame: str  # "field" or "mirrored"
    transform: tuple[float, float, float]  # from the robot's frame to the field's
    bias_body: tuple[float, float]  # m, in the robot's frame (ahead, left)
    heading_bias: float  # rad
    noise: tuple[float, float, float]  # AR(1) position σ (m), heading σ (rad), correlation time (s)
    kidnaps: tuple[Kidnap, ...]


def _ar1(rng, n: int, dt: float, sigma: float, tau: float, dims: int) -> np.ndarray:
    a = math.exp(-dt / tau)
    e = rng.normal(0.0, sigma * math.sqrt(1.0 - a * a), (n, dims))
    out = np.empty((n, dims))
    out[0] = rng.normal(0.0, sigma, dims)
    for k in range(1, n):
        out[k] = a * out[k - 1] + e[k]
    return out


def simulate_beliefs(stamps: np.ndarray, truth: np.ndarray, centre: tuple[float, float], seed: int = 0,
                     names: list[str] | None = None, mirrored: int | None = -1
                     ) -> list[tuple[PutIn, np.ndarray, np.ndarray]]:
    """Each robot's beliefs from the scenario's truth (``truth [T, M, 3]`` at laptop ``stamps``, NaN
    where a robot is absent): ``(put_in, robot_stamps, poses in its frame)`` per robot. ``mirrored``:
    the index of the robot in the other team's frame (``-1``: one drawn by the seed where there are
    two robots or more; ``None``: none)."""
    rng = np.random.default_rng([seed, 41])
    m_robots = truth.shape[1]
    names = names or [f"robot{m + 1}" for m in range(m_robots)]
    if mirrored == -1:  # a robot of the other team, where there are two robots or more
        mirrored = int(rng.integers(m_robots)) if m_robots >= 2 else None
    out = []
    for m in range(m_robots):
        present = np.all(np.isfinite(truth[:, m]), axis=1)
        if present.sum() < 2:
            continue
        ts, ps = stamps[present], truth[present, m]
        t = np.arange(ts[0], ts[-1], 1.0 / RATE_HZ)
        true_pose, ok = interpolate(t, ts, ps, TRUTH_GAP_S)
        t, true_pose = t[ok], true_pose[ok]
        n = t.size
        along = rng.uniform(0, 2 * math.pi)
        bias = rng.uniform(0.02, 0.04) * np.array([math.cos(along), math.sin(along)])
        head_bias = math.radians(rng.uniform(1.0, 3.0)) * rng.choice([-1.0, 1.0])
        sigma_p, sigma_h, tau = rng.uniform(0.015, 0.03), math.radians(rng.uniform(1.0, 2.0)), rng.uniform(0.5, 1.5)
        c, s = np.cos(true_pose[:, 2]), np.sin(true_pose[:, 2])
        err_xy = np.stack([c * bias[0] - s * bias[1], s * bias[0] + c * bias[1]], -1)
        err_xy += _ar1(rng, n, 1.0 / RATE_HZ, sigma_p, tau, 2) + rng.normal(0.0, 0.005, (n, 2))
        err_th = head_bias + _ar1(rng, n, 1.0 / RATE_HZ, sigma_h, tau, 1)[:, 0] + rng.normal(0, math.radians(0.3), n)
        kidnaps = []
        span = t[-1] - t[0]
        for _ in range(rng.poisson(KIDNAPS_PER_S * span) if span > 12.0 else 0):
            start = float(rng.uniform(t[0] + 5.0, t[-1] - 7.0))
            if any(abs(start - k.start) < 8.0 for k in kidnaps):
                continue
            d, a = float(rng.uniform(2.0, 6.0)), float(rng.uniform(0, 2 * math.pi))
            kidnaps.append(Kidnap(start, d, KIDNAP_M * math.cos(a), KIDNAP_M * math.sin(a)))
            during = (t >= start) & (t < start + d)
            err_xy[during] += [KIDNAP_M * math.cos(a), KIDNAP_M * math.sin(a)]
        belief = np.concatenate([true_pose[:, :2] + err_xy, wrap(true_pose[:, 2] + err_th)[:, None]], -1)
        frame = (0.0, 0.0, 0.0)
        kind = "field"
        if m == mirrored:
            kind, frame = "mirrored", mirror_frame(centre)
            belief = transform(belief, invert(frame))
        offset = float(rng.uniform(0.1, 2.0) * rng.choice([-1.0, 1.0]))
        put = PutIn(names[m], m, offset, kind, tuple(float(v) for v in frame), (float(bias[0]), float(bias[1])),
                    head_bias, (sigma_p, sigma_h, tau), tuple(sorted(kidnaps, key=lambda k: k.start)))
        out.append((put, t + offset, belief))
    return out


def write_beliefs(beliefs, folder: str | os.PathLike) -> list[Path]:
    """Each robot's poses as ``NAME.csv`` (``stamp,x,y,theta``, the form ``grade`` reads) and what was
    put in as ``put-in.json``; the paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for put, t, poses in beliefs:
        path = folder / f"{put.name}.csv"
        with open(path, "w") as f:
            f.write("stamp,x,y,theta\n")
            f.writelines(f"{float(s)!r},{x:.6f},{y:.6f},{th:.6f}\n" for s, (x, y, th) in zip(t, poses, strict=True))
        paths.append(path)
    with open(folder / "put-in.json", "w") as f:
        json.dump({"rate_hz": RATE_HZ, "robots": [asdict(put) for put, _, _ in beliefs]}, f, indent=1)
    return paths


def read_put_in(folder: str | os.PathLike) -> list[PutIn]:
    """``put-in.json`` read back."""
    data = json.loads((Path(folder) / "put-in.json").read_text())
    return [PutIn(**{**r, "transform": tuple(r["transform"]), "bias_body": tuple(r["bias_body"]),
                     "noise": tuple(r["noise"]), "kidnaps": tuple(Kidnap(**k) for k in r["kidnaps"])})
            for r in data["robots"]]


def put_in_error(put: PutIn, robot_stamps: np.ndarray, poses: np.ndarray, t: np.ndarray, stamps: np.ndarray,
                 truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The error put in at laptop times ``t``: the belief read at ``t + offset``, taken to the field by
    the true frame, minus the truth there (``stamps``, ``truth [T, M, 3]``); ``(position error [m],
    heading error [rad])``, NaN where either is missing."""
    belief, ok_b = interpolate(t + put.offset, robot_stamps, poses, 2.0 / RATE_HZ)
    belief = transform(belief, put.transform)
    col = truth[:, put.truth_index]
    present = np.all(np.isfinite(col), axis=1)
    true_pose, ok_t = interpolate(t, stamps[present], col[present], TRUTH_GAP_S)
    ok = ok_b & ok_t
    pos = np.where(ok, np.hypot(*(belief[:, :2] - true_pose[:, :2]).T), np.nan)
    head = np.where(ok, wrap(belief[:, 2] - true_pose[:, 2]), np.nan)
    return pos, head
