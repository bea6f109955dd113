"""The retarget stage's defaults, in one place.

``keyshape retarget`` / ``pose`` / ``solve`` / ``preview``, the in-memory layer (:mod:`keyshape.retarget.api`),
:mod:`keyshape.api`, ``keyshape batch``, ``keyshape live`` and ``keyshape demo`` all take them from here:
plain values, and :class:`SolveOptions`, the per-frame solve's options that each of them builds. A leaf
module (no stage imports), so that building the command line stays cheap. What each default measured is in
``docs/benchmarks.md``.
"""
from __future__ import annotations

from dataclasses import dataclass

from keyshape.decompose.defaults import DEFAULT_FPS  # noqa: F401  (a leaf module too)

FORM = "auto"                # delta with a neutral, else absolute
METRIC = "geodesic"          # distance of the region band
SPARSITY = 0.01              # keyshape pose: L1 weight of a pose fit
NUISANCE = "auto"            # keyshape pose: region motions fitted freely (retarget.rig.poses.auto_nuisance)
OPPOSED = -0.5               # keyshape pose: antagonist shapes never in one pose below this cosine
SYMMETRY = 0.03              # keyshape pose: left-right prior (keyshape solve's)
HEAD_MOTION = "3d"           # the head written beside the curves: the 3D head (yaw, pitch, roll, translation with depth)
GAZE = "angles"              # the pupils' gaze: the Live Link eye angles only ("shapes": also the rig's eyeLook*,
                             # which on ICT-FaceKit move the lids too)
GAZES = ("angles", "shapes", "none")


@dataclass(frozen=True)
class SolveOptions:
    """The per-frame solve's options (``keyshape solve``, :func:`keyshape.api.solve`, ``keyshape batch``,
    ``keyshape live``): each builds one from these defaults.

    Attributes
    ----------
    sparsity : L1 weight (dimensionless): larger gives fewer shapes per frame
    symmetry : weight of the left-right prior (mirrored ``_L``/``_R`` shapes kept alike unless the actor's
        sides differ)
    smooth : temporal smoothness (0: none)
    calibrate : each eye's lid motion scaled so the take's deepest closure closes the rig's eye, and the brow
        shapes so the brow ends rise as far as the actor's
    gaze : ``angles`` (the Live Link eye angles), ``shapes`` (also the rig's ``eyeLook*``, held fixed in the
        solve) or ``none``
    landmarks : the rig's landmark JSON (None: the shipped one for ICT-FaceKit rigs)
    reference_frame : the tracks' frame of the rest head pose (None: with the 3D head its most front-facing
        relaxed frame, with a 2D head the first)
    head_units : rig units per tracker model unit of the head translation (None: the rig's inter-ocular
        distance over the actor's)
    head : the head motion written: ``3d``, or the 2D motion of ``rigid``/``tracker``
    rest_offset, yaw_slide, yaw_stretch : corrections, always on in the product (the actor's rest solved with
        the curves; the mouth's sideways parallax and vertical stretch under head yaw taken out,
        :func:`~keyshape.retarget.rig.solve.yaw_slide`, :func:`~keyshape.retarget.rig.solve.yaw_stretch`); off only
        in tests that measure them
    pitch_parallax, gaze_lids : experiments, off (``bench/synth3d_accuracy.py``, ``bench/real_rig_fidelity.py``):
        the mouth's vertical parallax under pitch taken out (:func:`~keyshape.retarget.rig.solve.pitch_parallax`);
        the lids solved with the pupils and the rig's ``eyeLook*`` (:func:`~keyshape.retarget.rig.solve.gaze_in_eye_region`)
    """

    sparsity: float = 0.01
    symmetry: float = 0.03
    smooth: float = 0.0
    calibrate: bool = True
    gaze: str = GAZE
    landmarks: str | None = None
    reference_frame: int | None = None
    head_units: float | None = None
    head: str = HEAD_MOTION
    rest_offset: bool = True
    yaw_slide: bool = True
    yaw_stretch: bool = True
    pitch_parallax: bool = False
    gaze_lids: bool = False


@dataclass(frozen=True)
class RetargetOptions:
    """``keyshape retarget``'s options beyond its inputs (:func:`keyshape.api.retarget`, ``keyshape batch``).

    Attributes
    ----------
    form, band, metric : the blend (:class:`~keyshape.retarget.targets.retargeter.Retargeter`): ``delta`` with a neutral
        (``auto``: delta where a neutral is given or found, else the paper's literal ``absolute``), the region
        band's width in mesh units (None: 10% of the bounding-box diagonal) and distance
    gaze : with a rig and tracks, as :class:`SolveOptions`
    head, reference_frame, head_units : the head motion written with tracks, as :class:`SolveOptions` (``head_units``
        None: with a rig its inter-ocular distance over the actor's, else 1)
    landmarks : the rig's landmark JSON (None: the shipped one for ICT-FaceKit rigs)
    """

    form: str = FORM
    band: float | None = None
    metric: str = METRIC
    gaze: str = GAZE
    head: str = HEAD_MOTION
    reference_frame: int | None = None
    head_units: float | None = None
    landmarks: str | None = None
