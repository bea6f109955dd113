"""The decompose stage's names and the product's defaults, in one place.

``keyshape select`` / ``decompose`` (``decompose/cli.py``), the in-memory layer
(:mod:`keyshape.decompose.api`, whose signatures use these), :mod:`keyshape.api`, ``keyshape batch``
(the manifest's defaults) and ``keyshape demo`` all take them from here, so a default changes in
one place. A leaf module (no imports), so that building the command line stays cheap.
"""
from __future__ import annotations

#: key-shape selectors (:func:`keyshape.decompose.selectors.make_selector`)
METHODS = ("spread", "kmeans2", "kmeans3", "hull2", "random", "greedy")
#: weight solvers (:func:`keyshape.decompose.weights.solve_weights`)
SOLVERS = ("nnls", "lstsq", "smooth")
#: how the head's motion is taken out of the shapes (:mod:`keyshape.decompose.stabilize`)
#: ``3d``: the head's 3D pose removed and the shapes brought to the front (:class:`keyshape.decompose.head3d.HeadPose3D`);
#: ``rigid``: the tracker's pose, then stabilised in 2D on the scheme's rigid points; ``tracker``: its pose alone
HEAD_POSES = ("3d", "rigid", "tracker")

METHOD = "greedy"            # key-shape selector (best in the project's measurements; spread is the paper's)
NEUTRAL_FRAME = "auto"       # weights relative to the actor's most relaxed frame (one for the whole face)
MIN_KEY_DISTANCE = 0.1       # near-duplicate keys dropped (fraction of the median key-to-neutral distance)
HEAD_POSE = "rigid"          # keys in the 2D head frame stabilised on the rigid points (docs/benchmarks.md: keys in
                             # the 3D head's frontalised frame measured worse on real footage); the 3D head is still
                             # what retarget and solve write (retarget/defaults.HEAD_MOTION)
SEED = 0                     # seed of kmeans/random/greedy
SOLVER = "smooth"            # NNLS + temporal smoothness
RIDGE = 0.03                 # Tikhonov shrinkage against tracking noise (docs/benchmarks.md, --ridge)
DEFAULT_FPS = 30.0           # when neither the tracks nor the weights give a frame rate
SMOOTH_LAMBDA = 0.1          # weight of the frame-to-frame change penalty of the smooth solver
