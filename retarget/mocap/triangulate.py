"""The planar-bone control surface: a triangulation of the markers over the face (001 section 4).

Design notes and figures: docs/mocap.md, "Notes on the code", ``retarget/mocap/triangulate.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import Delaunay

from keyshape.base.errors import InputError
from keyshape.retarget.mocap.planar_bones import triangle_min_angles


@dataclass
class CylinderFrame:
    """A cylinder around the head: axis through ``origin`` along ``up``; angle 0 at ``forward``."""

    origin: np.ndarray
    up: np.ndarray
    forward: np.ndarray
    radius: float

    @classmethod
    def around(cls, points, up=(0.0, 1.0, 0.0), forward=(0.0, 0.0, 1.0)) -> "CylinderFrame":
        """Fit to face points: the axis sits behind their centroid by their half-width."""
        p = np.asarray(points, dtype=np.float64)
        p = p[np.isfinite(p).all(axis=1)]
        up = np.asarray(up, float) / np.linalg.norm(up)
        fw = np.asarray(forward, float)
        fw = fw - up * (fw @ up)
        fw /= np.linalg.norm(fw)
        side = np.cross(up, fw)
        c = p.mean(axis=0)
        half = 0.5 * np.ptp(p @ side)
        origin = c - fw * half
        rel = p - origin
        radius = float(np.mean(np.linalg.norm(rel - np.outer(rel @ up, up), axis=1)))
        return cls(origin, up, fw, radius)

    def project(self, points) -> np.ndarray:
        """``(n, 2)``: (arc length around the axis, height along it)."""
        p = np.asarray(points, dtype=np.float64) - self.origin
        side = np.cross(self.up, self.forward)
        ang = np.arctan2(p @ side, p @ self.forward)
        return np.column_stack([self.radius * ang, p @ self.up])


def cylindrical_projection(points, up=(0.0, 1.0, 0.0), forward=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(n, 2) cylindrical coordinates of ``points`` in a cylinder fitted to them."""
    return CylinderFrame.around(points, up, forward).project(points)


@dataclass
class Triangulation:
    """Result of :func:`triangulate_markers`.

    Attributes
    ----------
    triangles : (n_bones, 3) int marker indices (counter-clockwise seen from outside)
    dropped : list of (corner labels, reason)
    """

    triangles: np.ndarray
    dropped: list = field(default_factory=list)

    def report(self) -> str:
        lines = [f"{len(self.triangles)} bones, {len(self.dropped)} triangle(s) dropped"]
        lines += [f"  dropped {'-'.join(c)}: {why}" for c, why in self.dropped]
        return "\n".join(lines)


def triangulate_markers(points, labels=None, up=(0.0, 1.0, 0.0), forward=(0.0, 0.0, 1.0),
                        min_angle_deg: float = 8.0, max_edge_ratio: float = 4.0, forbid=()) -> Triangulation:
    """Delaunay triangulation of markers in a cylindrical projection (the control surface).

    Parameters
    ----------
    points : (n_markers, 3) e.g. the retargeted neutral markers on the target
    labels : sequence of str, optional
    min_angle_deg : float
        Drop triangles whose smallest 3D angle is below this (slivers, collinear corners).
    max_edge_ratio : float
        Drop triangles with an edge longer than this times the median edge.
    forbid : sequence of (set_a, set_b) label sets
        Drop triangles that have corners in both sets.

    Raises
    ------
    InputError
        Fewer than 3 markers, NaN markers, or all markers collinear in the projection.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 3:
        raise InputError(f"points: expected (n_markers >= 3, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise InputError("points: NaN markers cannot be triangulated; rebuild them first")
    names = list(labels) if labels is not None else [str(i) for i in range(len(p))]
    uv = cylindrical_projection(p, up, forward)
    try:
        tri = Delaunay(uv).simplices.astype(np.intp)
    except Exception as exc:  # scipy's QhullError: all collinear / coincident
        raise InputError(f"markers cannot be triangulated in the cylindrical projection ({str(exc).splitlines()[0]})") from None
    # orient counter-clockwise in the projection (outward normals)
    a, b, c = uv[tri[:, 0]], uv[tri[:, 1]], uv[tri[:, 2]]
    cw = ((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]) < 0
    tri[cw] = tri[cw][:, [0, 2, 1]]
    keep = np.ones(len(tri), bool)
    dropped = []
    ang = np.rad2deg(triangle_min_angles(p[tri]))
    edges = np.linalg.norm(p[tri] - p[np.roll(tri, -1, axis=1)], axis=2)
    med = np.median(edges)
    sets = [(set(sa), set(sb)) for sa, sb in forbid]
    for k in range(len(tri)):
        corners = [names[i] for i in tri[k]]
        why = None
        if ang[k] < min_angle_deg:
            why = f"degenerate: smallest angle {ang[k]:.2g} deg < {min_angle_deg}"
        elif edges[k].max() > max_edge_ratio * med:
            why = f"edge {edges[k].max():.3g} > {max_edge_ratio} x median {med:.3g}"
        else:
            for sa, sb in sets:
                if any(n in sa for n in corners) and any(n in sb for n in corners):
                    why = "joins forbidden groups"
                    break
        if why:
            keep[k] = False
            dropped.append((corners, why))
    if not keep.any():
        raise InputError("every triangle of the marker triangulation is degenerate: markers nearly collinear?")
    return Triangulation(tri[keep], dropped)
