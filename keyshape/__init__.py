"""keyshape: a filmed facial performance to animation of an artist's own blendshapes.

One import namespace, built in floors (see ``docs/architecture.md``):

- :mod:`keyshape.base`: what every stage shares and that imports no stage: errors,
  atomic output files, progress, landmark schemes, geometry and drawing, and one
  module per file format (:mod:`keyshape.base.formats`).
- the stages, each importing only the base and earlier stages:
  :mod:`keyshape.tracker` (``tracker/``), :mod:`keyshape.decompose` (``decompose/``),
  :mod:`keyshape.retarget` (``retarget/``), :mod:`keyshape.data_synth` (``data_synth/``).
- the roof: :mod:`keyshape.cli` (the ``keyshape`` command) and :mod:`keyshape.demo`,
  the only modules that know every stage.
"""
__version__ = "0.1.0"

# The Python API (keyshape.api), loaded on first use so that importing keyshape.base does not
# import the stages (PEP 562). ``decompose`` and ``retarget`` are the stage packages of those
# names: their API functions are keyshape.api.decompose and keyshape.api.retarget.
_API = ("train", "track", "select", "Keys", "Weights", "Animation")


def __getattr__(name: str):
    if name in _API:
        from keyshape import api

        return getattr(api, name)
    raise AttributeError(f"module 'keyshape' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + list(_API))
