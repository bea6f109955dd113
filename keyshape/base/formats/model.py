"""Tracker model files (``.npz``): named arrays, parameters and the landmark scheme; reader and writer.

Design notes and figures: docs/formats.md, "Notes on the code", ``keyshape/base/formats/model.py``.
"""
from __future__ import annotations

import json
import tokenize
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keyshape.base.errors import InputError, require_file
from keyshape.base.files import atomic_path
from keyshape.base.schemes import Scheme, load_scheme, scheme_from_dict, scheme_to_dict

FORMAT = "keyshape-eigenpoints"
FORMAT_VERSION = 1


@dataclass
class ModelFile:
    """The content of a model file.

    Attributes
    ----------
    scheme : the landmark scheme the model was trained in
    params : constructor parameters of the model
    state : scalar learnt state (JSON numbers)
    arrays : name -> array
    path : the file read, for error messages (None when not read from a file)
    """

    scheme: Scheme
    params: dict
    state: dict
    arrays: dict
    path: Path | None = None


def write_model(path: str | Path, model: ModelFile) -> None:
    """Write a model file (.npz), atomically."""
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "scheme": scheme_to_dict(model.scheme),
            "params": dict(model.params), **model.state}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, meta=np.array(json.dumps(meta)), **model.arrays)


def _finite(text: str) -> float:
    v = float(text)
    if not np.isfinite(v):
        raise ValueError(f"number {text} out of range in the model header")
    return v


def _no_constant(name: str):
    raise ValueError(f"{name} in the model header")


def read_model(path: str | Path, scheme: str | Scheme | None = None) -> ModelFile:
    """Read a model file; raise :class:`InputError` naming it when it is not one or has another scheme
    than ``scheme`` (a name, JSON file or :class:`Scheme`; None accepts any)."""
    path = require_file(path, "model file")
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error, KeyError, NotImplementedError,
            MemoryError, OverflowError, SyntaxError, tokenize.TokenError, TypeError, RecursionError,
            AttributeError, IndexError) as exc:   # numpy parses each array's header with ast/tokenize
        raise InputError(f"not a keyshape model file (cannot read it as .npz: {exc})", path) from None
    try:
        meta = json.loads(str(data.pop("meta")), parse_constant=_no_constant, parse_float=_finite)
    except (KeyError, ValueError, RecursionError):
        raise InputError("not a keyshape model file (no format header)", path) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"not a keyshape model file (format {meta.get('format') if isinstance(meta, dict) else None!r})",
                         path)
    if meta.get("format_version") != FORMAT_VERSION:
        raise InputError(f"model format version {meta.get('format_version')} is not supported "
                         f"(this keyshape reads version {FORMAT_VERSION}); retrain with `keyshape train`", path)
    if not isinstance(meta.get("scheme"), dict) or not isinstance(meta.get("params"), dict):
        raise InputError("not a keyshape model file (no scheme or parameters in its header)", path)
    sch = scheme_from_dict(meta["scheme"], str(path))
    if scheme is not None:
        want = scheme if isinstance(scheme, Scheme) else load_scheme(scheme)
        if (want.name != sch.name or want.n_points != sch.n_points) and want.full() != sch:   # its nose too
            raise InputError(f"model was trained in scheme {sch.name!r} ({sch.n_points} points), "
                             f"not {want.name!r} ({want.n_points} points)", path)
    state = {k: v for k, v in meta.items() if k not in ("format", "format_version", "scheme", "params")}
    return ModelFile(sch, meta["params"], state, data, path)
