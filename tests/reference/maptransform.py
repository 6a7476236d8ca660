"""Stage f: the affine map from the sensor frame S to the field O, ``p_O = μ_O + A (p_S − μ_S)``,
re-estimated every scan from the detected landmarks: each landmark of the site takes its mutually
nearest detection of its class within the gate (after mapping the detections with the previous
transform), then centred OLS (eq. 18) if at least three of them spread in 2-D."""

import math

import numpy as np


class MapTransform:
    """The transform and its update, from the site's landmarks and the model's gate and spread."""

    def __init__(self, landmark_xy, landmark_class, map_gate: float, map_min_spread: float):
        self.landmark_xy = np.asarray(landmark_xy, np.float64)
        self.landmark_class = np.asarray(landmark_class, int)
        self.map_gate, self.map_min_spread = map_gate, map_min_spread

    def reset(self, sensor_pose) -> None:
        """The site's rough sensor pose as the transform, resting on no landmarks yet."""
        x, y, th = sensor_pose
        self.A = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        self.mu_s = np.zeros(2)
        self.mu_o = np.array([x, y])
        self.supported = False  # no fit from landmarks yet: the gate allows for a guessed heading

    def to_o(self, xy_s):
        """Points ``[n, 2]`` from S to O (eq. 10)."""
        return self.mu_o + (xy_s - self.mu_s) @ self.A.T

    def to_s(self, xy_o):
        """One point from O back to S."""
        return self.mu_s + np.linalg.solve(self.A, np.asarray(xy_o, np.float64) - self.mu_o)

    @property
    def rotation(self) -> float:
        return math.atan2(self.A[1, 0], self.A[0, 0])

    def update(self, det_s, det_cls) -> bool:
        """Associate and fit; returns whether the transform was re-estimated (else it is kept)."""
        if len(det_s) == 0:
            return False
        det_o = self.to_o(det_s)
        d2 = np.sum((self.landmark_xy[:, None] - det_o[None]) ** 2, axis=-1)
        d2[self.landmark_class[:, None] != det_cls[None, :]] = np.inf
        best_det = d2.argmin(axis=1)
        best_map = d2.argmin(axis=0)
        # while the transform rests on no landmarks, the gate allows a guessed heading 0.06 rad off
        slack = 0.0 if self.supported else 0.06
        gate = self.map_gate + slack * np.linalg.norm(det_s[best_det], axis=1)
        hit = (best_map[best_det] == np.arange(len(self.landmark_xy))) & (d2.min(axis=1) <= gate**2)
        n = int(hit.sum())
        if n < 3:
            return False
        ps, po = det_s[best_det[hit]], self.landmark_xy[hit]
        mu_s, mu_o = ps.mean(0), po.mean(0)
        X, Y = ps - mu_s, po - mu_o
        XtX = X.T @ X
        if np.linalg.eigvalsh(XtX / n)[0] <= self.map_min_spread**2:
            return False
        self.A = np.linalg.solve(XtX, X.T @ Y).T
        self.mu_s, self.mu_o = mu_s, mu_o
        return True
