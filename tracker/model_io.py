"""Saving and loading eigen-points models (``.npz`` with a format name, version and scheme).

A model file holds the learnt arrays of :class:`~tracker.eigenpoints.AppearanceModel`,
its parameters, the scheme it was trained in (name and the scheme JSON itself,
so a user scheme file need not travel with it) and ``format``/``format_version``
so that other ``.npz`` files and future layouts are refused with a clear message.
"""
from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_path
from keyshape.tracker.eigenpoints import FORMAT, FORMAT_VERSION, AppearanceModel, RegionModel
from keyshape.base.schemes import Scheme, _validate, load_scheme

_PARAMS = ("n_components", "variance", "face_width", "margin", "n_morphs", "landmark_weight", "ridge", "regions", "split_mouth", "region_grow")


def _scheme_dict(s: Scheme) -> dict:
    return {"name": s.name, "n_points": s.n_points, "description": s.description,
            "contours": {k: {"points": list(v), "closed": s.closed[k]} for k, v in s.contours.items()},
            "regions": {k: list(v) for k, v in s.regions.items()}, "inter_ocular": list(s.inter_ocular)}


def save_model(path: str | Path, model: AppearanceModel) -> None:
    """Write ``model`` to ``path`` (.npz), atomically."""
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "scheme": _scheme_dict(model.scheme_),
            "params": {k: getattr(model, k) for k in _PARAMS}, "landmark_scale": model.landmark_scale_,
            "patch_size": model.patch_size_, "n_samples": model.n_samples_,
            "region_models": [{"name": r.name, "landmark_scale": r.landmark_scale}
                              for r in getattr(model, "region_models_", [])]}
    arrays = {k.rstrip("_"): getattr(model, k) for k in AppearanceModel._ARRAYS}
    for i, r in enumerate(getattr(model, "region_models_", [])):
        for k in RegionModel.ARRAYS:
            arrays[f"region{i}_{k}"] = getattr(r, k)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, meta=np.array(json.dumps(meta)), **arrays)


def load_model(path: str | Path, scheme: str | Scheme | None = None) -> AppearanceModel:
    """Read a model file; raise :class:`InputError` naming it when it is not one or has another scheme."""
    path = require_file(path, "model file")
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(f"not a keyshape model file (cannot read it as .npz: {exc})", path) from None
    try:
        meta = json.loads(str(data["meta"]))
    except (KeyError, json.JSONDecodeError):
        raise InputError("not a keyshape model file (no format header)", path) from None
    if meta.get("format") != FORMAT:
        raise InputError(f"not a keyshape model file (format {meta.get('format')!r})", path)
    if meta.get("format_version") != FORMAT_VERSION:
        raise InputError(f"model format version {meta.get('format_version')} is not supported "
                         f"(this keyshape reads version {FORMAT_VERSION}); retrain with `keyshape train`", path)
    sch = _validate(meta["scheme"], str(path))
    if scheme is not None:
        want = scheme if isinstance(scheme, Scheme) else load_scheme(scheme)
        if want.name != sch.name or want.n_points != sch.n_points:
            raise InputError(f"model was trained in scheme {sch.name!r} ({sch.n_points} points), "
                             f"not {want.name!r} ({want.n_points} points)", path)
    params = dict(meta["params"])
    params.setdefault("regions", False)     # models written before region models existed
    params.setdefault("split_mouth", False)
    model = AppearanceModel(sch, **params)
    try:
        for k in AppearanceModel._ARRAYS:
            setattr(model, k, np.asarray(data[k.rstrip("_")]))
        model.region_models_ = [
            RegionModel(r["name"], *(np.asarray(data[f"region{i}_{k}"]) for k in RegionModel.ARRAYS),
                        r["landmark_scale"]) for i, r in enumerate(meta.get("region_models", []))]
    except KeyError as exc:
        raise InputError(f"model file is missing array {exc}", path) from None
    model.mask_ = model.mask_.astype(bool)
    model.scheme_ = sch
    model.landmark_scale_ = float(meta["landmark_scale"])
    model.patch_size_ = int(meta["patch_size"])
    model.n_samples_ = int(meta["n_samples"])
    model.k_ = len(model.components_)
    model._index = np.flatnonzero(model.mask_.ravel())
    n_pix, n_pts = len(model._index), len(model.reference_)
    if (model.mask_.shape != (model.patch_size_,) * 2 or model.components_.shape[1] != n_pix + 2 * n_pts
            or model.mean_.shape != (n_pix + 2 * n_pts,) or n_pts != sch.n_points
            or not np.isfinite(model.components_).all()
            or any(r.index.max(initial=0) >= model.patch_size_ ** 2 or r.points.max(initial=0) >= n_pts
                   or r.components.shape[1] != len(r.index) + 2 * len(r.points) for r in model.region_models_)):
        raise InputError("model file is inconsistent (array shapes do not match each other or the scheme)", path)
    model._precompute()
    return model
