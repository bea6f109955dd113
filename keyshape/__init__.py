"""keyshape: a filmed facial performance to animation of an artist's own blendshapes.

Design notes and figures: docs/python.md, "Notes on the code", ``keyshape/__init__.py``.
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
