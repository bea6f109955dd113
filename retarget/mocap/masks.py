"""Discontinuity masks: which bones may move which vertices (001 sections 4.3 and 6.1).

Design notes and figures: docs/mocap.md, "Notes on the code", ``retarget/mocap/masks.py``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from keyshape.base.errors import InputError
from keyshape.base.formats.masks import Masks
from keyshape.retarget.mocap.triangulate import CylinderFrame

IMAGE_MARGIN = 0.25


@dataclass
class Region:
    """Vertices of one mask region and the marker labels its bones may use."""

    name: str
    vertices: np.ndarray
    markers: set


def allowed_matrix(regions, triangles, labels, n_vertices: int) -> np.ndarray:
    """(n_vertices, n_bones) bool: may bone ``j`` move vertex ``v``."""
    tri = np.asarray(triangles)
    allowed = np.ones((n_vertices, len(tri)), bool)
    lab = np.asarray(labels, dtype=object)
    for r in regions:
        ok = np.array([all(lab[i] in r.markers for i in t) for t in tri], bool)
        v = np.asarray(r.vertices, dtype=np.intp)
        if len(v) and (v.min() < 0 or v.max() >= n_vertices):
            raise InputError(f"mask region {r.name!r}: vertex indices outside [0, {n_vertices})")
        allowed[v] &= ok[None, :]
    return allowed


def image_coordinates(vertices, markers, up=(0.0, 1.0, 0.0), forward=(0.0, 0.0, 1.0), shape=(256, 256),
                      reference_markers=None):
    """(row, col) float pixel coordinates of ``vertices`` in the markers' cylindrical frame.

    With ``reference_markers`` (the same markers on the face the image was painted on), the
    vertices' projections are first carried into the reference face's projection by a 2D
    thin-plate spline through the markers (new projection -> reference projection), so a
    mask follows the features between the markers, not only their bounding box (001 6.1).
    """
    m3 = np.asarray(markers, dtype=np.float64)
    r3 = m3 if reference_markers is None else np.asarray(reference_markers, dtype=np.float64)
    ref_frame = CylinderFrame.around(r3, up, forward)
    m = ref_frame.project(r3)
    if reference_markers is None:
        uv = ref_frame.project(vertices)
    else:
        from scipy.interpolate import RBFInterpolator

        if r3.shape != m3.shape:
            raise InputError(f"reference_markers: expected shape {m3.shape}, got {r3.shape}")
        new_frame = CylinderFrame.around(m3, up, forward)
        warp = RBFInterpolator(new_frame.project(m3), m, kernel="thin_plate_spline", degree=1)
        uv = warp(new_frame.project(vertices))
    lo, hi = m.min(axis=0), m.max(axis=0)
    span = hi - lo
    lo, hi = lo - IMAGE_MARGIN * span, hi + IMAGE_MARGIN * span
    uv = (uv - lo) / (hi - lo)
    h, w = shape[:2]
    return (1.0 - uv[:, 1]) * (h - 1), uv[:, 0] * (w - 1)


def regions_from_image(image: np.ndarray, vertices, markers, values: dict, up=(0.0, 1.0, 0.0),
                       forward=(0.0, 0.0, 1.0), reference_markers=None) -> dict:
    """Vertex indices per region name from a label image (``values``: name -> pixel value).

    ``reference_markers``: the markers of the face the image was painted on (see
    :func:`image_coordinates`); without them the image frame is the markers' own extent.
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., 0]
    r, c = image_coordinates(vertices, markers, up, forward, img.shape, reference_markers)
    ri, ci = np.rint(r).astype(np.intp), np.rint(c).astype(np.intp)
    inside = (ri >= 0) & (ri < img.shape[0]) & (ci >= 0) & (ci < img.shape[1])
    pix = np.full(len(ri), -1)
    pix[inside] = img[ri[inside], ci[inside]]
    return {name: np.flatnonzero(pix == val) for name, val in values.items()}


def render_mask_image(vertices, markers, regions: dict, values: dict, shape=(256, 256), up=(0.0, 1.0, 0.0),
                      forward=(0.0, 0.0, 1.0), splat: int = 2) -> np.ndarray:
    """Paint region vertices of a reference mesh into a label image (section 6.1, the other direction)."""
    img = np.zeros(shape[:2], np.uint8)
    r, c = image_coordinates(vertices, markers, up, forward, shape)
    for name, idx in regions.items():
        ri, ci = np.rint(r[idx]).astype(int), np.rint(c[idx]).astype(int)
        for dr in range(-splat, splat + 1):
            for dc in range(-splat, splat + 1):
                rr, cc = np.clip(ri + dr, 0, shape[0] - 1), np.clip(ci + dc, 0, shape[1] - 1)
                img[rr, cc] = values[name]
    return img


def regions_from_masks(masks: Masks, labels, vertices=None, markers=None, mesh=None, up=(0.0, 1.0, 0.0),
                       forward=(0.0, 0.0, 1.0)) -> list:
    """The :class:`Region` objects of a masks file (:func:`keyshape.base.formats.masks.read_masks`).

    Parameters
    ----------
    masks : the file's content
    labels : all marker labels of the control surface (``exclude_markers`` is relative to them)
    vertices, markers : target mesh vertices and its (neutral) markers; needed for an image
    mesh : :class:`keyshape.base.formats.obj.Mesh`, needed for ``vertex_group``
    """
    path = masks.path
    regions = masks.regions
    labels = [str(s) for s in labels]
    image_regions = None
    if masks.image is not None:
        if vertices is None or markers is None:
            raise InputError("an image mask needs the target vertices and markers", path)
        ref = None
        if "image_markers" in masks.spec:                 # {label: [x, y, z]} on the painted face
            missing = [s for s in labels if s not in masks.spec["image_markers"]]
            if missing:
                raise InputError(f"image_markers lacks marker(s) {missing}", path)
            ref = np.array([masks.spec["image_markers"][s] for s in labels], dtype=np.float64)
        image_regions = regions_from_image(masks.image, vertices, markers,
                                           {masks.region_name(k): r["image_value"] for k, r in enumerate(regions)
                                            if "image_value" in r},
                                           up, forward, reference_markers=ref)
    out = []
    known = set(labels)
    for k, r in enumerate(regions):
        name = masks.region_name(k)
        if "vertices" in r:
            v = np.asarray(r["vertices"], dtype=np.intp)
        elif "vertex_group" in r:
            if mesh is None:
                raise InputError(f"region {name!r}: a vertex_group needs the target mesh", path)
            v = mesh.group_vertices(r["vertex_group"])
        else:
            v = image_regions[name]
        if "markers" in r:
            ms = set(map(str, r["markers"]))
        elif "exclude_markers" in r:
            ms = known - set(map(str, r["exclude_markers"]))
        else:
            raise InputError(f"region {name!r}: give 'markers' or 'exclude_markers'", path)
        unknown = (set(map(str, r.get("markers", r.get("exclude_markers", []))))) - known
        if unknown:
            raise InputError(f"region {name!r}: unknown marker label(s) {sorted(unknown)}", path)
        out.append(Region(name, v, ms))
    return out


def masks_from_regions(regions: list, image: str | None = None, image_values: dict | None = None) -> Masks:
    """Regions as a masks file (vertex lists, or image values when ``image`` is given), for
    :func:`keyshape.base.formats.masks.write_masks`."""
    items = []
    for r in regions:
        d = {"name": r.name, "markers": sorted(r.markers)}
        if image is not None and image_values and r.name in image_values:
            d["image_value"] = int(image_values[r.name])
        else:
            d["vertices"] = [int(i) for i in r.vertices]
        items.append(d)
    spec = {"regions": items}
    if image is not None:
        spec["image"] = str(image)
    return Masks(spec)
