"""Orchestration of keyshape's stages and the ``keyshape`` command line.

Only :mod:`pipeline.cli` and :mod:`pipeline.demo` know every stage. The small
modules :mod:`pipeline.errors`, :mod:`pipeline.files` and
:mod:`pipeline.progress` hold what every stage shares (the error hierarchy,
atomic output, progress reporting) and import no stage.
"""
