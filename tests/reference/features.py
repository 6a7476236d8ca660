"""Stages b–c for each segment: its origin of reference system (ORS, the middle of its angular span
at the mean of its nearest and farthest range), its characteristic vector (width, the distance and
intensity profiles of eq. 11–12, depth, range) and the binary filters (points, width); and what the
shape envelopes read: ``(width, depth, n · r)`` and whether a nearer return occludes an end."""

import dataclasses
import math

import numpy as np

from .segment import segments


class FrontEnd:
    """Stages a–c from a model's ``FrontEndConfig`` and the GP columns it was trained on."""

    def __init__(self, fe, gp_columns: tuple[int, ...] = ()):
        self.K, self.L = fe.max_candidates, fe.window
        self.n_dist, self.n_intensity = fe.n_dist, fe.n_intensity
        self.fe = {
            f.name: float(np.asarray(getattr(fe, f.name)))
            for f in dataclasses.fields(fe)
            if f.name not in ("max_candidates", "window", "n_dist", "n_intensity")
        }
        self.cells_on_bbox = bool(self.fe["cells_on_bbox"])
        self.gp_columns = gp_columns

    def profile(self, n, ylo, yhi, y, q):
        """Eq. 11–12: Gaussian-weighted mean of the columns of ``q`` in each of ``n`` cells."""
        if self.cells_on_bbox:
            lo, hi = ylo, yhi
        else:
            lo, hi = -0.5 * self.fe["cell_span"], 0.5 * self.fe["cell_span"]
        cw = (hi - lo) / n
        c = lo + (np.arange(n) + 0.5) * cw
        sigma = max(self.fe["sigma_cells"] * cw, self.fe["sigma_min"])
        dist = (c[:, None] - y[None, :]) ** 2 / (2 * sigma * sigma)
        w = np.exp(-(dist - dist.min(axis=1, keepdims=True)))  # scaled per cell: no underflow
        return (w @ q) / w.sum(axis=1, keepdims=True)

    def candidates(self, ranges, intensities, valid, angles):
        """GP inputs, ORS origins and headings of the candidates that pass the filters, and what the
        shape envelopes read: ``(width, depth, n · r)``, whether occluded."""
        segs, r, x, y = segments(ranges, valid, angles, self.fe["break_distance"], self.fe["break_growth"], self.K)
        ok_beam = valid & np.isfinite(ranges) & (ranges > 0)
        inten = np.where(valid & np.isfinite(intensities), intensities, 0.0)
        vecs, origins, headings, shape, occluded = [], [], [], [], []
        for s, e in segs:
            n = e - s + 1
            if n > self.L or n < self.fe["min_points"]:
                continue
            sl = slice(s, e + 1)
            rr, px, py = r[sl], x[sl], y[sl]
            th = 0.5 * (angles[s] + angles[e])
            c, sn = math.cos(th), math.sin(th)
            u = c * px + sn * py
            v = c * py - sn * px
            r_j = 0.5 * (rr.min() + rr.max())
            xp = u - r_j
            ylo, yhi = v.min(), v.max()
            width = yhi - ylo
            if not (self.fe["width_min"] <= width <= self.fe["width_max"]):
                continue
            height = xp.max() - xp.min()
            if self.n_dist == self.n_intensity:
                both = self.profile(self.n_dist, ylo, yhi, v, np.stack([xp, inten[sl]], 1))
                d, i = both[:, 0], both[:, 1]
            else:
                d = self.profile(self.n_dist, ylo, yhi, v, xp[:, None])[:, 0]
                i = self.profile(self.n_intensity, ylo, yhi, v, inten[sl][:, None])[:, 0]
            vecs.append(np.concatenate([[width], d, i, [height, abs(r_j)]]))
            origins.append((r_j * c, r_j * sn))
            headings.append(th)
            shape.append((width, height, n * abs(r_j)))
            # a nearer return just beside either end: something stands in front of it there
            occluded.append(
                any(0 <= b < len(r) and ok_beam[b] and r[b] < r[end] for b, end in ((s - 1, s), (e + 1, e)))
            )
        d = 1 + self.n_dist + self.n_intensity + 2
        x = np.array(vecs).reshape(-1, d)
        if self.gp_columns:  # the inputs the model was trained on
            x = x[:, list(self.gp_columns)]
        origins = np.array(origins).reshape(-1, 2)
        return x, origins, np.array(headings), np.array(shape).reshape(-1, 3), np.array(occluded, bool)
